"""The companion engine's step, pure: typed inputs and a fake clock in, corrections and targets out
(no sockets, no sleeps); one engine or a group's engines on an in-process bus against the step in
one process, the receivers' common GNSS error, polling only when needed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.corrections import compute_corrections
from companion.engine import Command, CommandOut, CompanionEngine, CorrectionOut, TargetOut
from companion.estimation.neighbour import NeighbourMeasurement, NeighbourView, marker_in_camera, mount_covariance
from companion.fleetnet.group import GroupLink
from companion.fleetnet.hub import LocalHub
from companion.fleetnet.leader import GlobalStepNode
from companion.estimation.so3 import rotmat_to_quat
from companion.fleetnet import codec
from companion.messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, LinkState, NeighbourPose

from ..chains import perturbed_chain
from ..engine_cases import feed, fly_group_engines, group_engines, of, setup_for, straight_state


def test_step_on_flight_controller_time_sends_corrections_targets_and_arm():
    engine = CompanionEngine(setup_for())
    out = feed(engine, 0.0, 1.0, dx=(0.0, 0.2, 0.0))
    corr = of(CorrectionOut, out)
    assert [c.row for c in corr] == [0, 1, 2] and corr[0].correction.ekf_time_s == 0.0
    assert corr[1].correction.dp_w_m[0] < -0.05  # link 2 moved back towards the chain
    assert corr[0].correction.dp_w_m[0] > 0.0 and corr[2].correction.dp_w_m[0] > 0.0
    assert corr[1].corrected.p_w_m[0] == pytest.approx(0.2 + corr[1].correction.dp_w_m[0])
    targets = of(TargetOut, out)
    assert [t.system_id for t in targets] == [1, 2, 3] and targets[0].time_us == 0
    # anchored at the chain's middle in the first step's estimate: the middle link's target is at
    # its corrected estimate
    np.testing.assert_allclose(targets[1].target.p_w_m, corr[1].corrected.p_w_m, atol=1e-9)
    assert [c.row for c in of(CommandOut, out) if c.command is Command.ARM] == [0, 1, 2]
    # 20 Hz on flight-controller time: nothing at 0.02 s and 0.04 s, the step at 0.06 s once
    # every link has reported for it
    assert not of(CorrectionOut, feed(engine, 0.02, 1.02)) and not of(CorrectionOut, feed(engine, 0.04, 1.04))
    engine.on_state(0, straight_state(0, 3, 0.06), STATE_FLAG_EKF_OK, 1.06)
    assert not of(CorrectionOut, engine.poll(1.06))
    for i in (1, 2):
        engine.on_state(i, straight_state(i, 3, 0.06), STATE_FLAG_EKF_OK | STATE_FLAG_ARMED, 1.061)
    nxt = of(CorrectionOut, engine.poll(1.061))
    assert len(nxt) == 3 and nxt[0].correction.ekf_time_s == pytest.approx(0.06)
    assert nxt[0].correction.seq == corr[0].correction.seq + 1
    assert len(engine.log["t_sckf"]) == 2


@pytest.mark.parametrize("home, anchor, bias, expected_shift", [
    ("estimate", (0.0, 0.0, 2.0), (0.3, -0.2, 1.5), (0.3, -0.2, 1.5)),  # flown from the estimated start
    ("estimate", (0.0, 0.0, 2.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    ("anchor", (0.0, 0.0, 2.0), (0.3, -0.2, 1.5), (0.0, 0.0, 0.0)),  # flown at the anchor as given
])
def test_a_centralised_companion_flies_the_trajectory_from_its_estimated_start(home, anchor, bias, expected_shift):
    """Links that all report a shared offset from where the chain was set down (``anchor``): with
    ``home = "estimate"`` every target, from the first on, is the trajectory's shifted by it, so the
    chain holds where it believes it rests and climbs the take-off's height from there."""
    setup = setup_for()
    setup = replace(setup, trajectory=replace(setup.trajectory, home=home))
    engine = CompanionEngine(setup, start_center=anchor)
    reference = CompanionEngine(setup_for(), start_center=(0.0, 0.0, 2.0))  # the trajectory as written

    def states(t):
        return [replace(straight_state(i, 3, t), p_w_m=straight_state(i, 3, t).p_w_m + np.asarray(bias))
                for i in range(3)]

    for k in range(0, 200):  # 4 s at 50 Hz: holding the start, then the take-off's first seconds
        t = 0.02 * k
        for i, state in enumerate(states(t)):
            engine.on_state(i, state, STATE_FLAG_EKF_OK, t)
            reference.on_state(i, straight_state(i, 3, t), STATE_FLAG_EKF_OK, t)
        got, want = of(TargetOut, engine.poll(t)), of(TargetOut, reference.poll(t))
        assert len(got) == len(want) and (k or len(got) == 3)  # from the first poll on
        for g, w in zip(got, want):
            assert g.time_us == w.time_us
            np.testing.assert_allclose(g.target.p_w_m, w.target.p_w_m + np.asarray(expected_shift), atol=1e-9)
            np.testing.assert_allclose(g.target.q_wxyz, w.target.q_wxyz, atol=1e-12)
    np.testing.assert_allclose(engine.targets.home_offset_w_m, expected_shift, atol=1e-9)
    assert engine.targets.trajectory.targets(3.0)[1].p_w_m[2] > 2.0 + 1e-3  # climbing at 3 s


@pytest.mark.parametrize("distributed", [False, True])
def test_the_home_follows_the_settling_estimate_while_the_chain_rests_then_is_kept(distributed):
    """The links' shared error drifts while the chain rests (an estimate settling after its
    start): the home is measured again until 0.2 s before the take-off starts (1 s), then kept;
    every target is the trajectory's shifted by the home of its time, in every group alike once
    kept."""
    groups = ((1, 2), (3, 4, 5)) if distributed else ()
    setup = setup_for(5, groups=groups, distributed=distributed)
    clock = [0.0]
    engines = (group_engines(setup, lambda: clock[0])[1] if distributed
               else [CompanionEngine(setup, start_center=(0.0, 0.0, 2.0))])

    def bias(t):
        return np.array([0.0, 0.0, 0.3 - 0.1 * min(t, 2.0)])

    homes = {}
    for k in range(100):  # 2 s at 50 Hz
        t = clock[0] = 0.02 * k
        for e in engines:
            for lk in e.links:
                state = straight_state(lk.index, 5, t)
                e.on_state(lk.row, replace(state, p_w_m=state.p_w_m + bias(t)), STATE_FLAG_EKF_OK, t)
        for _ in range(6):
            for e in engines:
                for out in of(TargetOut, e.poll(t)):
                    unshifted = e.targets.trajectory.targets(out.time_us * 1e-6)[e.links[out.row].index].p_w_m
                    homes.setdefault(round(out.time_us * 1e-6, 3), set()).add(tuple(out.target.p_w_m - unshifted))
    for t, seen in homes.items():  # one home per target time in every group; while it rests, a group
        # takes the measuring group's newest at its next poll (within two steps of the estimate's drift)
        assert len(seen) == 1 or (t < 1.0 and np.ptp([h[2] for h in seen]) <= 0.1 * 0.1 + 1e-9), (t, seen)
    z = {t: max(h[2] for h in seen) for t, seen in homes.items()}
    assert z[min(z)] == pytest.approx(0.3, abs=0.011)  # from the first targets (the first step's)
    final = z[max(z)]
    assert 0.3 - 0.1 * 0.8 - 1e-9 <= final <= 0.3 - 0.1 * 0.65 + 1e-9  # the last measurement before 0.8 s
    assert all(v == pytest.approx(final, abs=1e-12) for t, v in z.items() if t >= 1.0)  # kept from the take-off
    assert len({round(v, 9) for v in z.values()}) > 5  # (it followed the estimate before)


@pytest.mark.parametrize("home, expected", [("estimate", (0.3, -0.2, 1.5)), ("anchor", (0.0, 0.0, 0.0))])
def test_distributed_companions_fly_from_the_home_the_middle_group_measures(home, expected):
    """Links that all report a shared offset from where the chain was set down: the group that
    holds the middle link measures the home from its first step and publishes it, and every group
    flies the trajectory shifted by that one offset, from its first targets on (``home =
    "estimate"``); with ``home = "anchor"`` every group flies the shared anchor as given."""
    setup = setup_for(5, groups=((1, 2), (3, 4, 5)), distributed=True)
    setup = replace(setup, trajectory=replace(setup.trajectory, home=home))
    clock = [0.0]
    _, engines = group_engines(setup, lambda: clock[0])
    bias = np.array([0.3, -0.2, 1.5])
    first = {}
    for k in range(6):
        t = clock[0] = 0.05 * k
        for e in engines:
            for lk in e.links:
                state = straight_state(lk.index, 5, t)
                e.on_state(lk.row, replace(state, p_w_m=state.p_w_m + bias), STATE_FLAG_EKF_OK, t)
        for _ in range(6):
            for e in engines:
                for out in of(TargetOut, e.poll(t)):
                    i = e.links[out.row].index
                    first.setdefault(i, k)
                    unshifted = e.targets.trajectory.targets(out.time_us * 1e-6)[i].p_w_m
                    np.testing.assert_allclose(out.target.p_w_m - unshifted, expected, atol=1e-9)
    assert sorted(first) == [0, 1, 2, 3, 4] and max(first.values()) <= 1  # within the first cycle
    for e in engines:
        np.testing.assert_allclose(e.targets.home_offset_w_m, expected, atol=1e-9)
        np.testing.assert_allclose(e.targets.trajectory.targets(0.0)[2].p_w_m, [0.0, 0.0, 2.0], atol=1e-9)
    if home == "estimate":
        assert [e.targets.home.source for e in engines] == ["group 2", "measured"]
        assert engines[1].summary()["home"]["published"] >= 1 and engines[0].summary()["home"]["received"] >= 1
    else:
        assert all(e.targets.home is None for e in engines)


def test_disabled_companion_logs_the_ekf_states_and_corrects_nothing():
    engine = CompanionEngine(setup_for(enabled=False))
    out = feed(engine, 0.0, 0.0, dx=(0.0, 0.2, 0.0))
    assert not of(CorrectionOut, out) and of(TargetOut, out)
    assert engine.log["p_ekf_sckf"][0][1, 0] == pytest.approx(0.2) and not engine.log["global_applied"][0]


@pytest.mark.parametrize("n, groups", [(3, ()), (5, ((1, 2), (3, 4, 5))), (7, ((1, 2), (3, 4, 5), (6, 7)))])
def test_one_engine_equals_the_in_process_step(n, groups):
    rng = np.random.default_rng(n)
    p, v, q, w, d, P = perturbed_chain(rng, n)
    setup = setup_for(n, groups)
    setup = replace(setup, skeleton=replace(setup.skeleton, link_length_m=2 * d[0, 0]))
    states = [LinkState(i, 0.0, p[i], v[i], q[i], w[i], P[i]) for i in range(n)]
    engine = CompanionEngine(setup)
    for i, st in enumerate(states):
        engine.on_state(i, st, STATE_FLAG_EKF_OK, 0.0)
    got = of(CorrectionOut, engine.poll(0.0))
    _, want = compute_corrections(states, setup.skeleton.d_b_m, setup.companion.group_layout(n), setup.companion.params)
    for g, c in zip(got, want):
        np.testing.assert_allclose(g.correction.dp_w_m, c.dp_w_m, atol=1e-12)
        np.testing.assert_allclose(g.correction.dtheta_w_rad, c.dtheta_w_rad, atol=1e-12)


def test_neighbour_measurements_reach_the_next_step_and_are_counted():
    """A camera measurement between links 2 and 3 given to the engine goes into its next step as
    compute_corrections takes it, with its age at the step; one captured too long before the
    step, and one on a row the engine does not have, are dropped and counted; each is used once."""
    n = 4
    rng = np.random.default_rng(40)
    p, v, q, w, d, P = perturbed_chain(rng, n)
    setup = setup_for(n)
    setup = replace(setup, skeleton=replace(setup.skeleton, link_length_m=2 * d[0, 0]))
    states = [LinkState(i, 1.0, p[i], v[i], q[i], w[i], P[i]) for i in range(n)]
    view = NeighbourView(np.array([0.45, 0.0, 0.05]), np.eye(3), np.array([0.0, 0.0, 0.08]), np.eye(3))
    R_cm, t_cm = marker_in_camera(p[1], q[1], p[2], q[2], view)
    m = NeighbourMeasurement(1, 2, R_cm, t_cm + [0.05, 0.0, 0.02], np.eye(6) * 1e-3, view)
    engine = CompanionEngine(setup)
    engine.on_neighbour(0.95, m)
    engine.on_neighbour(0.5, m)  # captured 0.5 s before the step
    engine.on_neighbour(0.95, replace(m, observed=4))  # no such row
    for i, st in enumerate(states):
        engine.on_state(i, st, STATE_FLAG_EKF_OK, 1.0)
    got = of(CorrectionOut, engine.poll(1.0))
    # (the engine adds the mounts' calibration error to the PnP's covariance)
    mounts = mount_covariance(m.t_cm_m, setup.companion.neighbour_mount_std_m,
                              np.radians(setup.companion.neighbour_mount_std_deg))
    _, want = compute_corrections(states, setup.skeleton.d_b_m, setup.companion.group_layout(n),
                                  setup.companion.params, neighbours=[replace(m, age_s=0.05, cov=m.cov + mounts)])
    _, plain = compute_corrections(states, setup.skeleton.d_b_m, setup.companion.group_layout(n), setup.companion.params)
    for g, c in zip(got, want):
        np.testing.assert_allclose(g.correction.dp_w_m, c.dp_w_m, atol=1e-12)
    assert not np.allclose(want[1].dp_w_m, plain[1].dp_w_m, atol=1e-4)
    assert engine.summary()["neighbour_measurements"] == {"received": 3, "applied": 1, "not_applied": 0,
                                                          "too_old": 1, "left_out": 1, "reapplied": 0,
                                                          "pending": 0}


@pytest.mark.parametrize("hold_s", [0.0, 0.12])
def test_a_held_neighbour_measurement_is_applied_again_until_it_is_too_old(hold_s):
    """With ``neighbour_hold_s``, the newest accepted measurement of a pair goes into the later
    steps too, each time with its age at that step, until it is older than the hold (a camera at
    10 Hz, steps at 20 Hz: every step gets one); a newer one replaces it, and one the gate
    refuses is not held. Counted apart (``reapplied``); without a hold each is used once."""
    n = 3
    rng = np.random.default_rng(41)
    p, v, q, w, d, P = perturbed_chain(rng, n)
    setup = setup_for(n, neighbour_hold_s=hold_s, neighbour_mount_std_m=0.0, neighbour_mount_std_deg=0.0)
    setup = replace(setup, skeleton=replace(setup.skeleton, link_length_m=2 * d[0, 0]))
    view = NeighbourView(np.array([0.45, 0.0, 0.05]), np.eye(3), np.array([0.0, 0.0, 0.08]), np.eye(3))
    R_cm, t_cm = marker_in_camera(p[0], q[0], p[1], q[1], view)
    m = NeighbourMeasurement(0, 1, R_cm, t_cm + [0.02, 0.0, 0.01], np.eye(6) * 1e-3, view)
    far = replace(m, t_cm_m=t_cm + [5.0, 0.0, 0.0])  # the gate refuses it
    engine = CompanionEngine(setup)

    def step(t):
        states = [LinkState(i, t, p[i], v[i], q[i], w[i], P[i]) for i in range(n)]
        for i, st in enumerate(states):
            engine.on_state(i, st, STATE_FLAG_EKF_OK, t)
        got = [c.correction.dp_w_m for c in of(CorrectionOut, engine.poll(t))]
        return got, states

    def want(states, t_capture, t):
        _, c = compute_corrections(states, setup.skeleton.d_b_m, setup.companion.group_layout(n),
                                   setup.companion.params,
                                   neighbours=[replace(m, age_s=t - t_capture)] if t_capture is not None else [])
        return [x.dp_w_m for x in c]

    engine.on_neighbour(0.95, m)
    steps = [(1.0, 0.95), (1.05, 0.95 if hold_s else None), (1.1, None)]  # (step, capture it applies)
    for t, t_capture in steps:
        got, states = step(t)
        np.testing.assert_allclose(got, want(states, t_capture, t), atol=1e-12)
    engine.on_neighbour(1.12, far)
    got, states = step(1.15)
    np.testing.assert_allclose(got, want(states, None, 1.15), atol=1e-12)  # refused; nothing held
    got, states = step(1.2)
    np.testing.assert_allclose(got, want(states, None, 1.2), atol=1e-12)
    assert engine.summary()["neighbour_measurements"] == {
        "received": 2, "applied": 1, "not_applied": 1, "too_old": 0, "left_out": 0, "reapplied": 1 if hold_s else 0,
        "pending": 0}


def test_a_neighbour_pose_off_the_wire_is_the_measurement_between_the_links_it_names():
    """A NeighbourPose (chain indices, quaternions, through the Zenoh codec) gives the engine the
    same step as the NeighbourMeasurement it stands for; a distributed group's engine takes the
    poses between its own links only and counts the others (another group's pair, a pair across
    two groups) as left out."""
    n = 4
    rng = np.random.default_rng(42)
    p, v, q, w, d, P = perturbed_chain(rng, n)
    view = NeighbourView(np.array([0.45, 0.0, 0.05]), rot_z(0.3), np.array([0.0, 0.0, 0.08]),
                         rot_z(-0.2))
    R_cm, t_cm = marker_in_camera(p[1], q[1], p[2], q[2], view)
    cov = np.diag([1e-3, 2e-3, 1e-3, 4e-4, 4e-4, 9e-4])
    m = NeighbourMeasurement(1, 2, R_cm, t_cm + [0.05, 0.0, 0.02], cov, view)
    pose = codec.decode(codec.encode(NeighbourPose(1, 2, 0.95, 7, rotmat_to_quat(R_cm), m.t_cm_m, cov,
                                                   view.camera_pos_b_m, rotmat_to_quat(view.R_b_c),
                                                   view.marker_pos_b_m, rotmat_to_quat(view.R_b_m))))
    setup = setup_for(n)
    setup = replace(setup, skeleton=replace(setup.skeleton, link_length_m=2 * d[0, 0]))
    states = [LinkState(i, 1.0, p[i], v[i], q[i], w[i], P[i]) for i in range(n)]
    got = []
    for give in (lambda e: e.on_neighbour_pose(pose), lambda e: e.on_neighbour(0.95, m)):
        engine = CompanionEngine(setup)
        give(engine)
        for i, st in enumerate(states):
            engine.on_state(i, st, STATE_FLAG_EKF_OK, 1.0)
        got.append([c.correction.dp_w_m for c in of(CorrectionOut, engine.poll(1.0))])
        assert engine.summary()["neighbour_measurements"]["applied"] == 1
    np.testing.assert_allclose(got[0], got[1], atol=1e-12)
    # groups (1, 2) and (3, 4) in two engines: the pose between links 2 and 3 crosses them
    setup = setup_for(n, ((1, 2), (3, 4)), distributed=True)
    _, engines = group_engines(setup, lambda: 1.0)
    for e in engines:
        e.on_neighbour_pose(pose)
        e.on_neighbour_pose(replace(pose, observer=3, observed=2))
    assert [e.step.neighbours.counts()["left_out"] for e in engines] == [2, 1]
    assert engines[1].step.neighbours.counts()["received"] == 2


def rot_z(angle_rad: float) -> np.ndarray:
    """A rotation about z (a camera or marker mount turned on its link)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_needs_poll_leaves_out_only_polls_that_would_do_nothing():
    """Two copies of a distributed companion (groups [1, 2] and [3], a LocalHub each) get the same
    inputs: states every 30 ms (link 2 silent from 0.6 s: the leader's wait and the shift deadline
    run out), flags that never say armed (ARM retries), a health period of 0.3 s, heartbeats; both
    are polled on a 1 ms grid, one on every tick, the other only when needs_poll. The same outputs
    at the same times and the same step logs; every poll needs_poll would leave out returns nothing."""
    n, groups = 3, ((1, 2), (3,))
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(5), n)
    setup = setup_for(n, groups, distributed=True, health_period_s=0.3)
    setup = replace(setup, skeleton=replace(setup.skeleton, link_length_m=2 * d[0, 0]))

    def system():
        clock = [0.0]
        hub, engines = group_engines(setup, lambda: clock[0], startup_s=0.1)
        return clock, hub, engines

    runs = {}
    for every in (True, False):
        clock, hub, engines = system()
        outputs, polls = [], 0
        for k in range(1500):
            t = clock[0] = k * 1e-3
            for e in engines:
                if k % 30 == 0:
                    for lk in e.links:
                        if lk.index != 1 or t < 0.6:
                            e.on_state(lk.row, LinkState(lk.index, t, p[lk.index], v[lk.index], q[lk.index],
                                                         w[lk.index], P[lk.index]), STATE_FLAG_EKF_OK, t)
                if k % 700 == 350:
                    e.on_heartbeat(0, t)
            for _ in range(6):
                for g, e in enumerate(engines):
                    idle = not e.needs_poll(t)
                    if every or not idle:
                        polls += 1
                        out = e.poll(t)
                        assert not (idle and out), (t, g, out)
                        outputs += [(k, g, type(o).__name__, getattr(o, "row", None)) for o in out]
                if not hub.pending():
                    break
        runs[every] = outputs, polls, [e.log_arrays() for e in engines], [dict(e.net.node.counts) for e in engines]
    (out_every, polls_every, logs_every, counts), (out_needed, polls_needed, logs_needed, counts_needed) = (
        runs[True], runs[False])
    kinds = {kind for _, _, kind, _ in out_every}
    assert {"Heartbeat", "HealthDue", "CommandOut", "CorrectionOut", "TargetOut"} <= kinds, kinds
    assert out_needed == out_every and counts_needed == counts
    assert all(c["global"] > 5 for c in counts) and counts[1]["local_only"] > 10, counts  # deadlines ran out
    assert polls_needed < 0.5 * polls_every  # (the start-up listening and the silence need the most)
    for a, b in zip(logs_every, logs_needed):
        assert a.keys() == b.keys() and a["t_sckf"].size > 20
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


@pytest.mark.parametrize("groups", [((1, 2), (3, 4, 5), (6, 7)), ((1, 2, 3), (4, 5, 6, 7))])
def test_distributed_engines_on_an_in_process_bus_equal_the_in_process_step(groups):
    """Group engines joined by a LocalHub (batch mode's bus): after the start-up listening, every
    cycle ends with the leader's eq. 6 shift, and the corrections equal Alg. 2 + eq. 6 in one process."""
    n = 7
    rng = np.random.default_rng(4)
    p, v, q, w, d, P = perturbed_chain(rng, n)
    setup = setup_for(n, groups, distributed=True)
    setup = replace(setup, skeleton=replace(setup.skeleton, link_length_m=2 * d[0, 0]))
    clock = [0.0]
    layout = setup.companion.group_layout(n)
    _, engines = group_engines(setup, lambda: clock[0])
    states_at = lambda t: [LinkState(i, t, p[i], v[i], q[i], w[i], P[i]) for i in range(n)]  # noqa: E731
    got = fly_group_engines(engines, clock, states_at)  # 0.8 s: the first cycles fall in the start-up listening
    late = [k for k in range(16) if all((k, i) in got for i in range(n))]
    assert len(late) >= 5
    _, want = compute_corrections(states_at(0.0), setup.skeleton.d_b_m, layout, setup.companion.params)
    k = late[-1]
    for i in range(n):
        np.testing.assert_allclose(got[(k, i)].dp_w_m, want[i].dp_w_m, atol=1e-9)
        np.testing.assert_allclose(got[(k, i)].dv_w_m_s, want[i].dv_w_m_s, atol=1e-9)
    assert all(e.log["global_applied"][-1] for e in engines)
    assert len({e.log["leader"][-1] for e in engines}) == 1


def test_a_group_engine_applies_its_neighbour_measurements_in_its_local_half():
    """Distributed, 7 links in groups (1, 2), (3, 4, 5), (6, 7); group 2's engine is given a camera
    measurement between links 3 and 4 every cycle, captured at the cycle: the corrections equal
    Alg. 2 + eq. 6 in one process with the measurement in group 2, and each was applied."""
    n, groups = 7, ((1, 2), (3, 4, 5), (6, 7))
    rng = np.random.default_rng(41)
    p, v, q, w, d, P = perturbed_chain(rng, n)
    setup = setup_for(n, groups, distributed=True, neighbour_mount_std_m=0.0, neighbour_mount_std_deg=0.0)
    setup = replace(setup, skeleton=replace(setup.skeleton, link_length_m=2 * d[0, 0]))
    view = NeighbourView(np.array([0.45, 0.0, 0.05]), np.eye(3), np.array([0.0, 0.0, 0.08]), np.eye(3))
    R_cm, t_cm = marker_in_camera(p[2], q[2], p[3], q[3], view)
    m = NeighbourMeasurement(2, 3, R_cm, t_cm + [0.04, -0.02, 0.01], np.eye(6) * 1e-3, view)
    clock = [0.0]
    _, engines = group_engines(setup, lambda: clock[0])
    states_at = lambda t: [LinkState(i, t, p[i], v[i], q[i], w[i], P[i]) for i in range(n)]  # noqa: E731
    got = fly_group_engines(engines, clock, states_at,
                            before=lambda k, t: engines[1].on_neighbour(t, m.numbered_from(2)))
    k = [k for k in range(16) if all((k, i) in got for i in range(n))][-1]
    _, want = compute_corrections(states_at(0.0), setup.skeleton.d_b_m, setup.companion.group_layout(n),
                                  setup.companion.params, neighbours=[m])
    for i in range(n):
        np.testing.assert_allclose(got[(k, i)].dp_w_m, want[i].dp_w_m, atol=1e-9)
    counts = engines[1].summary()["neighbour_measurements"]
    assert counts["received"] == 16 and counts["applied"] >= 5 and counts["not_applied"] == 0


@pytest.mark.parametrize("down, parts, joined", [
    # the middle of group 2: two one-link parts, each joined to its neighbouring group
    (3, {(0, 1, 2): ((0, 1), (2,)), (4, 5, 6): ((0,), (1, 2))}, [True, True, True]),
    # its first link: group 2's rest joins group 3; group 1 is alone (Alg. 1 on its own)
    (2, {(0, 1): ((0, 1),), (3, 4, 5, 6): ((0, 1), (2, 3))}, [False, True, True]),
])
def test_a_holed_group_takes_part_in_the_global_step_part_by_part(down, parts, joined):
    """Distributed, 7 links in groups (1, 2), (3, 4, 5), (6, 7), link ``down`` silent: each part
    of group 2 takes part in the global step joined to the group it touches, so every live link
    is corrected, as Alg. 2 + eq. 6 in one process on each side of the hole (with those parts
    as groups); a part that touches no group is corrected alone."""
    n, groups = 7, ((1, 2), (3, 4, 5), (6, 7))
    rng = np.random.default_rng(5)
    p, v, q, w, d, P = perturbed_chain(rng, n)
    setup = setup_for(n, groups, distributed=True)
    setup = replace(setup, skeleton=replace(setup.skeleton, link_length_m=2 * d[0, 0]))
    clock = [0.0]
    _, engines = group_engines(setup, lambda: clock[0])
    states_at = lambda t: [LinkState(i, t, p[i], v[i], q[i], w[i], P[i]) for i in range(n)]  # noqa: E731
    got = fly_group_engines(engines, clock, states_at, heard=lambda k, i: i != down or k == 0)
    live = [i for i in range(n) if i != down]
    k = max(k for k in range(16) if all((k, i) in got for i in live))
    assert k >= 12 and (k, down) not in got
    for seg, layout in parts.items():
        _, want = compute_corrections([states_at(0.05 * k)[i] for i in seg], setup.skeleton.d_b_m[list(seg)], layout,
                                      setup.companion.params)
        for i, c in zip(seg, want):
            np.testing.assert_allclose(got[(k, i)].dp_w_m, c.dp_w_m, atol=1e-9)
            np.testing.assert_allclose(got[(k, i)].dv_w_m_s, c.dv_w_m_s, atol=1e-9)
            np.testing.assert_allclose(got[(k, i)].dtheta_w_rad, c.dtheta_w_rad, atol=1e-9)
    assert [bool(e.log["global_applied"][-1]) for e in engines] == joined
    assert np.asarray(engines[1].log["corrected_sckf"][-1]).tolist() == [i != down for i in (2, 3, 4)]


@pytest.mark.parametrize("distributed", [False, True])
def test_the_common_gnss_error_stays_out_of_the_step_and_back_in_the_covariance(distributed):
    """gnss_common_pos_var_m2: links whose reported position covariance includes the receivers'
    common error are corrected as if it were not there (no constraint sees a common offset) and
    their corrected covariance gets it back; a link whose covariance is not larger keeps it."""
    n, groups = (7, ((1, 2), (3, 4, 5), (6, 7))) if distributed else (3, ())
    rng = np.random.default_rng(9)
    p, v, q, w, d, P = perturbed_chain(rng, n)
    C = np.diag([3.24, 3.24, 7.29])
    P_rep = P.copy()
    P_rep[:, :3, :3] += C
    if not distributed:
        P_rep[1] = P[1]  # this link's EKF does not report the receiver's bias

    def run(common, P_in):
        setup = setup_for(n, groups, distributed=distributed, gnss_common_pos_var_m2=common)
        setup = replace(setup, skeleton=replace(setup.skeleton, link_length_m=2 * d[0, 0]))
        states = [LinkState(i, 0.0, p[i], v[i], q[i], w[i], P_in[i]) for i in range(n)]
        if not distributed:
            engine = CompanionEngine(setup)
            for i, st in enumerate(states):
                engine.on_state(i, st, STATE_FLAG_EKF_OK, 0.0)
            got = {i: c.correction for c in of(CorrectionOut, engine.poll(0.0)) for i in [c.row]}
            return got, np.asarray(engine.log["P_corr_sckf"][-1]), np.asarray(engine.log["P_ekf_sckf"][-1]), [engine]
        clock = [0.0]
        _, engines = group_engines(setup, lambda: clock[0])
        got = {}
        for k in range(14):
            t = clock[0] = 0.05 * k
            for e in engines:
                for lk in e.links:
                    e.on_state(lk.row, replace(states[lk.index], time_s=t), STATE_FLAG_EKF_OK, t)
            for _ in range(6):
                for e in engines:
                    for out in of(CorrectionOut, e.poll(t)):
                        got[e.links[out.row].index] = out.correction
        assert all(e.log["global_applied"][-1] for e in engines)
        cat = lambda key: np.concatenate([np.asarray(e.log[key][-1]) for e in engines])  # noqa: E731
        return got, cat("P_corr_sckf"), cat("P_ekf_sckf"), engines

    want, P_corr_want, _, _ = run(None, P)
    got, P_corr, P_ekf, engines = run((3.24, 7.29), P_rep)
    for i in range(n):
        np.testing.assert_allclose(got[i].dp_w_m, want[i].dp_w_m, atol=1e-9)
        np.testing.assert_allclose(got[i].dtheta_w_rad, want[i].dtheta_w_rad, atol=1e-9)
    # logged per link as 3x3 blocks (position, velocity, attitude): the position block gets C back
    kept = [] if distributed else [1]
    for i in range(n):
        extra = 0.0 if i in kept else C
        np.testing.assert_allclose(P_corr[i, 0], P_corr_want[i, 0] + extra, atol=1e-9)
        np.testing.assert_allclose(P_corr[i, 1:], P_corr_want[i, 1:], atol=1e-9)
        np.testing.assert_allclose(P_ekf[i, 0], P_rep[i][:3, :3], atol=1e-12)  # as the links reported it
    assert sum(e.summary()["common_mode_kept"] for e in engines) == len(kept)
    with pytest.raises(ValueError, match="gnss_common_pos_var_m2"):
        CompanionConfig(gnss_common_pos_var_m2=(-1.0, 0.0))


def test_engine_rejects_inconsistent_group_arguments():
    with pytest.raises(ValueError, match="give the group"):
        CompanionEngine(setup_for(7, ((1, 2), (3, 4, 5), (6, 7)), distributed=True))
    with pytest.raises(ValueError, match="only for distributed"):
        CompanionEngine(setup_for(), group=0)
    with pytest.raises(ValueError, match="share the trajectory's anchor"):
        hub = LocalHub(3, lambda: 0.0)
        CompanionEngine(setup_for(7, ((1, 2), (3, 4, 5), (6, 7)), distributed=True), group=0,
                        net=GroupLink(GlobalStepNode(0, 3, (1, 0, 2), 50_000), hub.join(0)))

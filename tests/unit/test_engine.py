"""The companion engine, pure: typed inputs and a fake clock in, outputs out (no sockets, no sleeps)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.config import CompanionConfig, CompanionSetup, LinkEndpoint
from companion.corrections import compute_corrections
from companion.engine import (
    ARM_FAST_TRIES,
    ARM_RETRY_S,
    RETRY_S,
    Command,
    CommandOut,
    CompanionEngine,
    CorrectionOut,
    HealthDue,
    Heartbeat,
    TargetOut,
)
from companion.estimation.so3 import quat_from_euler_zyx
from companion.fleetnet.group import GroupLink
from companion.fleetnet.hub import LocalHub
from companion.fleetnet.leader import GlobalStepNode
from companion.messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, STATE_FLAG_GPS_FAULT, GroupPassiveLinks, LinkState
from companion.skeleton.body import SkeletonConfig
from companion.trajectory import TrajectoryConfig

from ..chains import perturbed_chain

def setup_for(n=3, groups=(), **companion) -> CompanionSetup:
    """A companion config: ``n`` links of 1 m, the paper's bending flight as targets."""
    links = tuple(LinkEndpoint(i + 1, f"udpin://127.0.0.1:{15000 + i}") for i in range(n))
    return CompanionSetup(name="engine_test", skeleton=SkeletonConfig(n_links=n),
                          companion=CompanionConfig(links=links, groups=groups, **companion),
                          trajectory=TrajectoryConfig(kind="bend", takeoff_altitude_m=2.5, bend_start_s=20.0))


def straight_state(i, n, t, dx=0.0, L=1.0):
    p = np.array([(i - (n - 1) / 2) * L + dx, 0.0, 2.0])
    return LinkState(i, t, p, np.zeros(3), quat_from_euler_zyx(0.0, 0.0, 0.0), np.zeros(3),
                     np.diag([0.04] * 6 + [1e-3] * 3))


def of(kind, outputs):
    return [o for o in outputs if isinstance(o, kind)]


def feed(engine, t, now, dx=None, flags=STATE_FLAG_EKF_OK, offsets=None):
    for lk in engine.links:
        off = offsets[lk.row] if offsets is not None else 0.0
        engine.on_state(lk.row, straight_state(lk.index, engine.n, t + off, 0.0 if dx is None else dx[lk.row]), flags,
                        now)
    return engine.poll(now)


def test_stream_request_retries_each_second_until_acknowledged():
    engine = CompanionEngine(setup_for())
    engine.on_heartbeat(0, 10.0)
    req = of(CommandOut, engine.poll(10.0))
    assert [(r.row, r.command, r.system_id) for r in req] == [(0, Command.STREAM, 1)]
    assert req[0].interval_us == pytest.approx(1e6 / 50.0)
    engine.on_heartbeat(0, 10.0 + 0.5 * RETRY_S)
    assert not of(CommandOut, engine.poll(10.5))  # too soon
    engine.on_heartbeat(0, 10.0 + RETRY_S)
    assert of(CommandOut, engine.poll(11.0))  # retried
    engine.on_command_ack(0, Command.STREAM, True)
    engine.on_heartbeat(0, 20.0)
    assert not of(CommandOut, engine.poll(20.0))


def test_heartbeat_each_second_and_health_each_period():
    engine = CompanionEngine(setup_for(health_period_s=5.0))
    beats = health = 0
    for k in range(121):  # 12 s in 0.1 s
        out = engine.poll(100.0 + 0.1 * k)
        beats += len(of(Heartbeat, out))
        health += len(of(HealthDue, out))
    assert beats == 13 and health == 2


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
    # anchored at the chain's middle: the middle link's target is at its estimate
    np.testing.assert_allclose(targets[1].target.p_w_m, [0.2, 0.0, 2.0], atol=1e-9)
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


def test_a_link_on_another_clock_is_left_out_and_the_others_go_on(caplog):
    """A Pixhawk booted at another time (or a link that stopped): never extrapolated over seconds,
    never moving the cycle clock; the links that agree keep being corrected."""
    engine = CompanionEngine(setup_for())
    corrected = []
    for k in range(3):
        out = feed(engine, 0.02 * k, 5.0 + 0.02 * k, offsets=(0.0, 0.0, 12.5), dx=(0.0, 0.2, 0.0))
        corrected += [c.row for c in of(CorrectionOut, out)]
    assert set(corrected) == {0, 1} and engine.fc_time_us < 100_000
    assert engine.links[2].future == 0  # consistent with its own clock: accepted, not used
    assert [r["status"] for r in engine.health_rows(1.0, 6.0)] == ["", "", "stale"]
    assert engine.summary()["links"]["3"]["excluded_steps"] == {"stale": engine.summary()["steps"]}
    assert "does not share the chain's time base" in caplog.text


def test_gps_time_base_aligns_pixhawks_booted_at_different_times(caplog):
    caplog.set_level("INFO", logger="companion.engine")
    engine = CompanionEngine(setup_for(time_base="gps"))
    boot = [0.0, 7.25, 31.5]  # link i's clock reads t + boot[i] at GPS time t (since 1.8e9 s)
    unix0 = 1_800_000_000.0
    dx = (0.0, 0.2, 0.0)
    for k in range(3):  # states alone are not used until the link's offset is known
        for i in range(3):
            assert not engine.on_state(i, straight_state(i, 3, 0.02 * k + boot[i], dx[i]), STATE_FLAG_EKF_OK, 0.02 * k)
        assert not of(CorrectionOut, engine.poll(0.02 * k))
    for i in range(3):
        engine.on_system_time(i, 0, int((boot[i] + 0.04) * 1000))  # no fix yet: ignored
        engine.on_system_time(i, int((unix0 + 0.05) * 1e6), int((boot[i] + 0.05) * 1000))
    assert [lk.offset_us for lk in engine.links] == [int((unix0 - b) * 1e6) for b in boot]
    corr = []
    for k in range(3, 6):
        for i in range(3):
            assert engine.on_state(i, straight_state(i, 3, 0.02 * k + boot[i], dx[i]), STATE_FLAG_EKF_OK, 0.02 * k)
        corr += of(CorrectionOut, engine.poll(0.02 * k))
    assert len(corr) == 3
    for c in corr:  # stamped on each link's own clock, the step at GPS time unix0 + 0.1 s
        assert c.correction.ekf_time_s == pytest.approx(0.10 + boot[c.row], abs=1e-6)
    assert corr[1].correction.dp_w_m[0] < -0.05  # the same correction as with one clock
    assert engine.withheld == 0 and "boot clock + " in caplog.text


def test_rejected_states_are_counted_per_link():
    engine = CompanionEngine(setup_for())
    engine.on_rejected(1, "SKELETON_LINK_STATE", "q: quaternion norm 0.9 is not 1")
    assert [lk.rejected for lk in engine.links] == [0, 1, 0]
    rows = engine.health_rows(1.0, 0.0)
    assert [r["rejected"] for r in rows] == [0, 1, 0] and rows[1]["latency_p50_ms"] is None


def test_arm_retries_until_the_link_reports_armed():
    """A disarmed link with a usable EKF (e.g. rebooted in flight, rotors off) is asked again every
    ARM_RETRY_S for the first ARM_FAST_TRIES commands (a lost command costs 0.2 s, not 1 s), then
    every RETRY_S; a link that reports armed is left alone and its count starts over."""
    engine = CompanionEngine(setup_for())

    def arms(t, now, flags=STATE_FLAG_EKF_OK):
        return [a.row for a in of(CommandOut, feed(engine, t, now, flags=flags)) if a.command is Command.ARM]

    assert arms(0.0, 0.0) == [0, 1, 2]
    assert arms(0.02, 0.5 * ARM_RETRY_S) == []  # too soon
    sent = [0.0]
    now = 0.0
    while len(sent) < ARM_FAST_TRIES:
        now += ARM_RETRY_S + 1e-6
        assert arms(now, now) == [0, 1, 2]
        sent.append(now)
    assert arms(now + ARM_RETRY_S, now + ARM_RETRY_S) == []  # the fast tries are used up
    assert arms(now + 0.9 * RETRY_S, now + 0.9 * RETRY_S) == []
    assert arms(now + RETRY_S + 1e-6, now + RETRY_S + 1e-6) == [0, 1, 2]
    now += RETRY_S + 1e-6
    assert arms(now + 0.1, now + 5.0, flags=STATE_FLAG_EKF_OK | STATE_FLAG_ARMED) == []
    # disarmed again later (a reboot in flight): fast again
    assert arms(now + 0.2, now + 6.0) == [0, 1, 2]
    assert arms(now + 0.3, now + 6.0 + ARM_RETRY_S + 1e-6) == [0, 1, 2]


@pytest.mark.parametrize("n, down", [(3, 1), (5, 2), (7, 3)])
def test_a_link_without_rotors_is_carried_by_its_neighbours(n, down):
    """A link that has flown and goes silent (power lost), comes back disarmed (rebooted) and is
    re-armed (ESCs restarting) is carried: the feed-forward of its neighbours' targets takes its
    weight, from carry_silence_s after its last state (on the time base) until carry_spinup_s
    after it reports armed again; the links carry nothing otherwise, and the summary says how
    long it was carried. A dropout of an armed link is carried only while it lasts."""
    pytest.importorskip("pinocchio")
    setup = setup_for(n)
    setup = replace(setup, trajectory=replace(setup.trajectory, kind="hover", feedforward=True))
    cfg = setup.companion
    engine = CompanionEngine(setup)
    flying = STATE_FLAG_EKF_OK | STATE_FLAG_ARMED
    t = 0.0

    def tick(rows, down_flags=flying):
        nonlocal t, weight
        t = round(t + 0.02, 6)
        for r in rows:
            engine.on_state(r, straight_state(r, n, t), down_flags if r == down else flying, t)
        out = of(TargetOut, engine.poll(t))
        # its weight, and what its target's acceleration (the take-off's) needs
        weight = mass * (9.80665 + out[down].target.a_w_m_s2[2])
        return {o.row: o.target.force_ff_w_n for o in out}

    everyone, others = range(n), [r for r in range(n) if r != down]
    mass, weight = 0.0, 0.0
    ff = tick(everyone)
    mass = engine.trajectory.dynamics.inertia.mass_kg
    while t < 1.0:
        ff = tick(everyone)
    assert all(np.abs(f).max() < 1e-9 for f in ff.values())  # hover: each link carries itself
    t_silent = t
    carried_from = None
    while t < t_silent + 0.5:
        ff = tick(others)
        lift = sum(ff[r][2] for r in (down - 1, down + 1))
        if carried_from is None and lift > 0.5 * weight:
            carried_from = t
    assert carried_from is not None and carried_from - t_silent == pytest.approx(cfg.carry_silence_s, abs=0.021)
    assert engine.summary()["links"][str(down + 1)]["carried_s"] == pytest.approx(t - carried_from, abs=1e-6)
    # its two neighbours take its weight; the others are unmoved; its own target keeps the
    # feed-forward of a flying chain (none in a hover), to lift itself when its rotors are back
    assert lift == pytest.approx(weight, rel=1e-5) and np.abs(ff[down]).max() < 1e-9
    assert np.abs(engine.trajectory.dynamics.last.rotor_wrench_w[down]).max() < 1e-5 * weight  # its rotors: nothing
    assert all(np.abs(ff[r]).max() < 1e-5 * weight for r in others if abs(r - down) > 1)
    for _ in range(10):  # back, disarmed (a reboot): still carried
        ff = tick(everyone, down_flags=STATE_FLAG_EKF_OK)
    assert ff[down - 1][2] + ff[down + 1][2] == pytest.approx(weight, rel=1e-5)
    t_armed = t + 0.02
    released = None
    while t < t_armed + 1.0:
        ff = tick(everyone)
        if released is None and abs(ff[down - 1][2]) < 1e-6 * weight:
            released = t
    assert released is not None and released - t_armed == pytest.approx(cfg.carry_spinup_s, abs=0.021)
    carried = engine.summary()["links"][str(down + 1)]["carried_s"]
    assert carried == pytest.approx(released - carried_from, abs=1e-6)
    assert all(engine.summary()["links"][str(r + 1)]["carried_s"] == 0.0 for r in others)
    # a dropout shorter than reboot_silence_s, heard armed again: carried while unheard only
    t_silent = t
    while t < t_silent + 0.3:
        ff = tick(others)
    assert ff[down - 1][2] + ff[down + 1][2] == pytest.approx(weight, rel=1e-5)
    ff = tick(everyone)
    assert abs(ff[down - 1][2]) < 1e-6 * weight
    # silent reboot_silence_s, then heard armed (a reboot whose disarmed states were lost):
    # carried until carry_spinup_s after it is heard
    t_silent = t
    while t < t_silent + cfg.reboot_silence_s + 0.02:
        tick(others)
    t_heard = t + 0.02
    ff = tick(everyone)
    assert ff[down - 1][2] + ff[down + 1][2] == pytest.approx(weight, rel=1e-5)
    while t < t_heard + cfg.carry_spinup_s - 0.03:
        ff = tick(everyone)
    assert ff[down - 1][2] + ff[down + 1][2] == pytest.approx(weight, rel=1e-5)
    for _ in range(3):
        ff = tick(everyone)
    assert abs(ff[down - 1][2]) < 1e-6 * weight


@pytest.mark.parametrize("n", [2, 3])
def test_forged_states_of_one_link_carry_no_link(n):
    """An unsigned wire's forger sends plausible states of link 2 stamped 0.08 s ahead and
    reporting it disarmed, between its real (armed) ones: with three links or more the others do
    not fall behind the median of the chain's stamps; with two (a group's engine) the other falls
    behind link 2's forged stamps, but it has not been silent on the companion's own clock (its
    states keep arriving); a lone disarmed report is not believed. So nothing is carried."""
    pytest.importorskip("pinocchio")
    setup = setup_for(n)
    setup = replace(setup, trajectory=replace(setup.trajectory, kind="hover", feedforward=True))
    engine = CompanionEngine(setup)
    flying = STATE_FLAG_EKF_OK | STATE_FLAG_ARMED
    t = 0.0
    for k in range(150):
        t = round(t + 0.02, 6)
        for r in range(n):
            engine.on_state(r, straight_state(r, n, t), flying, t)
        if k > 50 and k % 2:
            engine.on_state(1, straight_state(1, n, t + 0.08), STATE_FLAG_EKF_OK, t)  # forged: ahead, disarmed
        out = of(TargetOut, engine.poll(t))
        assert all(np.abs(o.target.force_ff_w_n).max() < 1e-6 for o in out), k
    assert all(engine.summary()["links"][str(i + 1)]["carried_s"] == 0.0 for i in range(n))


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


@pytest.mark.parametrize("groups, down", [(((1, 2), (3, 4, 5), (6, 7)), 2), (((1, 2), (3, 4, 5), (6, 7)), 4),
                                          (((1, 2, 3), (4, 5, 6, 7)), 3), (((1,), (2, 3)), 1)])
def test_a_link_at_a_groups_end_is_carried_by_the_next_groups_companion_too(groups, down):
    """Distributed mode: a dead link at the end of its group hangs on a link of the next group. Its
    group's companion publishes it as carried (GroupPassiveLinks) and the other companions carry it
    too: each group's neighbour of it gets its share of the weight within two target periods, and
    the shares are those of the single-engine feed-forward. A group's claim about links that are
    not its own, or a stale one, is counted and dropped; a group that leaves takes its claim with it."""
    pytest.importorskip("pinocchio")
    n = max(max(g) for g in groups)
    setup = setup_for(n, groups, distributed=True)
    # a hover at the start's height: the targets do not depend on when each engine computes them
    setup = replace(setup, trajectory=replace(setup.trajectory, kind="hover", feedforward=True, takeoff_altitude_m=2.0))
    clock = [0.0]
    hub = LocalHub(len(groups), lambda: clock[0])
    layout = setup.companion.group_layout(n)
    engines = [CompanionEngine(setup, group=g, start_center=(0.0, 0.0, 2.0),
                               net=GroupLink(GlobalStepNode(g, len(groups), setup.zenoh.order(len(groups)), 50_000,
                                                            shift_deadline_s=0.035, leader_wait_s=0.025),
                                             hub.join(g), lambda: clock[0]))
               for g in range(len(groups))]
    # one engine over the whole chain: the reference shares
    whole = CompanionEngine(replace(setup_for(n), trajectory=setup.trajectory), start_center=(0.0, 0.0, 2.0))
    flying = STATE_FLAG_EKF_OK | STATE_FLAG_ARMED
    ff: dict[int, np.ndarray] = {}
    ref: dict[int, np.ndarray] = {}

    def tick(t, alive):
        clock[0] = t
        running = [e for e in engines if e.group in hub.buses]  # (a group's companion may have left)
        for e in [*running, whole]:
            for lk in e.links:
                if lk.index in alive:
                    e.on_state(lk.row, straight_state(lk.index, n, t), flying, t)
        for _ in range(3):
            for e in running:
                for o in of(TargetOut, e.poll(t)):
                    ff[e.links[o.row].index] = o.target.force_ff_w_n
        for o in of(TargetOut, whole.poll(t)):
            ref[o.row] = o.target.force_ff_w_n

    t = 0.0
    while t < 1.0:
        t = round(t + 0.02, 6)
        tick(t, range(n))
    assert all(np.abs(f).max() < 1e-9 for f in ff.values())  # hover: each link carries itself
    t_dead = t
    neighbours = [i for i in (down - 1, down + 1) if 0 <= i < n]
    g_down = next(g for g, m in enumerate(layout) if down in m)
    other = [i for i in neighbours if i not in layout[g_down]]
    assert other, "the case has a neighbour in another group"
    carried_at = {}
    while t < t_dead + 0.3:
        t = round(t + 0.02, 6)
        tick(t, [i for i in range(n) if i != down])
        for i in neighbours:
            if i not in carried_at and ff[i][2] > 1.0:
                carried_at[i] = t
    weight = whole.trajectory.dynamics.inertia.mass_kg * 9.80665
    for i in neighbours:  # each neighbour, in whichever group, carries its share of the whole chain's
        np.testing.assert_allclose(ff[i], ref[i], atol=1e-6 * weight)
        assert carried_at[i] - t_dead <= setup.companion.carry_silence_s + 2 * 0.02 + 1e-9
    assert sum(ff[i][2] for i in neighbours) == pytest.approx(weight, rel=1e-5)
    g_other = next(g for g, m in enumerate(layout) if other[0] in m)
    summary = engines[g_other].summary()
    assert summary["carried_by_other_groups_s"][str(down + 1)] > 0.2
    assert summary["carried_links_messages"]["rejected"] == 0
    # hostile or stale claims: dropped and counted; they carry nothing
    e = engines[g_other]
    healthy = other[0]
    for msg in (GroupPassiveLinks(g_down, int(t * 1e6), (healthy,)),            # not its link
                GroupPassiveLinks(g_other, int(t * 1e6), (healthy,)),           # "from" the receiver itself
                GroupPassiveLinks(g_down, int((t - 5.0) * 1e6), (down,)),       # stale
                GroupPassiveLinks(g_down, int((t + 60.0) * 1e6), (down,))):     # far ahead
        e.carrying.on_remote(msg, e.fc_time_us)
    assert e.summary()["carried_links_messages"]["rejected"] == 4
    # its group's companion leaves: its claim goes with it (the link is back to flying itself here)
    hub.buses[g_down].close()
    t = round(t + 0.02, 6)
    tick(t, [i for i in range(n) if i != down and i not in layout[g_down]])
    assert abs(ff[healthy][2]) < 1e-6 * weight


def test_a_carried_links_claim_before_the_cycle_clock_is_held_and_one_far_ahead_cannot_pin():
    """A group's claim that arrives before this companion has a cycle clock (the groups start in
    any order) is held, not counted as rejected; once the clock runs, only a claim within 2.5 s of
    it is used, and one that is not gives way to the next real one."""
    setup = setup_for(4, ((1, 2), (3, 4)), distributed=True)
    hub = LocalHub(2, lambda: 0.0)
    engine = CompanionEngine(setup, group=0, start_center=(0.0, 0.0, 2.0),
                             net=GroupLink(GlobalStepNode(0, 2, setup.zenoh.order(2), 50_000), hub.join(0), lambda: 0.0))
    hub.join(1)
    engine.poll(0.0)  # (group 2 is up)
    engine.carrying.on_remote(GroupPassiveLinks(1, 600_000_000, (2,)), engine.fc_time_us)  # far ahead, before any clock
    assert engine.passive_counts == {"published": 0, "received": 1, "rejected": 0}
    for lk in engine.links:
        engine.on_state(lk.row, straight_state(lk.index, 4, 1.0), STATE_FLAG_EKF_OK, 1.0)
    assert engine.fc_time_us == 1_000_000
    assert engine.carrying.remote(engine.fc_time_us) == frozenset()  # not current: not used
    engine.carrying.on_remote(GroupPassiveLinks(1, 1_000_000, (2,)), engine.fc_time_us)  # the real one replaces it
    assert engine.carrying.remote(engine.fc_time_us) == {2}
    engine.carrying.on_remote(GroupPassiveLinks(1, 900_000_000, (3,)), engine.fc_time_us)  # far ahead: dropped, counted
    assert engine.passive_counts["rejected"] == 1 and engine.carrying.remote(engine.fc_time_us) == {2}


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
        hub = LocalHub(len(groups), lambda: clock[0])
        engines = []
        for g in range(len(groups)):
            node = GlobalStepNode(g, len(groups), setup.zenoh.order(len(groups)), 50_000, startup_s=0.1,
                                  shift_deadline_s=0.035, leader_wait_s=0.025)
            engines.append(CompanionEngine(setup, group=g, start_center=(0.0, 0.0, 2.0),
                                           net=GroupLink(node, hub.join(g), lambda: clock[0])))
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
    hub = LocalHub(len(groups), lambda: clock[0])
    layout = setup.companion.group_layout(n)
    engines = []
    for g in range(len(groups)):
        node = GlobalStepNode(g, len(groups), setup.zenoh.order(len(groups)), 50_000,
                              shift_deadline_s=0.035, leader_wait_s=0.025)
        engines.append(CompanionEngine(setup, group=g, start_center=(0.0, 0.0, 2.0),
                                       net=GroupLink(node, hub.join(g), lambda: clock[0])))
    states_at = lambda t: [LinkState(i, t, p[i], v[i], q[i], w[i], P[i]) for i in range(n)]  # noqa: E731
    got = {}
    for k in range(16):  # 0.8 s: the first cycles fall in the 0.5 s start-up listening
        t = 0.05 * k
        clock[0] = t
        for e in engines:
            for lk in e.links:
                e.on_state(lk.row, states_at(t)[lk.index], STATE_FLAG_EKF_OK, t)
        for _ in range(6):
            for e in engines:
                for out in of(CorrectionOut, e.poll(t)):
                    got[(k, e.links[out.row].index)] = out.correction
    late = [k for k in range(16) if all((k, i) in got for i in range(n))]
    assert len(late) >= 5
    _, want = compute_corrections(states_at(0.0), setup.skeleton.d_b_m, layout, setup.companion.params)
    k = late[-1]
    for i in range(n):
        np.testing.assert_allclose(got[(k, i)].dp_w_m, want[i].dp_w_m, atol=1e-9)
        np.testing.assert_allclose(got[(k, i)].dv_w_m_s, want[i].dv_w_m_s, atol=1e-9)
    assert all(e.log["global_applied"][-1] for e in engines)
    assert len({e.log["leader"][-1] for e in engines}) == 1


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
        hub = LocalHub(len(groups), lambda: clock[0])
        engines = [CompanionEngine(setup, group=g, start_center=(0.0, 0.0, 2.0),
                                   net=GroupLink(GlobalStepNode(g, len(groups), setup.zenoh.order(len(groups)), 50_000,
                                                                shift_deadline_s=0.035, leader_wait_s=0.025),
                                                 hub.join(g), lambda: clock[0]))
                   for g in range(len(groups))]
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


# -- plausibility before use: stamps, the joint gate, segments ---------------------------------------------


def _feed_rows(engine, rows, t, now, dx=None, P=None, flags=STATE_FLAG_EKF_OK):
    for r in rows:
        st = straight_state(r, engine.n, t, 0.0 if dx is None else dx[r])
        if P is not None and P.get(r) is not None:
            st = replace(st, P=P[r])
        engine.on_state(r, st, flags, now)
    return engine.poll(now)


def test_replayed_and_future_states_are_rejected_and_never_move_the_cycle_clock():
    engine = CompanionEngine(setup_for())
    feed(engine, 0.0, 0.0)
    feed(engine, 0.02, 0.02)
    assert not engine.on_state(1, straight_state(1, 3, 0.0), STATE_FLAG_EKF_OK, 0.03)  # a replay
    assert not engine.on_state(1, straight_state(1, 3, 1000.0), STATE_FLAG_EKF_OK, 0.03)  # 1000 s ahead
    assert engine.fc_time_us == 20_000 and engine.links[1].state.time_s == pytest.approx(0.02)
    steps = 0
    for k in range(2, 40):  # the flight goes on: a step every 50 ms, every link corrected
        out = feed(engine, 0.02 * k, 0.02 * k)
        steps += len(of(CorrectionOut, out)) == 3
    assert steps >= 14 and engine.withheld == 0
    rows = engine.health_rows(1.0, 0.8)
    assert (rows[1]["replayed"], rows[1]["future"], rows[1]["rejected"]) == (1, 1, 2)


@pytest.mark.parametrize("n, bad", [(3, 0), (3, 2), (5, 2), (7, 0), (7, 3)])
def test_a_plausible_false_state_is_left_out_not_spread(n, bad):
    """+3 m with a 1e-6 covariance on one link: it gets no correction, its neighbours get what
    their segments alone give, and no healthy link is moved by metres."""
    engine = CompanionEngine(setup_for(n))
    dx = [0.0] * n
    dx[bad] = 3.0
    tiny = {bad: np.eye(9) * 1e-6}
    out = of(CorrectionOut, _feed_rows(engine, range(n), 0.0, 0.0, dx=dx, P=tiny))
    got = {c.row: c.correction for c in out}
    assert bad not in got and engine.links[bad].status == "gate"
    assert all(np.linalg.norm(c.dp_w_m) < 0.01 for c in got.values())  # the others were consistent already
    healthy = [r for r in range(n) if r != bad]
    alone = {r for r in healthy if (r == 0 and bad == 1) or (r == n - 1 and bad == n - 2)}
    assert set(got) == set(healthy) - alone - ({r for r in healthy if n == 3 and bad == 1})
    assert engine.summary()["links"][str(bad + 1)]["excluded_steps"] == {"gate": 1}
    assert engine.log["corrected_sckf"][0].tolist() == [r in got for r in range(n)]


@pytest.mark.parametrize("n, bad, groups", [(3, 1, ()), (3, 0, ()), (5, 2, ()), (7, 6, ()), (5, 2, ((1, 2), (3, 4, 5)))])
def test_a_link_flagging_a_gps_fault_is_corrected_from_its_neighbours_one_way(n, bad, groups):
    """Its EKF 0.8 m off (a GPS ramp it followed before it could tell), a tight covariance, and
    the GPS-fault flag: it is not left out but moved onto its neighbours, which stay put."""
    engine = CompanionEngine(setup_for(n, groups=groups))
    dx = [0.0] * n
    dx[bad] = 0.8
    for r in range(n):
        st = replace(straight_state(r, n, 0.0, dx[r]), P=np.eye(9) * 1e-4 if r == bad else np.eye(9) * 1e-3)
        engine.on_state(r, st, STATE_FLAG_EKF_OK | (STATE_FLAG_GPS_FAULT if r == bad else 0), 0.0)
    got = {c.row: c.correction for c in of(CorrectionOut, engine.poll(0.0))}
    assert set(got) == set(range(n)) and engine.links[bad].status == ""
    np.testing.assert_allclose(got[bad].dp_w_m, [-0.8, 0.0, 0.0], atol=0.01)
    # one group: exact up to the variance ratio; with groups the global step's rigid group shifts
    # (eq. 6) leak a little (millimetres of the 0.8 m)
    bound = 1e-3 if not groups else 1e-2
    assert max(np.linalg.norm(c.dp_w_m) for r, c in got.items() if r != bad) < bound
    assert engine.summary()["links"][str(bad + 1)]["gps_fault_steps"] == 1
    assert engine.health_rows(1.0, 0.0)[bad]["status"] == "gps"
    # without the flag the same state is left out (a plausible false state)
    engine = CompanionEngine(setup_for(n, groups=groups))
    for r in range(n):
        st = replace(straight_state(r, n, 0.0, dx[r]), P=np.eye(9) * 1e-4 if r == bad else np.eye(9) * 1e-3)
        engine.on_state(r, st, STATE_FLAG_EKF_OK, 0.0)
    got = {c.row: c.correction for c in of(CorrectionOut, engine.poll(0.0))}
    assert bad not in got and engine.links[bad].status == "gate"


def test_a_flagged_link_that_agrees_with_its_neighbours_takes_part_as_usual():
    engine = CompanionEngine(setup_for(3))
    for r in range(3):
        engine.on_state(r, straight_state(r, 3, 0.0, 0.05 if r == 1 else 0.0),
                        STATE_FLAG_EKF_OK | (STATE_FLAG_GPS_FAULT if r == 1 else 0), 0.0)
    got = {c.row: c.correction for c in of(CorrectionOut, engine.poll(0.0))}
    assert set(got) == {0, 1, 2} and engine.summary()["links"]["2"]["gps_fault_steps"] == 0
    assert np.linalg.norm(got[0].dp_w_m) > 0.005  # its dead-reckoned position still counts


def test_a_silent_link_splits_the_chain_and_the_others_keep_their_corrections():
    engine = CompanionEngine(setup_for(5))
    rows = range(5)
    corrected = []
    for k in range(40):
        live = [r for r in rows if r != 2 or k < 5]  # link 3 stops after 0.1 s
        out = _feed_rows(engine, live, 0.02 * k, 0.02 * k, dx=[0.0, 0.1, 0.0, 0.0, -0.1])
        if of(CorrectionOut, out):
            corrected.append(sorted(c.row for c in of(CorrectionOut, out)))
    # every step has corrections: all five at first, then the two segments either side of link 3
    assert corrected[0] == [0, 1, 2, 3, 4] and corrected[-1] == [0, 1, 3, 4]
    assert len(corrected) == len(engine.log["t_sckf"]) and engine.withheld == 0
    assert engine.links[2].status == "stale" and engine.degraded >= 10


def test_a_link_rebooted_onto_its_own_boot_clock_is_rebased_and_kept_out():
    """Link 2's clock restarts at 0.1 s after 1.5 s of silence: its gate re-bases after ten states
    (a reboot, counted), its stamps never move the cycle clock, and with ``time_base =
    "flight_controller"`` it stays out (``stale``): links 1 and 3, alone, get no corrections."""
    engine = CompanionEngine(setup_for(3))
    for k in range(20):
        _feed_rows(engine, range(3), 100.0 + 0.02 * k, 0.02 * k)
    statuses, rows_corrected = [], []
    for k in range(20, 200):
        t_now = 0.02 * k
        _feed_rows(engine, (0, 2), 100.0 + t_now, t_now, P=None)
        if k >= 95:  # back after 1.5 s, its boot clock from 0.1 s
            engine.on_state(1, straight_state(1, 3, 0.1 + 0.02 * (k - 95)), STATE_FLAG_EKF_OK, t_now)
        out = engine.poll(t_now)
        statuses.append(engine.links[1].status)
        rows_corrected.append(sorted(c.row for c in of(CorrectionOut, out)))
    assert engine.links[1].reboots == 1 and engine.links[1].stamps.last_us < 5_000_000
    assert engine.fc_time_us > 103_000_000
    assert statuses[-1] == "stale" and rows_corrected[-1] == []


def test_a_rebooted_link_on_the_chain_clock_is_readmitted_after_the_wait():
    """SITL restarts a vehicle on simulated time: its stamps jump forward after the silence (a
    plausible stamp); it is left out while its EKF is not usable, then for READMIT_CYCLES usable
    cycles, then corrected again."""
    from companion.engine import READMIT_CYCLES
    engine = CompanionEngine(setup_for(3))
    for k in range(20):
        _feed_rows(engine, range(3), 0.02 * k, 0.02 * k)
    statuses = []
    for k in range(20, 200):
        t_now = 0.02 * k
        _feed_rows(engine, (0, 2), t_now, t_now)
        if k >= 95:
            flags = STATE_FLAG_EKF_OK if k >= 120 else 0  # its EKF initialises 0.5 s after it is back
            engine.on_state(1, straight_state(1, 3, t_now), flags, t_now)
        engine.poll(t_now)
        statuses.append(engine.links[1].status)
    assert "stale" in statuses[:75] and set(statuses[80:100]) == {"ekf"}  # (statuses change at the 20 Hz steps)
    assert "returning" in statuses and statuses[-1] == ""
    assert engine.summary()["links"]["2"]["excluded_steps"]["returning"] == READMIT_CYCLES


def test_a_rejected_state_changes_no_flag_and_no_latency():
    """A replayed frame claiming the EKF is lost (flags 0) and a huge latency changes nothing."""
    engine = CompanionEngine(setup_for())
    feed(engine, 0.0, 0.0)
    feed(engine, 0.02, 0.02)
    engine.on_state(1, straight_state(1, 3, 0.0), 0, 0.03, correction_seq=99, correction_latency_us=9_000_000)
    assert engine.links[1].flags == STATE_FLAG_EKF_OK and engine.links[1].latencies_ms == []


def test_a_group_with_a_link_left_out_corrects_its_segments_alone_and_publishes_no_boundary():
    """Distributed: group 2 (links 3, 4, 5) with link 3 stale: links 4 and 5 get Alg. 1 on the two
    of them (local-only, no global step), link 3 none, and no boundary of group 2 goes out."""
    n, groups = 7, ((1, 2), (3, 4, 5), (6, 7))
    setup = setup_for(n, groups, distributed=True)
    hub = LocalHub(3, lambda: 1.0)
    node = GlobalStepNode(1, 3, setup.zenoh.order(3), 50_000, startup_s=0.0)
    engine = CompanionEngine(setup, group=1, start_center=(0.0, 0.0, 2.0), net=GroupLink(node, hub.join(1), lambda: 1.0))
    watcher = hub.join(0)
    dx = {2: 0.0, 3: 0.1, 4: -0.1}
    for lk in engine.links:  # all three report at 0 s, then link 3 falls silent
        engine.on_state(lk.row, straight_state(lk.index, n, 0.0, dx[lk.index]), STATE_FLAG_EKF_OK, 0.0)
    for lk in engine.links[1:]:
        engine.on_state(lk.row, straight_state(lk.index, n, 0.5, dx[lk.index]), STATE_FLAG_EKF_OK, 0.5)
    got = {engine.links[c.row].index: c.correction for c in of(CorrectionOut, engine.poll(0.5))}
    assert set(got) == {3, 4} and engine.links[0].status == "stale"
    states = [straight_state(i, n, 0.5, dx[i]) for i in (3, 4)]
    _, want = compute_corrections(states, setup.skeleton.d_b_m[[3, 4]], [(0, 1)], setup.companion.params)
    for i, w in zip((3, 4), want):
        np.testing.assert_allclose(got[i].dp_w_m, w.dp_w_m, atol=1e-12)
    assert not engine.log["global_applied"][-1] and engine.log["corrected_sckf"][-1].tolist() == [False, True, True]
    assert not [e for e in watcher.drain() if e.kind == "boundary"]

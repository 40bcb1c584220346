"""The companion engine, pure: typed inputs and a fake clock in, outputs out (no sockets, no sleeps)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.config import CompanionConfig, CompanionSetup, LinkEndpoint
from companion.corrections import compute_corrections
from companion.engine import (
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
from companion.messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, LinkState
from companion.skeleton.body import SkeletonConfig
from companion.trajectory import TrajectoryConfig

from .chains import perturbed_chain

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


def test_links_on_different_clocks_get_no_corrections(caplog):
    """Pixhawks booted at different times (or a link that stopped): no extrapolation over seconds."""
    engine = CompanionEngine(setup_for())
    for k in range(3):
        out = feed(engine, 0.02 * k, 5.0 + 0.02 * k, offsets=(0.0, 0.0, 12.5))
        assert not of(CorrectionOut, out)
    assert engine.withheld >= 1 and engine.summary()["withheld_steps"] == engine.withheld
    assert "link 1's newest state is 12.500 s behind" in caplog.text and "time base" in caplog.text


def test_gps_time_base_aligns_pixhawks_booted_at_different_times(caplog):
    caplog.set_level("INFO", logger="companion.engine")
    engine = CompanionEngine(setup_for(time_base="gps"))
    boot = [0.0, 7.25, 31.5]  # link i's clock reads t + boot[i] at GPS time t (since 1.8e9 s)
    unix0 = 1_800_000_000.0
    dx = (0.0, 0.2, 0.0)
    for k in range(3):  # states alone are not used until the link's offset is known
        for i in range(3):
            assert not engine.on_state(i, straight_state(i, 3, 0.02 * k + boot[i], dx[i]), STATE_FLAG_EKF_OK, k)
        assert not of(CorrectionOut, engine.poll(k))
    for i in range(3):
        engine.on_system_time(i, 0, int((boot[i] + 0.04) * 1000))  # no fix yet: ignored
        engine.on_system_time(i, int((unix0 + 0.05) * 1e6), int((boot[i] + 0.05) * 1000))
    assert [lk.offset_us for lk in engine.links] == [int((unix0 - b) * 1e6) for b in boot]
    corr = []
    for k in range(3, 6):
        for i in range(3):
            assert engine.on_state(i, straight_state(i, 3, 0.02 * k + boot[i], dx[i]), STATE_FLAG_EKF_OK, k)
        corr += of(CorrectionOut, engine.poll(k))
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
    engine = CompanionEngine(setup_for())
    arms = of(CommandOut, feed(engine, 0.0, 0.0))
    assert len([a for a in arms if a.command is Command.ARM]) == 3
    assert not [a for a in of(CommandOut, feed(engine, 0.02, 0.5)) if a.command is Command.ARM]
    again = [a for a in of(CommandOut, feed(engine, 0.04, 1.0)) if a.command is Command.ARM]
    assert len(again) == 3
    assert not [a for a in of(CommandOut, feed(engine, 0.06, 3.0, flags=STATE_FLAG_EKF_OK | STATE_FLAG_ARMED))
                if a.command is Command.ARM]


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


def test_engine_rejects_inconsistent_group_arguments():
    with pytest.raises(ValueError, match="give the group"):
        CompanionEngine(setup_for(7, ((1, 2), (3, 4, 5), (6, 7)), distributed=True))
    with pytest.raises(ValueError, match="only for distributed"):
        CompanionEngine(setup_for(), group=0)
    with pytest.raises(ValueError, match="share the trajectory's anchor"):
        hub = LocalHub(3, lambda: 0.0)
        CompanionEngine(setup_for(7, ((1, 2), (3, 4, 5), (6, 7)), distributed=True), group=0,
                        net=GroupLink(GlobalStepNode(0, 3, (1, 0, 2), 50_000), hub.join(0)))

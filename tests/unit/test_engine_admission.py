"""Which link states the companion engine admits and which links take part in a step, pure (a
fake clock, no sockets): time bases, rejected, replayed and future states, the joint gate, GPS-fault
flags, silent and rebooted links, segments."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.corrections import compute_corrections
from companion.engine import CompanionEngine, CorrectionOut
from companion.fleetnet.group import GroupLink
from companion.fleetnet.hub import LocalHub
from companion.fleetnet.leader import GlobalStepNode
from companion.messages import STATE_FLAG_EKF_OK, STATE_FLAG_GPS_FAULT

from ..clocks import FakeClock
from ..engine_cases import feed, of, setup_for, straight_state


# -- time bases and rejected states ------------------------------------------------------------------------


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


@pytest.mark.parametrize("n", [2, 3])
@pytest.mark.parametrize("burst", [1, 5])
def test_states_forged_ahead_leave_no_streaming_link_out(n, burst):
    """An unsigned wire's forger sends states of link 2 stamped ahead, ``burst`` at a time each
    0.24 s further (walking its stamps forward within the stamp margin), between its real ones:
    the cycle clock moves at most once by the margin (then link 2's stream holds replays and its
    stamps move it no more), and link 1, whose states keep arriving, is never left out as silent;
    the forged link is."""
    engine = CompanionEngine(setup_for(n))
    t = 0.0
    for k in range(100):
        t = round(t + 0.02, 6)
        for r in range(n):
            engine.on_state(r, straight_state(r, n, t), STATE_FLAG_EKF_OK, t)
        if k >= 30 and k % 10 == 0:
            for b in range(burst):
                engine.on_state(1, straight_state(1, n, t + 0.24 * (b + 1)), STATE_FLAG_EKF_OK, t)
        engine.poll(t)
        assert engine.fc_time_us * 1e-6 - t < 0.25 * burst + 0.01 if k == 30 else True
        assert engine.links[0].status != "stale", k
    assert engine.fc_time_us * 1e-6 - t < 0.25 * burst + 0.01
    assert "stale" not in engine.summary()["links"]["1"]["excluded_steps"]
    assert engine.links[1].replayed > 0


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


@pytest.mark.parametrize("n", [2, 3])
def test_a_link_rebooted_onto_its_own_boot_clock_is_rebased_and_kept_out(n):
    """Link 2's clock restarts at 0.1 s after 1.5 s of silence: its gate re-bases after ten states
    (a reboot, counted), its stamps never move the cycle clock nor hold it back (two links: it
    would be the second newest), and with ``time_base = "flight_controller"`` it stays out
    (``stale``): the others, alone, get no corrections."""
    engine = CompanionEngine(setup_for(n))
    others = [r for r in range(n) if r != 1]
    for k in range(20):
        _feed_rows(engine, range(n), 100.0 + 0.02 * k, 0.02 * k)
    statuses, rows_corrected = [], []
    for k in range(20, 200):
        t_now = 0.02 * k
        _feed_rows(engine, others, 100.0 + t_now, t_now, P=None)
        if k >= 95:  # back after 1.5 s, its boot clock from 0.1 s
            engine.on_state(1, straight_state(1, n, 0.1 + 0.02 * (k - 95)), STATE_FLAG_EKF_OK, t_now)
        out = engine.poll(t_now)
        statuses.append(engine.links[1].status)
        rows_corrected.append(sorted(c.row for c in of(CorrectionOut, out)))
    assert engine.links[1].reboots == 1 and engine.links[1].stamps.last_us < 5_000_000
    assert engine.fc_time_us > 103_900_000  # (held back, it would have stopped at 101.9 s)
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
    assert engine.links[1].flags == STATE_FLAG_EKF_OK and engine.links[1].latencies_ms.count == 0


def test_a_group_with_a_link_left_out_publishes_its_part_and_corrects_it_alone_without_a_neighbour():
    """Distributed: group 2 (links 3, 4, 5) with link 3 stale: links 4 and 5 are one part, its
    boundary goes out as part 0 of 1 that joins the next group only; with no other group
    reporting, they get Alg. 1 on the two of them (local-only) and link 3 none."""
    n, groups = 7, ((1, 2), (3, 4, 5), (6, 7))
    setup = setup_for(n, groups, distributed=True)
    clock = FakeClock(0.5)
    hub = LocalHub(3, clock)
    node = GlobalStepNode(1, 3, setup.zenoh.order(3), 50_000, startup_s=0.0)
    engine = CompanionEngine(setup, group=1, start_center=(0.0, 0.0, 2.0), net=GroupLink(node, hub.join(1), clock))
    watcher = hub.join(0)
    dx = {2: 0.0, 3: 0.1, 4: -0.1}
    for lk in engine.links:  # all three report at 0 s, then link 3 falls silent
        engine.on_state(lk.row, straight_state(lk.index, n, 0.0, dx[lk.index]), STATE_FLAG_EKF_OK, 0.0)
    for lk in engine.links[1:]:
        engine.on_state(lk.row, straight_state(lk.index, n, 0.5, dx[lk.index]), STATE_FLAG_EKF_OK, 0.5)
    assert not of(CorrectionOut, engine.poll(0.5))  # waiting for the leader
    (b,) = [e.value for e in watcher.drain() if e.kind == "boundary"]
    assert (b.group, b.part, b.parts, b.joins_left, b.joins_right) == (1, 0, 1, False, True)
    clock.t = 0.55  # the shift's deadline passed
    got = {engine.links[c.row].index: c.correction for c in of(CorrectionOut, engine.poll(0.55))}
    assert set(got) == {3, 4} and engine.links[0].status == "stale"
    states = [straight_state(i, n, 0.5, dx[i]) for i in (3, 4)]
    _, want = compute_corrections(states, setup.skeleton.d_b_m[[3, 4]], [(0, 1)], setup.companion.params)
    for i, w in zip((3, 4), want):
        np.testing.assert_allclose(got[i].dp_w_m, w.dp_w_m, atol=1e-12)
    assert not engine.log["global_applied"][-1] and engine.log["corrected_sckf"][-1].tolist() == [False, True, True]

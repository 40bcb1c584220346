"""The companion engine carrying a link without rotors, pure (a fake clock, no sockets): its
neighbours' feed-forward takes its weight while it is silent or spinning up, forged states carry
nothing, and distributed companions carry a link at a group's end across groups."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.engine import CompanionEngine, TargetOut
from companion.engine.carrying import PASSIVE_STALE_US
from companion.fleetnet.group import GroupLink
from companion.fleetnet.hub import LocalHub
from companion.fleetnet.leader import GlobalStepNode
from companion.messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, GroupPassiveLinks

from ..engine_cases import group_engines, of, setup_for, straight_state


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
        weight = mass * (9.80665 + out[down].target.a_w_m_s2[2]) if out else weight
        return {o.row: o.target.force_ff_w_n for o in out}

    everyone, others = range(n), [r for r in range(n) if r != down]
    mass, weight = 0.0, 0.0
    while engine.trajectory is None:  # the first targets come with the first step
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


@pytest.mark.parametrize("groups, down", [(((1, 2), (3, 4, 5), (6, 7)), 2), (((1, 2), (3, 4, 5), (6, 7)), 4),
                                          (((1, 2, 3), (4, 5, 6, 7)), 3), (((1,), (2, 3)), 1)])
def test_a_link_at_a_groups_end_is_carried_by_the_next_groups_companion_too(groups, down):
    """Distributed mode: a dead link at the end of its group hangs on a link of the next group. Its
    group's companion publishes it as carried (GroupPassiveLinks) and the other companions carry it
    too: each group's neighbour of it gets its share of the weight within two target periods, and
    the shares are those of the single-engine feed-forward. A group's claim about links that are
    not its own, or a stale one, is counted and dropped; the claim of a group that leaves holds until
    it goes stale."""
    pytest.importorskip("pinocchio")
    n = max(max(g) for g in groups)
    setup = setup_for(n, groups, distributed=True)
    # a hover at the start's height: the targets do not depend on when each engine computes them
    # (the links fly from the first state: companions started in flight, at the anchor as given)
    setup = replace(setup, trajectory=replace(setup.trajectory, kind="hover", feedforward=True, takeoff_altitude_m=2.0,
                                              home="anchor"))
    clock = [0.0]
    layout = setup.companion.group_layout(n)
    hub, engines = group_engines(setup, lambda: clock[0])
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
    # its group's companion leaves: its claim holds (the dead link is still dead) until it goes stale
    hub.buses[g_down].close()
    t = round(t + 0.02, 6)
    tick(t, [i for i in range(n) if i != down and i not in layout[g_down]])
    np.testing.assert_allclose(ff[healthy], ref[healthy], atol=1e-6 * weight)
    t = round(t + PASSIVE_STALE_US * 1e-6 + 0.1, 6)
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


@pytest.mark.parametrize("offsets, released", [((0.3, 0.3), True), ((0.25, -0.2), False), ((-0.3, -0.3), False)],
                         ids=["both_up", "tilted", "both_down"])
def test_a_silent_link_that_lifts_itself_is_no_longer_carried(offsets, released):
    """The middle link of three has flown and goes silent (its MAVLink link failed, or it lost
    power); its neighbours report heights ``offsets`` against their targets. Both up (a live link
    carried pushes them up): no longer carried (counted in carry_released), and carried again once
    they sink as far below. One up and one down (a dead link tilting the chain) or both down: carried
    throughout."""
    pytest.importorskip("pinocchio")
    setup = setup_for(3)
    setup = replace(setup, trajectory=replace(setup.trajectory, kind="hover", feedforward=True))
    engine = CompanionEngine(setup)
    flying = STATE_FLAG_EKF_OK | STATE_FLAG_ARMED
    target_z = {r: 2.0 for r in range(3)}
    t = 0.0

    def tick(rows, dz=(0.0, 0.0, 0.0)):
        nonlocal t
        t = round(t + 0.02, 6)
        for r in rows:
            s = straight_state(r, 3, t)
            engine.on_state(r, replace(s, p_w_m=np.array([s.p_w_m[0], 0.0, target_z[r] + dz[r]])), flying, t)
        out = of(TargetOut, engine.poll(t))
        target_z.update({o.row: float(o.target.p_w_m[2]) for o in out})
        return {o.row: o.target.force_ff_w_n for o in out}

    while t < 1.0:
        tick(range(3))
    mass = engine.trajectory.dynamics.inertia.mass_kg
    lifts = []
    for k in range(20):  # at their targets while it is first carried, then moved by ``offsets``
        ff = tick((0, 2), (offsets[0], 0.0, offsets[1]) if k >= 6 else (0.0, 0.0, 0.0))
        lifts.append(ff[0][2] + ff[2][2])
    carried = [lift > 0.5 * mass * 9.80665 for lift in lifts]
    summary = engine.summary()["links"]["2"]
    if released:
        assert all(carried[3:6]) and not any(carried[-10:]) and summary["carry_released"] == 1
        for _ in range(5):
            ff = tick((0, 2), (-0.3, 0.0, -0.3))
        assert ff[0][2] + ff[2][2] > 0.9 * mass * 9.80665  # sinking: carried again (its weight, and the climb)
    else:
        assert all(carried[3:]) and summary["carry_released"] == 0


@pytest.mark.parametrize("groups, faulty, silent", [((), 2, True), ((), 0, True), (((1, 2, 3), (4, 5)), 0, True),
                                                  ((), 2, False)],
                         ids=["centralised_link3", "centralised_link1", "distributed_link1", "ekf_not_ok"])
@pytest.mark.parametrize("gps_fault", [True, False], ids=["gps_fault", "gps_healthy"])
def test_a_link_left_out_bridges_a_neighbour_without_gps(gps_fault, groups, faulty, silent):
    """The chain hovers; link 2 goes silent (carried) or reports its EKF unusable (left out, not
    carried), and the EKF of its
    neighbour ``faulty`` (an end link: alone once link 2 is left out) says it is 1 m further out
    than it is, along the chain. Flagging a GPS fault, it is corrected along link 2 from its other
    neighbour: the metre comes off its position (its velocity and attitude untouched), the summary
    counts the bridged steps, the step log has it corrected and link 2 not (NaN if silent), and
    link 2 gets nothing. With its GPS healthy nothing bridges: it is alone and uncorrected, as before.
    Centralised, and in distributed mode with link 2 inside the first of two groups (its other
    neighbour, link 3, is corrected by the global step with the second group)."""
    pytest.importorskip("pinocchio")
    from companion.engine import CorrectionOut
    from companion.messages import STATE_FLAG_GPS_FAULT

    n, down = (max(max(g) for g in groups) if groups else 3), 1
    out_dx = 1.0 if faulty > down else -1.0
    setup = setup_for(n, groups, distributed=bool(groups))
    # (the links fly from the first state: companions started in flight, at the anchor as given)
    setup = replace(setup, trajectory=replace(setup.trajectory, kind="hover", feedforward=True, takeoff_altitude_m=2.0,
                                              home="anchor"))
    clock = [0.0]
    engines = (group_engines(setup, lambda: clock[0])[1] if groups
               else [CompanionEngine(setup, start_center=(0.0, 0.0, 2.0))])
    flying = STATE_FLAG_EKF_OK | STATE_FLAG_ARMED
    corrections: dict[int, list] = {i: [] for i in range(n)}

    def tick(t, alive, dx=0.0, flags=flying):
        clock[0] = t
        for e in engines:
            for lk in e.links:
                if lk.index in alive:
                    mine = lk.index == faulty
                    state = straight_state(lk.index, n, t, dx=dx if mine else 0.0)
                    e.on_state(lk.row, state, flags if mine else flying, t)
        for _ in range(3):
            for e in engines:
                for out in of(CorrectionOut, e.poll(t)):
                    corrections[e.links[out.row].index].append(out.correction)

    t = 0.0
    while t < 1.0:
        t = round(t + 0.02, 6)
        tick(t, range(n))
    while t < 2.0:
        if t == 1.2:  # (link 2 taken as silent by now: what follows is the bridge's)
            for c in corrections.values():
                c.clear()
        t = round(t + 0.02, 6)
        if not silent:  # (streaming, armed, its EKF not usable)
            for e in engines:
                for lk in e.links:
                    if lk.index == down:
                        e.on_state(lk.row, straight_state(down, n, t + 0.02), STATE_FLAG_ARMED, t + 0.02)
        tick(t, [i for i in range(n) if i != down], out_dx, flying | (STATE_FLAG_GPS_FAULT if gps_fault else 0))
    own = engines[0]
    summary = own.summary()
    log = own.log_arrays()
    assert (summary["links"]["2"]["carried_s"] > 0.5) == silent and not corrections[down]
    assert not log["corrected_sckf"][-1][down] and np.isnan(log["p_corr_sckf"][-1][down]).all() == silent
    faulty_link = next(e for e in engines if any(lk.index == faulty for lk in e.links)).summary()["links"]
    bridged = faulty_link[str(faulty + 1)]["bridged_steps"]  # (the link's own count)
    if gps_fault:
        assert len(corrections[faulty]) > 10 and summary["bridged_steps"] >= len(corrections[faulty])
        # (one bridged link: each of its engine's bridged steps corrected it)
        assert len(corrections[faulty]) <= bridged == sum(e.summary()["bridged_steps"] for e in engines)
        last = corrections[faulty][-1]
        np.testing.assert_allclose(last.dp_w_m, [-out_dx, 0.0, 0.0], atol=1e-6)
        assert not last.dv_w_m_s.any() and not last.dtheta_w_rad.any()
        assert log["corrected_sckf"][-1][faulty]
    else:
        assert summary["bridged_steps"] == 0 == bridged and not corrections[faulty]


def test_the_bridge_starts_from_the_healthy_neighbours_corrected_state_at_its_own_stamp():
    """Four links flying sideways at 1 m/s; link 2's EKF is not usable (left out), link 1 flags a
    GPS fault and says it is 1 m further out than it is, and link 3's states are 20 ms older than
    link 4's. Links 3 and 4 are corrected together (aligned to link 4's stamp), and link 1 is
    bridged from link 3's corrected state at link 3's own stamp, carried to link 1's: the metre
    comes off exactly, and nothing moves it sideways (from link 3's state at the segment's stamp,
    taken for one at its own, link 3's tip would be 2 cm ahead)."""
    from companion.engine import CorrectionOut
    from companion.messages import STATE_FLAG_GPS_FAULT, LinkState

    n, vy, lag = 4, 1.0, 0.02
    engine = CompanionEngine(setup_for(n), start_center=(0.0, 0.0, 2.0))
    ok = STATE_FLAG_EKF_OK | STATE_FLAG_ARMED
    flags = (ok | STATE_FLAG_GPS_FAULT, STATE_FLAG_ARMED, ok, ok)
    corrections = []
    t = 0.0
    while t < 1.5:
        t = round(t + 0.02, 6)
        for row in range(n):
            stamp = t - (lag if row == 2 else 0.0)
            s = straight_state(row, n, stamp, dx=-1.0 if row == 0 else 0.0)
            engine.on_state(row, LinkState(row, stamp, s.p_w_m + [0.0, vy * stamp, 0.0], np.array([0.0, vy, 0.0]),
                                           s.q_wxyz, s.omega_b_rad_s, s.P), flags[row], t)
        corrections += [o.correction for o in of(CorrectionOut, engine.poll(t)) if o.row == 0]
    assert len(corrections) > 10 and engine.summary()["links"]["1"]["bridged_steps"] >= len(corrections)
    np.testing.assert_allclose(corrections[-1].dp_w_m, [1.0, 0.0, 0.0], atol=1e-6)

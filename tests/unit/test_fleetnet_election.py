"""Leader election of the global step on pure nodes (instant delivery, no session): failover and
return without two leaders in a cycle, the shift deadline, a healed partition, a restarted group
that follows the acting leader, and a lagging group that does not lead before the agreed hand-over
(the same over real Zenoh sessions: tests/integration/test_fleetnet_zenoh.py)."""

from __future__ import annotations

import numpy as np

from companion.fleetnet.leader import GlobalStepNode
from companion.messages import GlobalShift

from ..fleetnet_cases import PERIOD_US


# -- leader election, pure ------------------------------------------------------------------------------
def _drive(nodes, cycles, t0=0.0, alive=None):
    """Run ``cycles`` cycles on pure nodes with instant delivery; returns the leaders per cycle."""
    leaders = []
    now = t0
    live = [n for n in nodes if alive is None or n.group in alive]

    def deliver(shifts, at):
        for s in shifts:
            for node in live:
                node.on_shift(s, at)

    for k in cycles:
        cycle = k * PERIOD_US
        now += 0.05
        shifts, published = [], []
        for node in live:
            act = node.local_step(np.zeros(6), np.ones(6) * 0.1 * node.group, np.eye(6), cycle, now)
            published.append(act.boundary)
            shifts += act.shifts
        for report in published:
            for node in live:
                shifts += node.on_boundary(report, now + 0.001).shifts
        deliver(shifts, now + 0.002)
        late = [s for node in live for s in node.tick(now + 0.03).shifts]
        deliver(late, now + 0.031)
        leaders.append(sorted({s.leader_group for s in shifts + late}))
    return leaders, now


def test_election_failover_and_return_without_two_leaders_in_a_cycle():
    order = (1, 0, 2)
    nodes = [GlobalStepNode(g, 3, order, PERIOD_US, startup_s=0.1) for g in range(3)]
    for a in nodes:
        for b in nodes:
            a.on_liveliness(b.group, True, 0.0)
    leaders, now = _drive(nodes, range(1, 20))
    assert leaders[0] == []  # listening for an acting leader first
    assert all(ld == [1] for ld in leaders[1:])
    assert nodes[0].counts["global"] >= 15
    # the leader (group 2, index 1) disappears: group 1 (index 0) takes over at the next cycle
    for node in nodes:
        node.on_liveliness(1, False, now)
    leaders, now = _drive(nodes, range(20, 30), now, alive={0, 2})
    assert leaders[0] == [0] and all(ld == [0] for ld in leaders)
    # group 2 comes back as a new process: it follows, then gets leadership handed over at one cycle
    nodes[1] = GlobalStepNode(1, 3, order, PERIOD_US, startup_s=0.1)
    for a in nodes:
        for b in nodes:
            a.on_liveliness(b.group, True, now)
    leaders, now = _drive(nodes, range(30, 45), now)
    assert all(len(ld) <= 1 for ld in leaders), leaders
    assert leaders[-1] == [1]
    flat = [ld[0] for ld in leaders if ld]
    switch = flat.index(1)
    assert all(g == 0 for g in flat[:switch]) and all(g == 1 for g in flat[switch:])


def test_deadline_gives_local_only_and_two_leaders_resolve_to_the_preferred():
    node = GlobalStepNode(0, 2, (1, 0), PERIOD_US, shift_deadline_s=0.02, startup_s=0.0)
    node.on_liveliness(1, True, 0.0)
    act = node.local_step(np.zeros(6), np.zeros(6), np.eye(6), PERIOD_US, 0.0)
    assert not act.resolved and act.boundary is not None
    assert node.tick(0.01).resolved == []
    res = node.tick(0.021).resolved
    assert len(res) == 1 and res[0].shift is None and "deadline" in res[0].reason
    # both think they lead (a healed partition): the lower-ranked one yields on seeing the other's shift
    lower = GlobalStepNode(0, 2, (1, 0), PERIOD_US, startup_s=0.0)
    lower.acting = 0
    lower.on_liveliness(1, True, 1.0)
    lower.local_step(np.zeros(6), np.zeros(6), np.eye(6), 2 * PERIOD_US, 1.0)
    own = lower.tick(1.1).shifts
    assert own and own[0].leader_group == 0
    lower.on_shift(GlobalShift(1, 2 * PERIOD_US, (0,), np.zeros((1, 6)), hold_us=(0,)), 1.11)
    assert lower.counts["yielded"] == 1 and lower.leader_for(3 * PERIOD_US, 1.2) == 1
    assert lower.duplicates == [(2 * PERIOD_US, 0, 1, True)]  # the cycle, whose shift it applied, the second's


def test_a_restarted_group_that_has_not_stepped_yet_follows_the_acting_leader():
    """Group 1 (preferred) comes back while group 2 leads alone; before its first own cycle it
    sees group 2's checked shifts for cycles it has not reached: after its start-up listening it
    follows group 2 (which hands over at an agreed cycle) instead of leading at once."""
    rng = np.random.default_rng(6)
    g2 = GlobalStepNode(1, 2, (0, 1), PERIOD_US, startup_s=0.0)
    g2.on_liveliness(1, True, 0.0)
    g1 = GlobalStepNode(0, 2, (0, 1), PERIOD_US, startup_s=0.5)
    g1.start(10.0)
    g1.on_liveliness(0, True, 10.0)
    g1.on_liveliness(1, True, 10.0)
    for k in range(1, 12):  # 0.55 s of group 2 alone; group 1 hears every message but does not step
        cycle, now = (200 + k) * PERIOD_US, 10.0 + 0.05 * k
        act = g2.local_step(rng.normal(0, 0.01, 6), rng.normal(0, 0.01, 6), np.eye(6), cycle, now)
        g1.on_boundary(act.boundary, now + 0.001)
        act = act.merge(g2.tick(now + 0.03))
        for shift in act.shifts:
            g1.on_shift(shift, now + 0.031)
    assert g1.leader_for(212 * PERIOD_US, 10.6) == 1 and g1.acting == 1


def test_a_restarted_group_that_reaches_the_others_late_listens_before_it_leads():
    """Group 1 (preferred) restarts and steps alone, its session reaching group 2 (which leads)
    only after its own start-up listening is over: it listens again from group 2's coming up, so
    it follows group 2 instead of leading the next cycle beside it."""
    rng = np.random.default_rng(7)
    g2 = GlobalStepNode(1, 2, (0, 1), PERIOD_US, startup_s=0.0)
    g2.on_liveliness(1, True, 0.0)
    g2.acting = 1  # it led while group 1 was away
    g1 = GlobalStepNode(0, 2, (0, 1), PERIOD_US, startup_s=0.5)
    g1.start(10.0)
    g1.on_liveliness(1, True, 11.2)  # 1.2 s after it started
    g2.on_liveliness(0, True, 11.2)
    assert g1.leader_for(300 * PERIOD_US, 11.3) is None  # not itself: group 2 may be acting
    led = []

    def send(actions, node, now):
        for shift in actions.shifts:
            led.append((shift.cycle_us, shift.leader_group))
            (g2 if node is g1 else g1).on_shift(shift, now)

    for k in range(1, 8):
        cycle, now = (300 + k) * PERIOD_US, 11.2 + 0.05 * k
        a2 = g2.local_step(rng.normal(0, 0.01, 6), rng.normal(0, 0.01, 6), np.eye(6), cycle, now)
        a1 = g1.local_step(rng.normal(0, 0.01, 6), rng.normal(0, 0.01, 6), np.eye(6), cycle, now + 0.002)
        send(a2, g2, now + 0.003)
        send(a1, g1, now + 0.003)
        send(g1.on_boundary(a2.boundary, now + 0.003), g1, now + 0.004)
        send(g2.on_boundary(a1.boundary, now + 0.003), g2, now + 0.004)
        for node in (g1, g2):
            send(node.tick(now + 0.013), node, now + 0.014)
    # one leader per cycle: group 2, then group 1 from the cycle group 2 agreed to hand back at
    cycles = [c for c, _ in led]
    assert sorted(cycles) == [(300 + k) * PERIOD_US for k in range(1, 8)]
    leaders = [g for _, g in sorted(led)]
    assert leaders[0] == 1 and leaders[-1] == 0 and leaders == sorted(leaders, reverse=True)
    assert g1.counts["duplicate_shift"] == g2.counts["duplicate_shift"] == 0
    assert g1.counts["led"] + g2.counts["led"] == 7
    # with no group acting, a lone group that just met another leads after the listening
    alone = GlobalStepNode(0, 2, (0, 1), PERIOD_US, startup_s=0.5)
    alone.start(10.0)
    alone.on_liveliness(1, True, 11.2)
    assert alone.leader_for(300 * PERIOD_US, 11.5) is None and alone.leader_for(300 * PERIOD_US, 11.71) == 0


def test_a_returning_group_one_cycle_behind_does_not_lead_before_the_agreed_hand_over():
    """The hand-back to a returning preferred group (group 1) while it lags: group 2's boundary of
    the hand-over cycle reaches it before its own step of the cycle before. Asking who leads that
    later cycle must not move the hand-over earlier: group 2 leads up to the agreed cycle, group 1
    from it, never two leaders in one cycle (seen in fleet runs on a loaded 2-core machine)."""
    rng = np.random.default_rng(11)
    g2 = GlobalStepNode(1, 2, (0, 1), PERIOD_US, startup_s=0.0)
    g2.acting = 1  # it led while group 1 was away
    g1 = GlobalStepNode(0, 2, (0, 1), PERIOD_US, startup_s=0.1)
    for node in (g1, g2):
        node.start(10.0)
        node.on_liveliness(0, True, 10.0)
        node.on_liveliness(1, True, 10.0)
    leaders: dict[int, set[int]] = {}

    def boundary():
        return rng.normal(0, 0.01, 6), rng.normal(0, 0.01, 6), np.eye(6)

    def send(shifts, now):
        for s in shifts:
            leaders.setdefault(s.cycle_us, set()).add(s.leader_group)
            (g1 if s.leader_group == 1 else g2).on_shift(s, now)

    def on_time(k):
        cycle, now = k * PERIOD_US, 10.0 + 0.05 * (k - 200)
        a2 = g2.local_step(*boundary(), cycle, now)
        send(g1.on_boundary(a2.boundary, now + 0.001).shifts, now + 0.002)
        a1 = g1.local_step(*boundary(), cycle, now + 0.003)
        send(a1.shifts + g2.on_boundary(a1.boundary, now + 0.004).shifts, now + 0.005)
        send(g1.tick(now + 0.03).shifts + g2.tick(now + 0.03).shifts, now + 0.031)

    k = 201
    while g1.handover is None:  # group 2 leads and names group 1 for the hand-over
        on_time(k)
        k += 1
        assert k < 210
    assert g1.handover[0] == 0 and g2.handover == g1.handover
    first = g1.handover[1] // PERIOD_US
    while k < first - 1:
        on_time(k)
        k += 1
    # cycle first - 1: group 2 steps it and the hand-over cycle before group 1 steps the first
    cycle, now = k * PERIOD_US, 10.0 + 0.05 * (k - 200)
    a2 = g2.local_step(*boundary(), cycle, now)
    g1.on_boundary(a2.boundary, now + 0.001)
    solved = g2.tick(now + 0.015).shifts  # group 2 solves it alone (leader_wait_s)
    assert [s.leader_group for s in solved] == [1]
    a2 = g2.local_step(*boundary(), cycle + PERIOD_US, now + 0.02)
    g1.on_boundary(a2.boundary, now + 0.021)
    assert g1.leader_for(cycle + PERIOD_US, now + 0.022) == 0 and g1.leader_for(cycle, now + 0.022) == 1
    a1 = g1.local_step(*boundary(), cycle, now + 0.025)  # group 1, late, on the cycle before
    send(a1.shifts + g2.on_boundary(a1.boundary, now + 0.026).shifts + solved, now + 0.027)
    send(g1.tick(now + 0.045).shifts, now + 0.046)
    # the hand-over cycle and after: group 1 leads
    a1 = g1.local_step(*boundary(), cycle + PERIOD_US, now + 0.05)
    send(a1.shifts + g2.on_boundary(a1.boundary, now + 0.051).shifts, now + 0.052)
    for j in range(k + 2, k + 6):
        on_time(j)
    assert all(len(who) == 1 for who in leaders.values()), leaders
    assert leaders[cycle] == {1} and all(leaders[c] == {0} for c in leaders if c > cycle)
    assert g1.counts["duplicate_shift"] == g2.counts["duplicate_shift"] == 0
    assert g1.counts["rejected_shift"] == g2.counts["rejected_shift"] == 0
    assert g1.leader_log[-1][1] == 0 and g2.leader_log[-1][1] == 0

"""Trust in the global step of the semi-distributed companions, on pure nodes (instant delivery, no
session): a rogue on the bus sends fake shifts for this cycle or the next, forged boundaries,
shifts beyond the bounds, floods of uncheckable shifts and shifts in a silent leader's name; none
is applied, and a leader silent for three cycles is passed over (not one still listening at its
start). Codec, config, eq. 6 and election: tests/unit/test_fleetnet_*.py."""

from __future__ import annotations

import numpy as np

from companion.estimation.semi import GroupBoundary, global_step
from companion.fleetnet.leader import GlobalStepNode, PartBoundary
from companion.fleetnet.solve import solve_cycle
from companion.messages import GlobalShift, GroupBoundaryReport

from ..fleetnet_cases import PERIOD_US


# -- trust in the global step: a rogue on the bus ----------------------------------------------------------
def _cycle(nodes, k, rng, rogue_before=(), rogue_after=()):
    """One cycle on pure nodes with instant delivery; a rogue's messages are delivered before the
    groups publish (``rogue_before``) or between their boundaries and the leader's shift
    (``rogue_after``). Returns per node the Resolution of the cycle and the true eq. 6 shifts."""
    cycle = k * PERIOD_US
    now = 1.0 + 0.05 * k
    resolved = {n.group: [] for n in nodes}

    def deliver(msgs, at):
        for m in msgs:
            for node in nodes:
                act = node.on_shift(m, at) if isinstance(m, GlobalShift) else node.on_boundary(m, at)
                resolved[node.group] += act.resolved
                shifts.extend(act.shifts)

    shifts: list = []
    deliver(rogue_before, now - 0.001)
    published = []
    for node in nodes:
        act = node.local_step(rng.normal(0, 0.01, 6), rng.normal(0, 0.01, 6), np.eye(6) * (1 + node.group), cycle, now)
        published.append(act.boundary)
        resolved[node.group] += act.resolved
        shifts += act.shifts
    deliver(rogue_after, now + 0.0005)
    deliver(published, now + 0.001)
    real = list(shifts)
    shifts.clear()
    deliver(real, now + 0.002)
    for node in nodes:
        resolved[node.group] += node.tick(now + 0.03).resolved
    keys, truth = solve_cycle(published)
    return resolved, {g: shift for (g, _), shift in zip(keys, truth)}


def _fake(leader, cycle, groups, rng, scale=0.3):
    return GlobalShift(leader, cycle, tuple(groups), rng.normal(0, scale, (len(groups), 6)), hold_us=(0,) * len(groups))


def _two_groups():
    nodes = [GlobalStepNode(g, 2, (0, 1), PERIOD_US, startup_s=0.0) for g in range(2)]
    for a in nodes:
        for b in nodes:
            a.on_liveliness(b.group, True, 0.0)
    return nodes


def test_next_cycle_shifts_claiming_each_group_as_leader_are_never_applied():
    """Well-formed shifts for the next cycle, one claiming each group as the leader, before every
    cycle: none is applied, and both groups keep the true global step (they do not fall back to
    local-only corrections)."""
    rng = np.random.default_rng(1)
    nodes = _two_groups()
    applied = 0
    for k in range(1, 61):
        rogue = [_fake(g, (k + 1) * PERIOD_US, (0, 1), rng) for g in (0, 1)] if k > 5 else []
        resolved, truth = _cycle(nodes, k, rng, rogue_before=rogue)
        for g, res in resolved.items():
            assert len(res) == 1
            if res[0].shift is not None:
                np.testing.assert_allclose(res[0].shift, truth[g], atol=1e-12)  # only the true eq. 6
                applied += 1
    assert applied >= 2 * 59  # every cycle but the first, in both groups: the global step stayed on
    assert all(n.leader_log[-1][1] == 0 for n in nodes)
    assert nodes[1].rejections.get("not_pending", 0) + nodes[1].rejections.get("not_leader", 0) >= 55


def test_a_same_cycle_fake_shift_is_rejected_as_inconsistent():
    """A shift for the cycle the groups wait on, claiming the real leader, arriving before it."""
    rng = np.random.default_rng(2)
    nodes = _two_groups()
    _cycle(nodes, 1, rng)
    for k in range(2, 40):
        resolved, truth = _cycle(nodes, k, rng, rogue_after=[_fake(0, k * PERIOD_US, (0, 1), rng, 0.05)])
        res = resolved[1][0]
        assert res.shift is not None and np.allclose(res.shift, truth[1], atol=1e-12)
    assert nodes[1].rejections == {"inconsistent": 38}


def test_a_forged_boundary_leaves_its_group_out_and_no_fake_shift_gets_through():
    rng = np.random.default_rng(3)
    nodes = _two_groups()
    _cycle(nodes, 1, rng)
    for k in range(2, 20):
        forged = GroupBoundaryReport(0, k * PERIOD_US, np.ones(6), np.ones(6), np.eye(6))
        resolved, _ = _cycle(nodes, k, rng, rogue_before=[forged],
                             rogue_after=[_fake(0, k * PERIOD_US, (0, 1), rng, 0.05)])
        assert resolved[1][0].shift is None  # neither the fake nor the (uncheckable) real one
    assert nodes[1].counts["conflicting_boundary"] == 18


def test_shifts_beyond_the_bounds_are_rejected_and_a_silent_leader_is_passed_over():
    rng = np.random.default_rng(4)
    nodes = _two_groups()
    follower = nodes[1]
    _cycle(nodes, 1, rng)
    # a shift from the elected leader for the pending cycle, 5 m: rejected (no boundary to check it against)
    act = follower.local_step(np.zeros(6), np.zeros(6), np.eye(6), 2 * PERIOD_US, 2.0)
    assert act.boundary is not None
    big = GlobalShift(0, 2 * PERIOD_US, (1,), np.array([[5.0, 0, 0, 0, 0, 0]]), hold_us=(0,))
    assert not follower.on_shift(big, 2.001).resolved and follower.rejections == {"bounds": 1}
    # the leader's token stays but its shifts stop (a hung companion, or a rogue's token): after
    # three cycles without them the follower leads
    for k in range(3, 8):
        follower.local_step(np.zeros(6), np.zeros(6), np.eye(6), k * PERIOD_US, 2.0 + 0.05 * k)
        follower.tick(2.0 + 0.05 * k + 0.03)
    assert 0 in follower.muted and follower.leader_for(9 * PERIOD_US, 3.0) == 1


def test_a_flood_of_uncheckable_shifts_is_bounded():
    """Shifts for the pending cycle that list a boundary not received yet wait for it, at most
    four of them; the rest are dropped and counted."""
    rng = np.random.default_rng(5)
    nodes = _two_groups()
    follower = nodes[1]
    _cycle(nodes, 1, rng)
    follower.local_step(np.zeros(6), np.zeros(6), np.eye(6), 2 * PERIOD_US, 2.0)
    for _ in range(1000):
        follower.on_shift(_fake(0, 2 * PERIOD_US, (0, 1), rng, 0.05), 2.001)
    assert len(follower._held) == 4 and follower.rejections == {"unverifiable": 996}
    # the leader's boundary arrives: the held fakes are checked and rejected
    follower.on_boundary(GroupBoundaryReport(0, 2 * PERIOD_US, np.zeros(6), np.zeros(6), np.eye(6)), 2.002)
    assert not follower._held and follower.rejections["inconsistent"] == 4
    # the companion's summary reports them, by reason
    from companion.fleetnet.group import GroupLink
    from companion.fleetnet.hub import LocalHub

    report = GroupLink(follower, LocalHub(2, lambda: 2.0).join(1), lambda: 2.0).summary()["global_step"]
    assert report["rejected_shift"] == 1000 and report["rejected_shift_by_reason"] == {"unverifiable": 996,
                                                                                       "inconsistent": 4}


def test_a_leader_still_in_its_start_up_listening_is_not_passed_over():
    """Group 1 (preferred) joins after group 2 and listens for startup_s before it leads: its
    silence then is not the silence of a dead leader (group 2 must not take over for good)."""
    follower = GlobalStepNode(1, 2, (0, 1), PERIOD_US, startup_s=0.5)
    follower.start(0.0)
    follower.on_liveliness(0, True, 1.0)  # group 1's companion starts at 1.0 s
    for k in range(1, 10):  # 1.05 .. 1.45 s: inside its listening
        now = 1.0 + 0.05 * k
        follower.local_step(np.zeros(6), np.zeros(6), np.eye(6), k * PERIOD_US, now)
        follower.tick(now + 0.03)
    assert not follower.muted and follower.leader_for(11 * PERIOD_US, 1.5) == 0
    for k in range(10, 16):  # then it stays silent: a dead leader with its token still there
        now = 1.0 + 0.05 * k
        follower.local_step(np.zeros(6), np.zeros(6), np.eye(6), k * PERIOD_US, now)
        follower.tick(now + 0.03)
    assert 0 in follower.muted


def test_a_next_cycle_shift_that_leaves_a_group_out_cannot_make_it_local_only():
    """A well-formed shift for the next cycle from the expected leader, listing every group but
    the victim (as if the leader had solved without it): unverifiable before the cycle's
    boundaries exist, so it settles nothing and the victim keeps its global step."""
    rng = np.random.default_rng(4)
    nodes = [GlobalStepNode(g, 3, (1, 0, 2), PERIOD_US, startup_s=0.0) for g in range(3)]
    for a in nodes:
        for b in nodes:
            a.on_liveliness(b.group, True, 0.0)
    applied = {g: 0 for g in range(3)}
    for k in range(1, 41):
        rogue = [_fake(1, (k + 1) * PERIOD_US, groups, rng) for groups in ((0, 1), (1, 2), (0, 2))] if k > 5 else []
        resolved, truth = _cycle(nodes, k, rng, rogue_before=rogue)
        for g, res in resolved.items():
            if res and res[0].shift is not None:
                np.testing.assert_allclose(res[0].shift, truth[g], atol=1e-12)
                applied[g] += 1
    assert all(n >= 39 for n in applied.values()), applied
    assert sum(n.rejections.get("unverifiable", 0) for n in nodes) >= 2 * 35  # the leader ignores its own name


def test_forged_shifts_do_not_hide_a_silent_leader():
    """The elected leader's token stays but its shifts stop; a rogue keeps sending shifts in its
    name. They are not its shifts: the groups still pass it over after the silence cycles."""
    rng = np.random.default_rng(5)
    nodes = [GlobalStepNode(g, 2, (0, 1), PERIOD_US, startup_s=0.0) for g in range(2)]
    for a in nodes:
        for b in nodes:
            a.on_liveliness(b.group, True, 0.0)
    frozen = nodes[0]
    for k in range(1, 21):
        cycle, now = k * PERIOD_US, 1.0 + 0.05 * k
        act = nodes[1].local_step(rng.normal(0, 0.01, 6), rng.normal(0, 0.01, 6), np.eye(6), cycle, now)
        nodes[1].on_shift(_fake(0, cycle, (0, 1), rng), now + 0.001)  # forged in the frozen leader's name
        nodes[1].tick(now + 0.04)
        del act
    assert 0 in nodes[1].muted and frozen.group == 0


def test_a_split_group_is_solved_part_by_part_and_a_forged_part_count_leaves_it_out():
    """Three groups; group 2 reports two parts (a link down between them): the leader waits for
    both, joins the first to group 1 and the second to group 3, and each part gets its own shift
    (eq. 6 of its run). A report in group 2's name that disagrees on the number of parts is a
    conflict: group 2 is left out of that cycle."""
    nodes = [GlobalStepNode(g, 3, (0, 1, 2), PERIOD_US, startup_s=0.0) for g in range(3)]
    for a in nodes:
        for b in nodes:
            a.on_liveliness(b.group, True, 0.0)
    rng = np.random.default_rng(6)
    tip = lambda: rng.normal(0, 0.05, 6)  # noqa: E731
    left_part = PartBoundary(tip(), tip(), 2.0 * np.eye(6), joins_right=False)
    right_part = PartBoundary(tip(), tip(), 3.0 * np.eye(6), joins_left=False)
    cycle, now = PERIOD_US, 1.0
    a0 = nodes[0].local_step(tip(), tip(), np.eye(6), cycle, now)
    a2 = nodes[2].local_step(tip(), tip(), 4.0 * np.eye(6), cycle, now)
    a1 = nodes[1].local_parts([left_part, right_part], cycle, now)
    assert [(b.part, b.parts, b.joins_left, b.joins_right) for b in a1.boundaries] == [(0, 2, True, False),
                                                                                      (1, 2, False, True)]
    leader = nodes[0]
    for b in a2.boundaries + a1.boundaries[:1]:
        assert not leader.on_boundary(b, now + 0.001).shifts  # group 2's second part still missing
    (shift,) = leader.on_boundary(a1.boundaries[1], now + 0.001).shifts
    assert shift.keys == ((0, 0), (1, 0), (1, 1), (2, 0))
    runs = [[a0.boundary, a1.boundaries[0]], [a1.boundaries[1], a2.boundary]]
    want = np.concatenate([global_step([GroupBoundary(r.left_tip_pv_w, r.right_tip_pv_w, r.info_pv) for r in run])
                           for run in runs])
    np.testing.assert_allclose(shift.shift_pv_w, want, atol=1e-12)
    for node in nodes[1:]:
        for b in a0.boundaries + (a2.boundaries if node.group == 1 else a1.boundaries):
            node.on_boundary(b, now + 0.002)
    (res,) = nodes[1].on_shift(shift, now + 0.003).resolved
    assert res.global_applied and len(res.parts) == 2
    np.testing.assert_allclose(res.parts[0].shift, want[1], atol=1e-12)
    np.testing.assert_allclose(res.parts[1].shift, want[2], atol=1e-12)
    # next cycle: a forged one-part report in group 2's name beside its two parts
    cycle, now = 2 * PERIOD_US, 1.05
    a1 = nodes[1].local_parts([left_part, right_part], cycle, now)
    nodes[0].local_step(tip(), tip(), np.eye(6), cycle, now)
    forged = GroupBoundaryReport(1, cycle, np.zeros(6), np.zeros(6), np.eye(6))
    for b in [forged, *a1.boundaries]:
        leader.on_boundary(b, now + 0.001)
    assert leader.counts["conflicting_boundary"] == 1 and 1 in leader.conflicted[cycle]


def test_the_payload_queue_hands_over_in_order_and_counts_what_overflows():
    """A subscriber's callback queues (payload, key) pairs; take() hands them over oldest first;
    beyond the limit, samples are dropped and counted."""
    from types import SimpleNamespace

    from companion.fleetnet.payload_queue import PayloadQueue

    def sample(k: int):
        return SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: bytes([k])), key_expr=f"p/link/{k}/neighbour")

    q = PayloadQueue(limit=2)
    for k in range(3):
        q.on_sample(sample(k))
    assert list(q.take()) == [(b"\x00", "p/link/0/neighbour"), (b"\x01", "p/link/1/neighbour")] and q.overflow == 1
    q.on_sample(sample(5))
    assert list(q.take()) == [(b"\x05", "p/link/5/neighbour")] and list(q.take()) == []


def test_a_group_waiting_for_the_leaders_shift_sleeps_until_its_deadline():
    """A cycle that has waited leader_wait_s and another group leads gives no deadline in the past
    (a daemon that sleeps until the deadline would wake in a loop while the leader computes): the
    shift's deadline is next; the leader's own waited cycle is due at once; a group still in its
    startup window wakes when it ends (the clock alone may make it the leader)."""
    leader, follower = _two_groups()
    cycle, now = 20 * PERIOD_US, 1.0
    boundaries = [node.local_step(np.zeros(6), np.zeros(6), np.eye(6), cycle, now).boundary for node in (leader, follower)]
    follower.on_boundary(boundaries[0], now + 0.001)  # (the follower's is still on its way to the leader)
    later = now + follower.leader_wait_s + 0.005  # waited; the shift not here yet
    assert not follower.due(later) and not follower.tick(later).resolved
    assert follower.next_deadline_s(later) == now + follower.shift_deadline_s > later
    assert leader.due(later) and leader.next_deadline_s(later) <= later
    assert leader.tick(later).shifts  # (the leader solves it with what it has)
    fresh = GlobalStepNode(1, 2, (0, 1), PERIOD_US, startup_s=0.5)
    fresh.on_liveliness(0, True, now)
    fresh.on_liveliness(1, True, now)
    fresh.local_step(np.zeros(6), np.zeros(6), np.eye(6), cycle, now)
    fresh.on_boundary(boundaries[0], now + 0.001)
    waited = now + fresh.leader_wait_s + 0.001
    assert fresh.next_deadline_s(waited) == min(now + fresh.shift_deadline_s, now + fresh.startup_s)

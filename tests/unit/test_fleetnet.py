"""Zenoh layer of the semi-distributed companions, without a session: codec, config, eq. 6 over the
reported boundaries, leader election and trust in the global step on pure nodes (the same over real
Zenoh sessions: tests/integration/test_fleetnet_zenoh.py)."""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.configfile import ConfigError, build
from companion.corrections import compute_corrections, finish_step, local_step
from companion.estimation.semi import semi_distributed_apply
from companion.fleetnet import codec
from companion.fleetnet.bus import FleetBus, zenoh_config
from companion.fleetnet.config import ZenohConfig
from companion.fleetnet.leader import GlobalStepNode
from companion.fleetnet.solve import shift_covariance_terms, solve_cycle
from companion.messages import Correction, GlobalShift, GroupBoundaryReport, GroupPassiveLinks, LinkState, MessageError
from sitl.scenario import Scenario

from ..chains import perturbed_chain, random_covariances
from ..fleetnet_cases import LAYOUTS, PERIOD_US, chain_boundaries, equal, targets


# -- codec --------------------------------------------------------------------------------------------------
def _messages(rng):
    P = random_covariances(rng, 1)[0]
    info = np.linalg.inv(random_covariances(rng, 1)[0][:6, :6])
    q = rng.normal(size=4)
    return [
        LinkState(5, 12.345678, rng.normal(size=3), rng.normal(size=3), q / np.linalg.norm(q), rng.normal(size=3), P),
        Correction(2, 3.25, rng.normal(size=3), rng.normal(size=3), 0.01 * rng.normal(size=3), 4242),
        GroupBoundaryReport(1, 1_250_000, rng.normal(size=6), rng.normal(size=6), 0.5 * (info + info.T), 1234, 567),
        GroupBoundaryReport(2, 1_300_000, rng.normal(size=6), rng.normal(size=6), 0.5 * (info + info.T), 1234, 567,
                            _psd12(rng)),
        GlobalShift(1, 1_250_000, (0, 1, 3), rng.normal(size=(3, 6)), 0, 1_400_000, (10, 20, 30)),
        GlobalShift(2, 50_000, (2,), np.zeros((1, 6)), hold_us=(0,)),
        targets(rng, (0, 1, 2, 3, 4, 5, 6)),
        targets(rng, (2, 5)),
        GroupPassiveLinks(1, 20_060_000, (2,)),
        GroupPassiveLinks(0, 5_000_000, ()),
        GroupPassiveLinks(3, 2**40, (6, 7, 9)),
    ]


def _psd12(rng) -> np.ndarray:
    """A symmetric PSD 12 x 12 of rank 9 (a single link's tip covariance is singular)."""
    A = rng.normal(size=(12, 9))
    return A @ A.T


@pytest.mark.parametrize("seed", range(3))
def test_codec_round_trip_is_exact(seed):
    for msg in _messages(np.random.default_rng(seed)):
        out = codec.decode(codec.encode(msg))
        assert type(out) is type(msg)
        if isinstance(msg, LinkState):  # unit quaternion is renormalised, covariance symmetrised
            np.testing.assert_allclose(out.q_wxyz, msg.q_wxyz, atol=1e-15)
            np.testing.assert_allclose(out.P, 0.5 * (msg.P + msg.P.T), atol=0)
            assert out.link == msg.link and out.time_s == msg.time_s
        elif isinstance(msg, GroupBoundaryReport) and msg.tip_cov_pv is not None:  # symmetrised
            np.testing.assert_allclose(out.tip_cov_pv, msg.tip_cov_pv, atol=1e-12)
            assert equal(replace(out, tip_cov_pv=None), replace(msg, tip_cov_pv=None))
        else:
            assert equal(out, msg), msg


def test_codec_rejects_malformed_payloads_with_the_reason():
    good = codec.encode(_messages(np.random.default_rng(0))[2])
    bad_info = GroupBoundaryReport(0, 0, np.zeros(6), np.zeros(6), -np.eye(6))
    nan_tip = GroupBoundaryReport(0, 0, np.full(6, np.nan), np.zeros(6), np.eye(6))
    cases = {
        b"": "shorter than",
        b"XXXX" + good[4:]: "magic",
        good[:4] + bytes([9]) + good[5:]: "version 9",
        good[:5] + bytes([77]) + good[6:]: "unknown message type 77",
        good[:-3]: "truncated",
        good + b"\0": "trailing",
        codec.encode(bad_info): "info_pv: not positive definite",
        codec.encode(nan_tip): "left_tip_pv_w: non-finite",
        codec.encode(replace(nan_tip, left_tip_pv_w=np.zeros(6), tip_cov_pv=-np.eye(12))):
            "tip_cov_pv: not positive semidefinite",
        codec.encode(replace(nan_tip, left_tip_pv_w=np.zeros(6), tip_cov_pv=np.full((12, 12), np.nan))):
            "tip_cov_pv: non-finite",
        good[:-1] + bytes([2]): "tip_cov_pv: presence flag 2",  # (good has no tip covariance: flag 0 last)
        codec.encode(GlobalShift(0, 0, (2, 1), np.zeros((2, 6)), hold_us=(0, 0))): "increasing",
        codec.encode(replace(targets(np.random.default_rng(2), (0, 1)), links=(1, 1))): "ChainTargets.links",
        codec.encode(replace(targets(np.random.default_rng(2), (0, 1)), q_wxyz=np.ones((2, 4)))): r"q_wxyz\[link 1\]",
        codec.encode(replace(targets(np.random.default_rng(2), (0, 1)), a_w_m_s2=np.full((2, 3), np.inf))):
            "a_w_m_s2: non-finite",
        codec.encode(GroupPassiveLinks(1, 0, (3, 2))): "GroupPassiveLinks.links",
        codec.encode(replace(_messages(np.random.default_rng(3))[0], time_s=float("nan"))): "LinkState.time_s: non-finite",
        codec.encode(replace(_messages(np.random.default_rng(3))[1], ekf_time_s=float("inf"))):
            "Correction.ekf_time_s: non-finite",
        codec.encode(GroupPassiveLinks(1, 0, (2, 2))): "GroupPassiveLinks.links",
    }
    for payload, reason in cases.items():
        with pytest.raises(MessageError, match=reason):
            codec.decode(payload)
    rng = np.random.default_rng(1)
    for _ in range(300):  # random bytes behind a valid header never raise anything else
        body = rng.integers(0, 256, size=int(rng.integers(0, 400)), dtype=np.uint8).tobytes()
        try:
            codec.decode(good[:6] + body)
        except MessageError:
            pass


# -- config ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("zenoh_section, key, reason", [
    ({"prefix": "fleet/*"}, "zenoh.prefix", "wildcards"),
    ({"endpoints": ["tcp/10.0.0.1:7447", "tcp/10.0.0.2"]}, "zenoh.endpoints", "not a Zenoh endpoint"),
    ({"endpoints": ["tcp/10.0.0.1:7447"] * 3}, "zenoh.endpoints", "its own endpoint"),
    ({"endpoints": ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]}, "zenoh", "2 endpoints for 3 groups"),
    ({"leader_order": [2, 2, 1]}, "zenoh", "leader_order"),
    ({"shift_deadline_ms": 60.0}, "zenoh", "step period"),
    ({"mode": "client"}, "zenoh.connect", "router"),
    ({"tls": {"root_ca_certificate": "/etc/ca.pem"}, "endpoints": ["tls/a:1", "tls/b:1", "tls/c:1"],
      "leaderorder": [1, 2, 3]}, "zenoh.leaderorder", "unknown key"),
    ({"endpoints": ["tls/a:1", "tls/b:1", "tls/c:1"]}, "zenoh.endpoints", r"need \[zenoh.tls\]"),
])
def test_zenoh_config_errors_name_the_key(zenoh_section, key, reason):
    data = {"name": "t", "skeleton": {"n_links": 7}, "companion": {"groups": [[1, 2], [3, 4, 5], [6, 7]]},
            "zenoh": zenoh_section}
    with pytest.raises(ConfigError, match=reason) as err:
        build(Scenario, data, file="t.toml")
    assert f"t.toml: {key}" in str(err.value)


def test_access_control_file_is_read_and_checked_at_open(tmp_path):
    missing = ZenohConfig(endpoints=("tcp/127.0.0.1:1", "tcp/127.0.0.1:2"), access_control=str(tmp_path / "acl.json5"))
    with pytest.raises(ConfigError, match="zenoh.access_control: cannot read"):
        FleetBus(missing, "t", 0, 2)
    bad = tmp_path / "bad.json5"
    bad.write_text("{ enabled: true, rules: [ }")
    with pytest.raises(ConfigError, match="zenoh.access_control: Zenoh rejected access_control"):
        FleetBus(replace(missing, access_control=str(bad)), "t", 0, 2)
    good = tmp_path / "acl.json5"
    good.write_text('{ enabled: false, default_permission: "deny" }')
    zc = zenoh_config(replace(missing, access_control=str(good)), 0, 2)
    assert '"deny"' in zc.get_json("access_control/default_permission")


def test_default_leader_order_is_middle_out_and_tls_files_are_checked_at_open(tmp_path):
    assert ZenohConfig().order(3) == (1, 0, 2)
    assert ZenohConfig().order(4) == (1, 2, 0, 3)
    assert ZenohConfig(leader_order=(3, 1, 2)).order(3) == (2, 0, 1)
    cfg = ZenohConfig(endpoints=("tls/127.0.0.1:1", "tls/127.0.0.1:2"),
                      tls=build(type(ZenohConfig().tls), {"root_ca_certificate": str(tmp_path / "missing.pem")}, file="x"))
    with pytest.raises(ConfigError, match="zenoh.tls.root_ca_certificate: no such file"):
        FleetBus(cfg, "t", 0, 2)


# -- eq. 6 over groups, pure ----------------------------------------------------------------------------


@pytest.mark.parametrize("groups", LAYOUTS)
def test_solve_cycle_is_eq6_and_a_missing_group_splits_the_chain(groups):
    ref, reports = chain_boundaries(3, groups)
    got_groups, shifts = solve_cycle(reports[::-1])
    assert got_groups == tuple(range(len(groups)))
    np.testing.assert_allclose(shifts, ref.shifts, atol=1e-12)
    if len(groups) >= 3:
        present = [r for r in reports if r.group != 1]
        got_groups, shifts = solve_cycle(present)
        assert 1 not in got_groups
        np.testing.assert_allclose(shifts[0], 0.0, atol=1e-12)  # group 0 alone: nothing to close
        rest = solve_cycle(reports[2:])[1]
        np.testing.assert_allclose(shifts[1:], rest, atol=1e-12)


def test_one_cycles_eq6_is_solved_once_and_shared_read_only(monkeypatch):
    """The leader's solution, the followers' checks and every group's covariance terms of one
    cycle solve the same boundaries: computed once (three groups in one process, as in batch
    mode), the same numbers as a fresh solution, shared read-only; a changed number is solved anew."""
    from companion.estimation.semi import global_solution
    from companion.fleetnet import solve

    groups = ((0, 1), (2, 3, 4), (5, 6))
    n = 7
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(5), n)
    ref = semi_distributed_apply(p, v, q, w, d, P, groups)
    A = np.random.default_rng(6).normal(scale=0.1, size=(len(groups), 12, 12))
    covs = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(12)  # SPD tip covariances
    reports = [GroupBoundaryReport(g, PERIOD_US, b.left_tip, b.right_tip, b.info_pv, tip_cov_pv=covs[g])
               for g, b in enumerate(ref.boundaries)]
    calls = []
    monkeypatch.setattr(solve, "global_solution", lambda bs: calls.append(len(bs)) or global_solution(bs))
    solve._SOLUTIONS.clear()
    _, shifts = solve_cycle(reports)
    terms = [shift_covariance_terms(reports[::-1], g) for g in range(len(groups))]
    assert calls == [3]
    fresh = global_solution([solve._boundary(r) for r in reports])
    np.testing.assert_array_equal(shifts, fresh.shifts)
    for g, (gain, cov) in enumerate(terms):
        np.testing.assert_array_equal(gain, fresh.gains[g])
        np.testing.assert_array_equal(cov, fresh.shift_cov[g])
        assert not gain.flags.writeable and not cov.flags.writeable
    changed = [replace(reports[1], info_pv=2.0 * reports[1].info_pv)] + [reports[0], reports[2]]
    _, other = solve_cycle(changed)
    assert calls == [3, 3]
    assert not np.array_equal(other, shifts)
    np.testing.assert_array_equal(other, global_solution([solve._boundary(r) for r in sorted(changed, key=lambda r: r.group)]).shifts)


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


# -- the global step's halves, through the wire codec -----------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(st.integers(1, 4), min_size=2, max_size=6))
def test_networked_shifts_close_every_group_joint(seed, sizes):
    """Property: for any layout, the shifts solved from the reports (as the leader does) make the
    right tip of each group meet the left tip of the next, in position and velocity."""
    groups, start = [], 0
    for k in sizes:
        groups.append(tuple(range(start, start + k)))
        start += k
    ref, reports = chain_boundaries(seed, tuple(groups))
    decoded = [codec.decode(codec.encode(r)) for r in reports]
    got_groups, shifts = solve_cycle(decoded)
    np.testing.assert_allclose(shifts, ref.shifts, atol=1e-9)
    for g in range(len(groups) - 1):
        gap = (decoded[g].right_tip_pv_w + shifts[g]) - (decoded[g + 1].left_tip_pv_w + shifts[g + 1])
        np.testing.assert_allclose(gap, 0.0, atol=1e-9)


@pytest.mark.parametrize("groups", LAYOUTS)
def test_group_halves_equal_the_in_process_step(groups):
    """local_step per group, eq. 6 from the reports (through the wire codec), finish_step ==
    compute_corrections (one process), covariance carried through the shift included."""
    n = groups[-1][-1] + 1
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(21), n)
    states = [LinkState(i, 3.0, p[i], v[i], q[i], w[i], P[i]) for i in range(n)]
    ref, ref_corr = compute_corrections(states, d, groups)
    steps = [local_step([states[i] for i in g], d[list(g)], t=3.0) for g in groups]
    reports = [codec.decode(codec.encode(GroupBoundaryReport(
        k, 3_000_000, s.boundary.left_tip, s.boundary.right_tip, s.boundary.info_pv, tip_cov_pv=s.boundary.tip_cov)))
        for k, s in enumerate(steps)]
    _, shifts = solve_cycle(reports)
    for k, g in enumerate(groups):
        gain, cov = shift_covariance_terms(reports, k)
        p_out, v_out, q_out, P_out, corr = finish_step([states[i] for i in g], steps[k], shifts[k], 0, gain, cov)
        np.testing.assert_allclose(p_out, ref.p[list(g)], atol=1e-9)
        np.testing.assert_allclose(v_out, ref.v[list(g)], atol=1e-9)
        np.testing.assert_allclose(q_out, ref.q[list(g)], atol=1e-9)
        np.testing.assert_allclose(P_out, ref.P[list(g)], atol=1e-12)
        if len(groups) > 1:  # the shift moved the covariance away from the local step's
            assert np.abs(P_out - steps[k].result.P).max() > 1e-4
        for c, rc in zip(corr, [ref_corr[i] for i in g]):
            np.testing.assert_allclose(c.dp_w_m, rc.dp_w_m, atol=1e-9)
            np.testing.assert_allclose(c.dtheta_w_rad, rc.dtheta_w_rad, atol=1e-9)


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
    groups, truth = solve_cycle(published)
    return resolved, dict(zip(groups, truth))


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


def test_a_users_file_others_can_read_or_without_the_group_is_refused(tmp_path):
    from companion.fleetnet.config import new_users_file

    users = tmp_path / "u.txt"
    new_users_file(users, 2)
    cfg = ZenohConfig(users_file=str(users))
    with pytest.raises(ConfigError, match="no user companion-g3"):
        zenoh_config(cfg, 2, 3)
    os.chmod(users, 0o644)
    with pytest.raises(ConfigError, match="readable by others"):
        zenoh_config(cfg, 0, 2)


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

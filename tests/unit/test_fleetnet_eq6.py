"""Eq. 6 of the semi-distributed companions over the reported boundaries, pure: the leader's solution
of a cycle (solved once, shared read-only), the shifts closing every group joint through the wire
codec, and each group's halves of the step equal to the step in one process."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.corrections import compute_corrections, finish_step, local_step
from companion.estimation.semi import semi_distributed_apply
from companion.fleetnet import codec
from companion.fleetnet.solve import shift_covariance_terms, solve_cycle
from companion.messages import GroupBoundaryReport, LinkState

from ..chains import perturbed_chain
from ..fleetnet_cases import LAYOUTS, PERIOD_US, chain_boundaries


# -- eq. 6 over groups, pure ----------------------------------------------------------------------------


@pytest.mark.parametrize("groups", LAYOUTS)
def test_solve_cycle_is_eq6_and_a_missing_group_splits_the_chain(groups):
    ref, reports = chain_boundaries(3, groups)
    got, shifts = solve_cycle(reports[::-1])
    assert got == tuple((g, 0) for g in range(len(groups)))
    np.testing.assert_allclose(shifts, ref.shifts, atol=1e-12)
    if len(groups) >= 3:
        present = [r for r in reports if r.group != 1]
        got, shifts = solve_cycle(present)
        assert (1, 0) not in got
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

"""Null-space modulation (2.15) of control allocation: at most one rotor per side within the margin,
the closest feasible point, the stored xi''; and the continuity of lambda_gamma (2.17) on slow
pitch sweeps."""

import numpy as np
import pytest

from companion.skeleton.rotors import NU, R_SIDE, SIDES
from link_firmware_sim.allocation import (
    MARGIN_TOL_N,
    Allocator,
    gradual_selective_mapping,
    infinity_norm_allocation,
    selective_modulation,
)

from ..allocation_cases import (
    B,
    B_PINV,
    B_RED,
    EPS0,
    EPS1,
    GEOM,
    N_B,
    below_margin_per_side,
    check_allocator_step,
    hover_wrench,
    near_zero_wrenches,
    random_wrenches,
    ry,
    rz,
)


# ------------------------------------------------------------------------------------------
# (2.15): null-space modulation
# ------------------------------------------------------------------------------------------


def test_45_degree_pitch_hover_has_at_most_one_near_zero_rotor_per_side():
    U = hover_wrench(ry(np.pi / 4))
    alloc = Allocator(GEOM)
    r = check_allocator_step(alloc, U)
    # Without modulation, four rotors (two per side) sit at zero thrust (sec. 2.4.2).
    assert below_margin_per_side(r.lambda_alpha) == [2, 2]
    np.testing.assert_allclose(r.lambda_alpha[[0, 2, 4, 6]], 0.0, atol=1e-9)
    assert max(below_margin_per_side(r.lambda_beta)) <= 1
    # Modulation only moves along the kernel, by the smallest amount: one margin width.
    np.testing.assert_allclose(np.abs(alloc.xi_pre), EPS1, atol=1e-9)


def test_constructed_near_zero_wrenches_are_modulated():
    for U in near_zero_wrenches(50, seed=41):
        lam_o, xi1, lam_a = infinity_norm_allocation(B_PINV, U, NU)
        assert below_margin_per_side(lam_a) == [2, 2]
        xi2 = selective_modulation(lam_o, xi1, np.zeros(2), NU, EPS1)
        lam_b = lam_o + N_B @ (xi1 + xi2)
        assert max(below_margin_per_side(lam_b)) <= 1
        assert np.all(xi2 != 0.0)


def _brute_force_modulation(b, xi_pre, step=2e-4):
    """Closest feasible xi'' on a dense grid; b = nu-scaled lambda_alpha of one side."""
    span = np.max(np.abs(b + xi_pre)) + EPS1 + step  # beyond this everything is clear
    grid = xi_pre + np.arange(-span, span + step / 2, step)
    feasible = np.sum(np.abs(b[None, :] + grid[:, None]) < EPS1, axis=1) <= 1
    return np.min(np.abs(grid[feasible] - xi_pre))


def test_modulation_is_the_exact_closest_feasible_point():
    rng = np.random.default_rng(51)
    moved = 0
    for _ in range(60):
        lam_o = B_PINV @ random_wrenches(1, seed=int(rng.integers(1 << 30)))[0] * rng.uniform(0.02, 0.3)
        _, xi1, _ = infinity_norm_allocation(B_PINV, B @ lam_o, NU)
        xi_pre = rng.normal(0.0, 1.0, 2)
        xi2 = selective_modulation(lam_o, xi1, xi_pre, NU, EPS1)
        for s, side in enumerate(SIDES):
            b = NU * lam_o[side] + xi1[s]
            moved += xi2[s] != xi_pre[s]
            assert np.sum(np.abs(b + xi2[s]) < EPS1 - MARGIN_TOL_N) <= 1
            best = _brute_force_modulation(b, xi_pre[s])
            dist = abs(xi2[s] - xi_pre[s])
            assert best - 2e-4 - 1e-9 <= dist <= best + 1e-9
            if np.sum(np.abs(b + xi_pre[s]) < EPS1) <= 1:
                assert xi2[s] == xi_pre[s]  # no needless motion
    assert 30 <= moved <= 90  # both branches exercised


def test_modulation_can_jump_when_the_feasible_gap_closes():
    # Characterisation of the exact argmin of (2.15) (found on a random wrench trajectory): on the
    # r-side rotors 1 and 3 bracket a thin feasible gap holding xi''_pre; once their margins overlap
    # the gap is gone and the closest feasible point is the far end of rotor 4's margin, so xi''
    # jumps by ~0.36 N. See the continuity notes of selective_modulation.
    xi_pre = np.array([-0.7577, 0.0])
    for b, expected in (([-0.0423, -1.567, 1.567, 1.186], -0.7577), ([-0.0267, -1.560, 1.560, 1.1946], -0.3946)):
        # Realisable: b = nu * lambda_o_r + xi'_r with max(b) + min(b) = 0 (2.12) and
        # sum(nu * lambda_o_r) = 0 (lambda_o orthogonal to the kernel); the l-side is clear.
        b = np.array(b)
        lam = np.concatenate((NU * (b - b.mean()), NU * np.array([3.0, -3.0, 2.0, -2.0])))
        U = B @ lam
        lam_o, xi1, lam_a = infinity_norm_allocation(B_PINV, U, NU)
        np.testing.assert_allclose(NU * lam_a[R_SIDE], b, atol=1e-9)
        xi2 = selective_modulation(lam_o, xi1, xi_pre, NU, EPS1)
        assert xi2[0] == pytest.approx(expected, abs=1e-9)
        assert xi2[1] == 0.0
        assert np.sum(np.abs(b + xi2[0]) < EPS1 - MARGIN_TOL_N) == 1


def test_allocator_keeps_xi_pre_and_reset_clears_it():
    alloc = Allocator(GEOM)
    U = hover_wrench(ry(np.pi / 4))
    r1 = alloc.allocate(U)
    xi = alloc.xi_pre
    assert np.all(xi != 0.0)
    r2 = alloc.allocate(U)
    np.testing.assert_array_equal(alloc.xi_pre, xi)
    np.testing.assert_array_equal(r1.lambda_beta, r2.lambda_beta)
    # A nearby wrench for which the stored xi'' is still feasible keeps it (no needless motion).
    alloc.allocate(U + np.array([0.05, 0.0, 0.05, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(alloc.xi_pre, xi)
    alloc.reset()
    np.testing.assert_array_equal(alloc.xi_pre, [0.0, 0.0])
    # From a clear hover (level) xi'' stays 0 and lambda_beta = lambda_gamma = lambda_alpha.
    r = alloc.allocate(hover_wrench(np.eye(3)))
    np.testing.assert_array_equal(alloc.xi_pre, [0.0, 0.0])
    np.testing.assert_allclose(r.lambda_gamma, r.lambda_alpha, atol=1e-12)
    assert r.e == (1.0, 1.0) and r.near_zero == (-1, -1)


# ------------------------------------------------------------------------------------------
# Continuity of lambda_gamma on slow sweeps (2.17)
# ------------------------------------------------------------------------------------------


def _sweep(path, n):
    alloc = Allocator(GEOM)
    Us = np.array([path(s) for s in np.linspace(0.0, 1.0, n)])
    rs, xi2 = [], []
    for U in Us:
        rs.append(alloc.allocate(U))
        xi2.append(alloc.xi_pre)
    return Us, rs, np.array(xi2)


def _feasible(b, xi):
    """The constraint of (2.15) for one side: at most one |b_i + xi| below eps1."""
    return np.sum(np.abs(b + xi) < EPS1 - MARGIN_TOL_N) <= 1


def _forced_jump(U, xi_prev, radius):
    """Whether (2.15) forces some side's xi'' to move farther than ``radius`` from ``xi_prev``.

    The feasible set is a union of closed intervals bounded by the endpoints -b_i +- eps1, so
    no feasible point lies within ``radius`` iff ``xi_prev`` and every endpoint inside the window
    are infeasible (independent of the implementation's search).
    """
    lam_o, xi1, _ = infinity_norm_allocation(B_PINV, U, NU)
    for s, side in enumerate(SIDES):
        b = NU * lam_o[side] + xi1[s]
        ends = np.concatenate((-b - EPS1, -b + EPS1))
        window = ends[np.abs(ends - xi_prev[s]) <= radius]
        if not _feasible(b, xi_prev[s]) and not any(_feasible(b, x) for x in window):
            return True
    return False


def _step_sizes(Us, rs):
    """Per step: ||delta lambda_o||_inf, ||delta lambda_beta||_inf, ||delta lambda_gamma||_inf, ||delta U||_2."""
    lam = {k: np.array([getattr(r, k) for r in rs]) for k in ("lambda_o", "lambda_beta", "lambda_gamma")}
    d = {k: np.max(np.abs(np.diff(v, axis=0)), axis=1) for k, v in lam.items()}
    return d["lambda_o"], d["lambda_beta"], d["lambda_gamma"], np.linalg.norm(np.diff(Us, axis=0), axis=1)


def _gamma_step_bound(Us, rs, d_beta, d_u):
    r"""Per-step bound on ||delta lambda_gamma||_inf given the lambda_beta step (2.17).

    Per side lambda_gamma_s = (1 - e) P_j U + e lambda_beta_s, P_j the side rows of B^+_{\j}
    (2.18). With D = ||lambda_beta_s - P_j U||_inf at the active j (0 if the side is clear):
    * same j: delta = (1 - e') P_j dU + e' d(lambda_beta) + de (lambda_beta - P_j U), and e is
      1/(eps1 - eps0)-Lipschitz in min|lambda_beta_s|, so |de| <= ||d lambda_beta|| / (eps1 - eps0);
    * j changes (j -> j', or clear <-> near): argmin|lambda_beta_s| switches only where two rotors
      tie, and at most one is below eps1 after (2.15), so both 1 - e and 1 - e' are
      <= ||d lambda_beta|| / (eps1 - eps0) and delta = e' d(lambda_beta) + (1 - e')(P_j' U' -
      lambda_beta) + (1 - e)(lambda_beta - P_j U).
    Both cases: ||delta|| <= rho ||dU|| + ||d beta|| (1 + (D + D' + ||d beta||) / (eps1 - eps0)),
    rho the largest row norm of the reduced pseudo-inverses.
    """
    rho = np.max(np.linalg.norm(B_RED, axis=2))
    dist = np.zeros(len(rs))
    for i, (U, r) in enumerate(zip(Us, rs)):
        for s, side in enumerate(SIDES):
            j = r.near_zero[s]
            if j >= 0:
                dist[i] = max(dist[i], np.max(np.abs(r.lambda_beta[side] - B_RED[j][side] @ U)))
    return rho * d_u + d_beta * (1.0 + (dist[:-1] + dist[1:] + d_beta) / (EPS1 - EPS0))


PITCH_SWEEP = [
    # Pitch 0 -> 90 deg through the 45-deg intersection of zero-thrust lines (Fig. 2-4, 2-6).
    lambda s: hover_wrench(ry(s * np.pi / 2), (0.1, -0.05, 0.02)),
    # Same with a body yaw wobble and a varying torque.
    lambda s: hover_wrench(ry(s * np.pi / 2) @ rz(0.4 * np.sin(6 * s)), 0.5 * np.sin(2 * np.pi * s + np.arange(3))),
]


@pytest.mark.parametrize(("path", "n_forced"), list(zip(PITCH_SWEEP, (0, 1))), ids=["pitch", "pitch-yaw-torque"])
def test_lambda_gamma_continuous_on_slow_pitch_sweeps(path, n_forced):
    """lambda_beta moves by <= 4 ||d lambda_o|| per step except where (2.15) itself forces a jump,
    and lambda_gamma obeys the bound of :func:`_gamma_step_bound` at every step.

    lambda_beta bound: xi' is the mid-range of the nu-scaled lambda_o, so |d xi'| <= d_o :=
    ||d lambda_o||_inf and the forbidden intervals of (2.15) move by <= 2 d_o; xi'' stays or is
    pushed to the nearest (moved) endpoint, <= 2 d_o away, unless the feasible component holding
    it vanishes (a rotor inside the margin squeezed by two neighbours whose margins meet). Then
    every solution of (2.15) must jump: such steps are certified by :func:`_forced_jump`.
    """
    n = 4000
    Us, rs, xi2 = _sweep(path, n)
    d_o, d_beta, d_gamma, d_u = _step_sizes(Us, rs)
    smooth = d_beta <= 4.0 * d_o + 1e-12
    forced = np.flatnonzero(~smooth)
    assert len(forced) == n_forced
    for k in forced:
        assert _forced_jump(Us[k + 1], xi2[k], 2.0 * d_o[k])
    assert np.all(d_gamma <= _gamma_step_bound(Us, rs, d_beta, d_u) + 1e-12)
    # The sweep exercised the full fade-out (e = 0) and full use (e = 1) on both sides.
    e = np.array([r.e for r in rs])
    assert e.min(axis=0).tolist() == [0.0, 0.0]
    assert e.max(axis=0).tolist() == [1.0, 1.0]
    # Exactness along the whole sweep (Prop. 2).
    np.testing.assert_allclose(np.array([B @ r.lambda_gamma for r in rs]), Us, atol=1e-9)
    if n_forced == 0:
        # Lipschitz, not just bounded: halving the step halves the largest change.
        _, rs2, _ = _sweep(path, 2 * n)
        assert np.max(_step_sizes(Us, rs2)[2]) <= 0.55 * np.max(d_gamma)


def test_hard_switching_would_break_the_gamma_bound():
    # The bound above is meaningful: switching the near-zero rotor off abruptly at eps1 (e in {0, 1})
    # instead of fading it between eps0 and eps1 violates it on the pitch sweep.
    Us, rs, xi2 = _sweep(PITCH_SWEEP[0], 4000)
    _, d_beta, _, d_u = _step_sizes(Us, rs)
    bound = _gamma_step_bound(Us, rs, d_beta, d_u)
    hard = []
    for U, r, x2 in zip(Us, rs, xi2):
        _, xi1, _ = infinity_norm_allocation(B_PINV, U, NU)
        e_hard = tuple(0.0 if j >= 0 else 1.0 for j in r.near_zero)
        hard.append(gradual_selective_mapping(B_PINV, B_RED, U, NU, xi1 + x2, e_hard, r.near_zero))
    d_hard = np.max(np.abs(np.diff(np.array(hard), axis=0)), axis=1)
    assert np.max(d_hard - bound) > 0.1

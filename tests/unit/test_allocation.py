"""Control allocation with selective mapping (thesis sec. 2.4): geometry (Table 2.1, eq. 2.1,
2.11), Prop. 1 (2.12), modulation (2.15), gradual selective mapping (2.17) and Prop. 2."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from companion.skeleton.rotors import L_SIDE, N_ROTORS, NU, R_SIDE, SIDES, W_FORCE, W_TORQUE, RotorGeometry
from link_firmware_sim.allocation import (
    MARGIN_TOL_N,
    AllocationParams,
    Allocator,
    gradual_selective_mapping,
    infinity_norm_allocation,
    pseudo_inverse,
    reduced_pseudo_inverse,
    reduced_pseudo_inverses,
    selective_mapping_weights,
    selective_modulation,
    scaled_to_limit,
)

GEOM = RotorGeometry.odar()
B = GEOM.mapping_matrix()
B_PINV = pseudo_inverse(B)
B_RED = reduced_pseudo_inverses(B)
PARAMS = AllocationParams()
EPS0, EPS1, TMAX = PARAMS.eps0_n, PARAMS.eps1_n, PARAMS.thrust_max_n
N_B = np.zeros((N_ROTORS, 2))
N_B[R_SIDE, 0] = NU
N_B[L_SIDE, 1] = NU
MASS_KG, G = 1.8, 9.81

wrench = st.tuples(
    *[st.floats(-40.0, 40.0) for _ in range(3)], *[st.floats(-5.0, 5.0) for _ in range(3)]
).map(np.array)


def _random_wrenches(n, seed):
    rng = np.random.default_rng(seed)
    return np.hstack((rng.normal(0.0, 15.0, (n, 3)), rng.normal(0.0, 2.0, (n, 3))))


def _ry(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(psi):
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _hover_wrench(R, torque=(0.0, 0.0, 0.0)):
    """U = [R^T m g e3; tau] (eq. 2.8) for a 1.8 kg link hovering at attitude R."""
    return np.concatenate((R.T @ np.array([0.0, 0.0, MASS_KG * G]), torque))


def _near_zero_wrenches(n, seed):
    """Wrenches whose lambda_alpha has two rotors per side inside the margin eps1.

    lambda_o = B^+ U is any vector orthogonal to the kernel N_B (2.13), i.e. with
    sum(nu * lambda_o_s) = 0 per side. Per side a = nu * lambda_o_s = [p, d1, d2, -(p+d1+d2)]
    (shuffled) with |d| small: xi' = (d1 + d2) / 2 and lambda_alpha = nu (a + xi') has the d
    rotors at |d_i + (d1 + d2)/2| < eps1.
    """
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        lam = np.empty(N_ROTORS)
        for side in SIDES:
            p = rng.choice([-1.0, 1.0]) * rng.uniform(1.5, 6.0)
            d1, d2 = rng.uniform(-0.3, 0.3, 2)
            a = rng.permutation([p, d1, d2, -(p + d1 + d2)])
            lam[side] = NU * a
        out.append(B @ lam)
    return out


def _below_margin_per_side(lam):
    mag = np.abs(lam)
    return [int(np.sum(mag[side] < EPS1 - 10 * MARGIN_TOL_N)) for side in SIDES]


# ------------------------------------------------------------------------------------------
# Geometry: Table 2.1, eq. (2.1), (2.11)
# ------------------------------------------------------------------------------------------


def test_modified_design_matches_thesis_and_has_null_structure():
    t = GEOM.torque_per_thrust()
    thesis_t = np.array([[-0.18, -0.16, 0.21], [-0.18, 0.38, 0.01], [-0.18, -0.38, -0.01], [-0.18, 0.16, -0.21]])
    np.testing.assert_allclose(t[R_SIDE], thesis_t, atol=0.01)
    # Pair symmetry (sec. 2.2.2): u_{j+4} = u_j, t_{j+4} = -t_j.
    np.testing.assert_allclose(GEOM.directions[L_SIDE], GEOM.directions[R_SIDE])
    np.testing.assert_allclose(t[L_SIDE], -t[R_SIDE], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(GEOM.directions, axis=1), 1.0)
    np.testing.assert_array_equal(GEOM.spin, [-1, -1, -1, -1, 1, 1, 1, 1])
    assert GEOM.has_null_structure()
    assert B.shape == (6, 8)
    assert np.linalg.matrix_rank(B) == 6
    # (2.13): the kernel of B is blkdiag(nu, nu).
    np.testing.assert_allclose(B @ N_B, 0.0, atol=1e-12)
    np.testing.assert_allclose(B[W_FORCE], np.vstack([GEOM.directions.T]))
    np.testing.assert_allclose(B[W_TORQUE], t.T)


def test_table_design_as_printed_lacks_null_structure():
    g = RotorGeometry.odar(sigma1=+1)
    t = g.torque_per_thrust()
    np.testing.assert_allclose(t[0], [-0.15, -0.15, 0.24], atol=0.01)
    np.testing.assert_allclose(t[1:4], GEOM.torque_per_thrust()[1:4])  # only t1 (and t5) change
    assert not g.has_null_structure()
    assert np.linalg.matrix_rank(g.mapping_matrix()) == 6
    residual = g.mapping_matrix()[W_TORQUE, R_SIDE] @ NU
    assert np.max(np.abs(residual)) > 0.01  # 2 gamma u_1, not a rounding issue
    with pytest.raises(ValueError, match=r"\(2.11\)"):
        Allocator(g)
    with pytest.raises(ValueError, match=r"\(2.11\)"):
        Allocator(g, AllocationParams(selective_mapping=False))


@pytest.mark.parametrize("x_scale", [0.5, 1.0, 1.5, 3.0])
@pytest.mark.parametrize("gamma", [0.0, 0.02, 0.05])
def test_null_structure_kept_for_scaled_links_and_drag_ratios(x_scale, gamma):
    g = RotorGeometry.odar(drag_ratio=gamma, x_scale=x_scale)
    assert g.has_null_structure()
    assert np.linalg.matrix_rank(g.mapping_matrix()) == 6
    np.testing.assert_allclose(g.positions_m[0], [0.40 * x_scale, -0.17, 0.17])
    np.testing.assert_allclose(g.positions_m[L_SIDE], -g.positions_m[R_SIDE])


def test_geometry_is_immutable_and_validated():
    with pytest.raises(ValueError):
        GEOM.directions[0, 0] = 1.0
    with pytest.raises(ValueError, match="drag_ratio"):
        RotorGeometry.odar(drag_ratio=-0.01)
    with pytest.raises(ValueError, match="sigma1"):
        RotorGeometry.odar(sigma1=0)
    with pytest.raises(ValueError, match="x_scale"):
        RotorGeometry.odar(x_scale=0.0)
    with pytest.raises(ValueError, match="unit"):
        RotorGeometry(GEOM.directions * 2.0, GEOM.positions_m, GEOM.spin, 0.02)
    with pytest.raises(ValueError, match="spin"):
        RotorGeometry(GEOM.directions, GEOM.positions_m, np.zeros(8), 0.02)
    with pytest.raises(ValueError, match=r"\(8, 3\)"):
        RotorGeometry(GEOM.directions[:6], GEOM.positions_m, GEOM.spin, 0.02)


# ------------------------------------------------------------------------------------------
# Prop. 1: infinity-norm allocation (2.10), (2.12)
# ------------------------------------------------------------------------------------------


def _linprog_min_max(U):
    """min t s.t. B lambda = U, -t <= lambda_i <= t (the min-max problem (2.10))."""
    n = N_ROTORS
    c = np.zeros(n + 1)
    c[-1] = 1.0
    eye = np.eye(n)
    ones = np.ones((n, 1))
    A_ub = np.vstack((np.hstack((eye, -ones)), np.hstack((-eye, -ones))))
    A_eq = np.hstack((B, np.zeros((6, 1))))
    res = linprog(c, A_ub=A_ub, b_ub=np.zeros(2 * n), A_eq=A_eq, b_eq=U, bounds=(None, None), method="highs")
    assert res.status == 0
    return res.fun


def _check_prop1(U):
    lam_o, xi1, lam_a = infinity_norm_allocation(B_PINV, U, NU)
    np.testing.assert_allclose(lam_o, B_PINV @ U)
    np.testing.assert_allclose(lam_a, lam_o + N_B @ xi1, atol=1e-12)
    np.testing.assert_allclose(B @ lam_a, U, atol=1e-9)
    opt = _linprog_min_max(U)
    assert abs(np.max(np.abs(lam_a)) - opt) <= 1e-6 * max(opt, 1e-3)
    # The infinity norm is never worse than the two-norm solution's.
    assert np.max(np.abs(lam_a)) <= np.max(np.abs(lam_o)) + 1e-12


def test_prop1_matches_linprog_on_random_wrenches():
    for U in _random_wrenches(40, seed=11):
        _check_prop1(U)
    for U in _near_zero_wrenches(10, seed=12):
        _check_prop1(U)


@settings(max_examples=40, deadline=None)
@given(wrench)
def test_prop1_matches_linprog_hypothesis(U):
    _check_prop1(U)


def test_prop1_balances_extremes_per_side():
    # (2.12): with xi' the nu-scaled side values are centred, max + min = 0.
    for U in _random_wrenches(20, seed=13):
        _, _, lam_a = infinity_norm_allocation(B_PINV, U, NU)
        for side in SIDES:
            v = NU * lam_a[side]
            assert abs(v.max() + v.min()) < 1e-12


# ------------------------------------------------------------------------------------------
# Prop. 2: decoupling (2.18)-(2.19) and exactness of (2.17)
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("j", range(4))
@pytest.mark.parametrize("k", range(4, 8))
def test_decoupling_property(j, k):
    both = reduced_pseudo_inverse(B, (j, k))
    np.testing.assert_allclose(both[R_SIDE], B_RED[j][R_SIDE], atol=1e-12)
    np.testing.assert_allclose(both[L_SIDE], B_RED[k][L_SIDE], atol=1e-12)
    # (2.19): excluding an r-side rotor leaves the l-side rows of B^+ unchanged and vice versa.
    np.testing.assert_allclose(B_RED[j][L_SIDE], B_PINV[L_SIDE], atol=1e-12)
    np.testing.assert_allclose(B_RED[k][R_SIDE], B_PINV[R_SIDE], atol=1e-12)
    for red, i in ((both, j), (both, k), (B_RED[j], j)):
        np.testing.assert_allclose(B @ red, np.eye(6), atol=1e-12)
        assert np.all(red[i] == 0.0)


def test_decoupling_fails_without_null_structure():
    # Sanity check that the test above can fail: the printed Table 2.1 (sigma1=+1) does not decouple.
    Bt = RotorGeometry.odar(sigma1=+1).mapping_matrix()
    both = reduced_pseudo_inverse(Bt, (0, 5))
    assert np.max(np.abs(both[R_SIDE] - reduced_pseudo_inverse(Bt, (0,))[R_SIDE])) > 1e-4


def test_prop2_exact_on_grid_of_weights_and_near_zero_rotors():
    grid = np.linspace(0.0, 1.0, 6)
    rng = np.random.default_rng(21)
    for U in _random_wrenches(3, seed=22):
        xi = rng.normal(0.0, 2.0, 2)
        for j in range(4):
            for k in range(4, 8):
                for e_r in grid:
                    for e_l in grid:
                        lam = gradual_selective_mapping(B_PINV, B_RED, U, NU, xi, (e_r, e_l), (j, k))
                        np.testing.assert_allclose(B @ lam, U, atol=1e-9)
                # e = 0 removes the near-zero rotors entirely.
                lam0 = gradual_selective_mapping(B_PINV, B_RED, U, NU, xi, (0.0, 0.0), (j, k))
                assert lam0[j] == 0.0 and lam0[k] == 0.0
                # e = 1 is lambda_beta.
                lam1 = gradual_selective_mapping(B_PINV, B_RED, U, NU, xi, (1.0, 1.0), (j, k))
                np.testing.assert_allclose(lam1, B_PINV @ U + N_B @ xi, atol=1e-12)


def test_prop2_mapping_not_exact_without_null_structure():
    # Sanity check that exactness depends on (2.11): with sigma1=+1 the blended map misses U.
    Bt = RotorGeometry.odar(sigma1=+1).mapping_matrix()
    U = _random_wrenches(1, seed=23)[0]
    lam = gradual_selective_mapping(
        pseudo_inverse(Bt), reduced_pseudo_inverses(Bt), U, NU, np.array([0.7, -0.4]), (0.5, 0.5), (0, 5)
    )
    assert np.max(np.abs(Bt @ lam - U)) > 1e-3


def _check_allocator_step(alloc, U_asked, keep=None):
    """One allocate() call checked against the pure functions and Props. 1-2, (2.15), (2.17), and
    the limit (AllocationParams.scale_to_limit): every rotor of lambda_alpha and lambda_beta
    within it, all of U when U is feasible (Prop. 1's infinity norm within it), else
    keep + s (U - keep) on the limit (keep = 0 when it is beyond the rotors itself)."""
    xi_pre = alloc.xi_pre
    r = alloc.allocate(U_asked, keep)
    U, scale = scaled_to_limit(B_PINV, U_asked, TMAX, keep=keep)
    np.testing.assert_allclose(r.wrench, U, atol=1e-12)
    assert r.scale == pytest.approx(scale, abs=1e-12)
    inf_norm = lambda V: np.max(np.abs(infinity_norm_allocation(B_PINV, V, NU)[2]))  # noqa: E731
    feasible = inf_norm(U_asked) <= TMAX
    if feasible:
        assert r.scale == 1.0 and np.array_equal(r.wrench, U_asked)
    else:  # on the limit; what is kept whole, the rest in its direction
        K = np.zeros(6) if keep is None or inf_norm(keep) > TMAX else keep
        assert 0.0 <= scale < 1.0 and inf_norm(U) == pytest.approx(TMAX, abs=1e-9)
        np.testing.assert_allclose(U, K + scale * (U_asked - K), atol=1e-12)
    lam_o, xi1, lam_a = infinity_norm_allocation(B_PINV, U, NU)
    xi2 = selective_modulation(lam_o, xi1, xi_pre, NU, EPS1, TMAX)
    np.testing.assert_allclose(alloc.xi_pre, xi2, atol=1e-12)
    np.testing.assert_allclose(r.lambda_o, lam_o, atol=1e-12)
    np.testing.assert_allclose(r.lambda_alpha, lam_a, atol=1e-12)
    np.testing.assert_allclose(r.lambda_beta, lam_o + N_B @ (xi1 + xi2), atol=1e-12)
    e, near = selective_mapping_weights(r.lambda_beta, EPS0, EPS1)
    assert r.near_zero == near
    lam_g = gradual_selective_mapping(B_PINV, B_RED, U, NU, xi1 + xi2, r.e, r.near_zero)
    np.testing.assert_allclose(r.lambda_gamma, lam_g, atol=1e-9)
    # (2.17)'s weight, raised only as far as the limit needs (a rotor of that side on it); the
    # fade is affine in e, so any smaller weight would take that rotor past the limit
    faded = False
    for s, side in enumerate(SIDES):
        if r.e[s] != pytest.approx(e[s], abs=1e-12):
            faded = True
            assert r.e[s] > e[s] and np.max(np.abs(r.lambda_gamma[side])) == pytest.approx(TMAX, abs=1e-9)
            smaller = gradual_selective_mapping(B_PINV, B_RED, U, NU, xi1 + xi2,
                                                tuple(x - 1e-6 if k == s else x for k, x in enumerate(r.e)), r.near_zero)
            assert np.max(np.abs(smaller[side])) > TMAX
    assert np.max(np.abs(r.lambda_gamma)) <= TMAX + 1e-9
    # Prop. 2 and (2.15).
    for lam in (r.lambda_alpha, r.lambda_beta, r.lambda_gamma):
        np.testing.assert_allclose(B @ lam, U, atol=1e-9)
    assert np.max(np.abs(r.lambda_alpha)) <= TMAX + 1e-9 and np.max(np.abs(r.lambda_beta)) <= TMAX + 1e-9
    # (2.15)'s margin, unless the limit leaves no room for it: then (checked on a dense grid of
    # the xi'' the limit allows) the second-nearest-zero rotor as far from zero as it can be
    for s, c in enumerate(_below_margin_per_side(r.lambda_beta)):
        if c <= 1:
            continue
        b = NU * r.lambda_beta[SIDES[s]]  # nu-scaled, xi'' included: the grid is of moves of it
        grid = np.linspace(-TMAX - b.min(), TMAX - b.max(), 4001)
        mags = np.sort(np.abs(b[None, :] + grid[:, None]), axis=1)
        assert np.all(np.sum(mags < EPS1 - MARGIN_TOL_N, axis=1) >= 2), "a point within the limit clears the margin"
        assert np.sort(np.abs(b))[1] >= mags[:, 1].max() - 1e-9
    for s, side in enumerate(SIDES):
        if r.near_zero[s] == -1:
            assert r.e[s] == 1.0
            assert np.all(np.abs(r.lambda_beta[side]) >= EPS1 - MARGIN_TOL_N)
        else:
            assert side.start <= r.near_zero[s] < side.stop
            assert abs(r.lambda_beta[r.near_zero[s]]) < EPS1
            if r.e[s] == 0.0:
                assert r.lambda_gamma[r.near_zero[s]] == 0.0
    np.testing.assert_array_equal(r.command_n, np.clip(r.lambda_gamma, -TMAX, TMAX))
    np.testing.assert_allclose(B @ r.command_n, U, atol=1e-9)  # within the limit: nothing clipped
    assert r.saturated == (not feasible or faded or bool(np.any(np.abs(r.lambda_gamma) > TMAX)))
    return r


@settings(max_examples=60, deadline=None)
@given(st.lists(wrench, min_size=1, max_size=8))
def test_allocator_exact_and_consistent_hypothesis(Us):
    alloc = Allocator(GEOM)
    for U in Us:
        _check_allocator_step(alloc, U)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(wrench, st.floats(-3.2, 3.2), st.floats(-1.5, 1.5), st.floats(-3.2, 3.2)),
                min_size=1, max_size=8))
def test_allocator_keeping_the_weight_hypothesis(steps):
    """The firmware's call: the link's weight at its attitude kept whole at the limit."""
    alloc = Allocator(GEOM)
    for U, yaw, pitch, roll in steps:
        R = _rz(yaw) @ _ry(pitch) @ np.array([[1.0, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
        keep = _hover_wrench(R)
        r = _check_allocator_step(alloc, _hover_wrench(R) + 4.0 * U, keep)
        hover = np.max(np.abs(infinity_norm_allocation(B_PINV, keep, NU)[2])) <= TMAX  # (not past 50-60 deg of roll)
        if r.scale < 1.0 and hover:  # the weight is carried: B command = keep + s (U - keep)
            np.testing.assert_allclose(B @ r.command_n - keep, r.scale * 4.0 * U, atol=1e-9)


def test_a_far_target_gives_way_above_the_weight():
    """A target 30 m off asks eq. 1 for 300 N sideways (it has no limit of its own): clipped rotor
    by rotor that came out as 43 N sideways and no lift; the whole wrench scaled, 2.4 N of lift
    for 17.7 N of weight. With the weight kept (the firmware's call) the link holds its height and
    pushes sideways with what is left (25.8 N)."""
    weight = _hover_wrench(np.eye(3))
    U = weight + np.array([300.0, 0, 0, 0, 0, 0])
    clipped = Allocator(GEOM, AllocationParams(scale_to_limit=False)).allocate(U).command_n
    whole = Allocator(GEOM).allocate(U).command_n
    kept = Allocator(GEOM).allocate(U, weight)
    assert (B @ clipped)[2] < 0.1 and (B @ whole)[2] < 0.2 * weight[2]
    np.testing.assert_allclose(B @ kept.command_n, weight + kept.scale * (U - weight), atol=1e-9)
    assert (B @ kept.command_n)[2] == pytest.approx(weight[2], abs=1e-9) and (B @ kept.command_n)[0] > 25.0
    assert np.max(np.abs(kept.command_n)) == pytest.approx(TMAX, abs=1e-9)
    with pytest.raises(ValueError, match="keep"):
        Allocator(GEOM).allocate(U, [1.0, 2.0])


def test_allocator_exact_and_consistent_on_seeded_sequences():
    alloc = Allocator(GEOM)
    near_zero_seen = set()
    for U in list(_random_wrenches(100, seed=31)) + _near_zero_wrenches(100, seed=32):
        r = _check_allocator_step(alloc, U)
        near_zero_seen.update(r.near_zero)
    # The near-zero path of (2.17) was exercised on both sides.
    assert near_zero_seen & set(range(4)) and near_zero_seen & set(range(4, 8))


# ------------------------------------------------------------------------------------------
# (2.15): null-space modulation
# ------------------------------------------------------------------------------------------


def test_45_degree_pitch_hover_has_at_most_one_near_zero_rotor_per_side():
    U = _hover_wrench(_ry(np.pi / 4))
    alloc = Allocator(GEOM)
    r = _check_allocator_step(alloc, U)
    # Without modulation, four rotors (two per side) sit at zero thrust (sec. 2.4.2).
    assert _below_margin_per_side(r.lambda_alpha) == [2, 2]
    np.testing.assert_allclose(r.lambda_alpha[[0, 2, 4, 6]], 0.0, atol=1e-9)
    assert max(_below_margin_per_side(r.lambda_beta)) <= 1
    # Modulation only moves along the kernel, by the smallest amount: one margin width.
    np.testing.assert_allclose(np.abs(alloc.xi_pre), EPS1, atol=1e-9)


def test_constructed_near_zero_wrenches_are_modulated():
    for U in _near_zero_wrenches(50, seed=41):
        lam_o, xi1, lam_a = infinity_norm_allocation(B_PINV, U, NU)
        assert _below_margin_per_side(lam_a) == [2, 2]
        xi2 = selective_modulation(lam_o, xi1, np.zeros(2), NU, EPS1)
        lam_b = lam_o + N_B @ (xi1 + xi2)
        assert max(_below_margin_per_side(lam_b)) <= 1
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
        lam_o = B_PINV @ _random_wrenches(1, seed=int(rng.integers(1 << 30)))[0] * rng.uniform(0.02, 0.3)
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
    U = _hover_wrench(_ry(np.pi / 4))
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
    r = alloc.allocate(_hover_wrench(np.eye(3)))
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
    lambda s: _hover_wrench(_ry(s * np.pi / 2), (0.1, -0.05, 0.02)),
    # Same with a body yaw wobble and a varying torque.
    lambda s: _hover_wrench(_ry(s * np.pi / 2) @ _rz(0.4 * np.sin(6 * s)), 0.5 * np.sin(2 * np.pi * s + np.arange(3))),
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


# ------------------------------------------------------------------------------------------
# Selective mapping off, saturation, validation
# ------------------------------------------------------------------------------------------


def test_selective_mapping_off_sends_clipped_lambda_alpha():
    alloc = Allocator(GEOM, AllocationParams(selective_mapping=False, scale_to_limit=False))
    Us = list(_random_wrenches(30, seed=61)) + [_hover_wrench(_ry(np.pi / 4)), np.array([80.0, 0, 0, 0, 0, 0])]
    for U in Us:
        r = alloc.allocate(U)
        _, _, lam_a = infinity_norm_allocation(B_PINV, U, NU)
        np.testing.assert_allclose(r.lambda_alpha, lam_a, atol=1e-12)
        np.testing.assert_array_equal(r.lambda_beta, r.lambda_alpha)
        np.testing.assert_array_equal(r.lambda_gamma, r.lambda_alpha)
        np.testing.assert_array_equal(r.command_n, np.clip(r.lambda_alpha, -TMAX, TMAX))
        assert r.e == (1.0, 1.0) and r.near_zero == (-1, -1)
        assert r.saturated == bool(np.any(np.abs(r.lambda_alpha) > TMAX))
    np.testing.assert_array_equal(alloc.xi_pre, [0.0, 0.0])
    assert r.saturated  # the 80 N wrench


def test_selective_mapping_off_with_the_limit():
    alloc = Allocator(GEOM, AllocationParams(selective_mapping=False))
    for U in list(_random_wrenches(30, seed=61)) + [np.array([80.0, 0, 0, 0, 0, 0])]:
        r = alloc.allocate(U)
        V, scale = scaled_to_limit(B_PINV, U, TMAX)
        _, _, lam_a = infinity_norm_allocation(B_PINV, V, NU)
        np.testing.assert_allclose(r.lambda_alpha, lam_a, atol=1e-12)
        np.testing.assert_array_equal(r.lambda_gamma, r.lambda_alpha)
        assert np.max(np.abs(r.lambda_alpha)) <= TMAX + 1e-9
        np.testing.assert_array_equal(r.command_n, np.clip(r.lambda_alpha, -TMAX, TMAX))
        assert r.saturated == (r.scale != 1.0) and r.scale == pytest.approx(scale, abs=1e-12)
    assert r.saturated and r.scale == pytest.approx(TMAX / np.max(np.abs(infinity_norm_allocation(B_PINV, U, NU)[2])))
    np.testing.assert_allclose(B @ r.command_n, r.wrench, atol=1e-9)  # the 80 N wrench, scaled


def test_scaling_to_the_limit_keeps_the_wrench_a_link_carrying_a_neighbour_asks_for():
    """The case that made it (three_link, link 2 unpowered and carried): each neighbour holds its
    own weight plus half of link 2's (8.8 N) at its joint, 0.5 m from its centre (4.41 N m), with
    8 N rotors: 96 % of the limit when level. Tilted 20 deg, with the attitude loop asking 1.5 N m
    more, it is beyond the limit. Clipped rotor by rotor, the wrench produced loses 5 % of its
    pitch torque and gains a side force (5-15 % of the torque from 0 to 30 deg, the link tips
    further); scaled, force and torque give way alike and nothing else is produced."""
    carry = np.r_[0.0, 0.0, MASS_KG * G + 8.83]
    level = np.r_[carry, 0.0, 4.41, 0.0]
    assert np.max(np.abs(infinity_norm_allocation(B_PINV, level, NU)[2])) == pytest.approx(7.71, abs=0.01)
    U = np.r_[_ry(np.radians(20.0)).T @ carry, 0.0, 4.41 + 1.5, 0.0]
    clipped = Allocator(GEOM, AllocationParams(scale_to_limit=False)).allocate(U)
    scaled = Allocator(GEOM).allocate(U)
    assert clipped.saturated and scaled.saturated
    produced_clipped, produced_scaled = B @ clipped.command_n, B @ scaled.command_n
    assert produced_clipped[4] < 0.96 * U[4] and abs(produced_clipped[1]) > 0.15  # torque lost, a side force
    assert 0.9 < scaled.scale < 1.0
    np.testing.assert_allclose(produced_scaled, scaled.scale * U, atol=1e-9)
    assert np.max(np.abs(scaled.command_n)) <= TMAX


def test_the_limit_bounds_the_modulation_and_the_fade():
    """(2.15) keeps xi'' where it is while three rotors are clear of eps1 (it is not pulled back to
    the infinity-norm optimum): after a modulation at light load, a heavier feasible wrench (Prop.
    1's norm 7.9 N of 8) puts a rotor past the limit, and the clip distorts the wrench (0.18 N
    (N m) on average, up to 0.46). With scale_to_limit the limit bounds xi'' too, and where (2.17)'s
    fade of the near-zero rotor would shift thrust past it (121 of these 200 cases), the fade's
    weight is raised just enough: the command is the wrench, exactly."""
    thesis = Allocator(GEOM, AllocationParams(scale_to_limit=False))
    bounded = Allocator(GEOM)
    rng = np.random.default_rng(5)
    beta_over, raised, err_thesis, err_bounded = 0, 0, [], []
    for _ in range(200):
        light = _near_zero_wrenches(1, int(rng.integers(1 << 30)))[0]
        heavy = light * (7.9 / np.max(np.abs(infinity_norm_allocation(B_PINV, light, NU)[2])))
        for alloc in (thesis, bounded):
            alloc.reset()
            alloc.allocate(light)
        t, r = thesis.allocate(heavy), _check_allocator_step(bounded, heavy)
        beta_over += np.max(np.abs(t.lambda_beta)) > TMAX
        raised += r.saturated
        assert np.max(np.abs(r.lambda_beta)) <= TMAX + 1e-9 and r.scale == 1.0
        err_thesis.append(np.max(np.abs(B @ t.command_n - heavy)))
        err_bounded.append(np.max(np.abs(B @ r.command_n - heavy)))
    assert beta_over > 180  # the thesis's modulation alone: past the limit
    assert raised > 100 and np.mean(err_thesis) > 0.1 and max(err_bounded) < 1e-9


def test_where_the_limit_leaves_no_room_for_the_margin():
    """Found by hypothesis: after a modulation to xi'' = -0.435, a wrench beyond the limit (scaled
    by 0.757) leaves the l side's xi'' in [-0.619, 0.619], where two rotors are always within eps1
    of zero. Kept at -0.435 they would be at 0.335 and 0.593 N; the second is taken to 0.776 N
    (xi'' at the limit's end), as far from zero as the limit allows."""
    alloc = Allocator(GEOM)
    for U in ([0.0] * 6, [0.0, 9.0, 0.0, 5.0, 0.0, 0.0], [26.0, 12.0, 1.0, 0.0, 0.0, 0.5]):
        r = _check_allocator_step(alloc, np.array(U))
    assert r.scale == pytest.approx(0.7575, abs=1e-4)
    left = np.sort(np.abs(r.lambda_beta[L_SIDE]))
    assert _below_margin_per_side(r.lambda_beta)[1] == 2 and left[1] == pytest.approx(0.776, abs=1e-3)
    assert np.max(np.abs(r.lambda_beta[L_SIDE])) == pytest.approx(TMAX, abs=1e-9)


def test_saturation_flag_and_clipping():
    alloc = Allocator(GEOM, AllocationParams(thrust_max_n=5.0, scale_to_limit=False))
    r = alloc.allocate(np.array([60.0, 0.0, 20.0, 0.0, 0.0, 0.0]))
    assert r.saturated
    assert np.max(np.abs(r.lambda_gamma)) > 5.0
    assert np.max(np.abs(r.command_n)) == 5.0
    np.testing.assert_array_equal(r.command_n, np.clip(r.lambda_gamma, -5.0, 5.0))
    np.testing.assert_allclose(B @ r.lambda_gamma, [60.0, 0.0, 20.0, 0.0, 0.0, 0.0], atol=1e-9)
    r = alloc.allocate(_hover_wrench(np.eye(3)))
    assert not r.saturated
    np.testing.assert_array_equal(r.command_n, r.lambda_gamma)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"eps0_n": 0.8, "eps1_n": 0.8}, "eps0_n must be < eps1_n"),
        ({"eps0_n": 0.9, "eps1_n": 0.8}, "eps0_n must be < eps1_n"),
        ({"eps0_n": 0.0}, "eps0_n must be > 0"),
        ({"eps0_n": -0.1}, "eps0_n must be > 0"),
        ({"thrust_max_n": 0.8}, "thrust_max_n must be > eps1_n"),
        ({"thrust_max_n": float("nan")}, "finite"),
        ({"eps1_n": float("inf")}, "finite"),
    ],
)
def test_params_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        AllocationParams(**kwargs)


def test_allocate_rejects_bad_wrench_without_touching_state():
    alloc = Allocator(GEOM)
    alloc.allocate(_hover_wrench(_ry(np.pi / 4)))
    xi = alloc.xi_pre
    for bad in (np.zeros(5), np.array([0.0, 0.0, np.nan, 0.0, 0.0, 0.0]), np.array([np.inf, 0, 0, 0, 0, 0])):
        with pytest.raises(ValueError, match="finite"):
            alloc.allocate(bad)
    np.testing.assert_array_equal(alloc.xi_pre, xi)


def test_pseudo_inverse_rejects_rank_deficient_mapping():
    Bd = B.copy()
    Bd[5] = Bd[4]
    with pytest.raises(ValueError, match="rank"):
        pseudo_inverse(Bd)
    np.testing.assert_allclose(B @ B_PINV, np.eye(6), atol=1e-12)

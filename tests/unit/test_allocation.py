"""Control allocation with selective mapping (thesis sec. 2.4), its pure functions: geometry (Table
2.1, eq. 2.1, 2.11), Prop. 1 (2.12), gradual selective mapping (2.17) and Prop. 2, validation of the
parameters and inputs. Modulation (2.15) and the sweeps: test_allocation_modulation.py; the
Allocator step by step: test_allocator.py."""

import numpy as np
import pytest
from hypothesis import given, settings
from scipy.optimize import linprog

from companion.skeleton.rotors import L_SIDE, N_ROTORS, NU, R_SIDE, SIDES, W_FORCE, W_TORQUE, RotorGeometry
from link_firmware_sim.allocation import (
    AllocationParams,
    Allocator,
    gradual_selective_mapping,
    infinity_norm_allocation,
    pseudo_inverse,
    reduced_pseudo_inverse,
    reduced_pseudo_inverses,
)

from ..allocation_cases import (
    B,
    B_PINV,
    B_RED,
    GEOM,
    N_B,
    hover_wrench,
    near_zero_wrenches,
    random_wrenches,
    ry,
    wrench,
)


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
    for U in random_wrenches(40, seed=11):
        _check_prop1(U)
    for U in near_zero_wrenches(10, seed=12):
        _check_prop1(U)


@settings(max_examples=40, deadline=None)
@given(wrench)
def test_prop1_matches_linprog_hypothesis(U):
    _check_prop1(U)


def test_prop1_balances_extremes_per_side():
    # (2.12): with xi' the nu-scaled side values are centred, max + min = 0.
    for U in random_wrenches(20, seed=13):
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
    for U in random_wrenches(3, seed=22):
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
    U = random_wrenches(1, seed=23)[0]
    lam = gradual_selective_mapping(
        pseudo_inverse(Bt), reduced_pseudo_inverses(Bt), U, NU, np.array([0.7, -0.4]), (0.5, 0.5), (0, 5)
    )
    assert np.max(np.abs(Bt @ lam - U)) > 1e-3


# ------------------------------------------------------------------------------------------
# Validation
# ------------------------------------------------------------------------------------------


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
    alloc.allocate(hover_wrench(ry(np.pi / 4)))
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

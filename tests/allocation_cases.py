"""Cases shared by the tests of control allocation (tests/unit/test_allocation*.py and
tests/unit/test_allocator.py): the modified ODAR geometry and its pseudo-inverses, wrenches (random,
hovering, with rotors near zero thrust), and one Allocator step checked against the pure functions."""

import numpy as np
import pytest
from hypothesis import strategies as st

from companion.skeleton.rotors import L_SIDE, N_ROTORS, NU, R_SIDE, SIDES, RotorGeometry
from link_firmware_sim.allocation import (
    MARGIN_TOL_N,
    AllocationParams,
    gradual_selective_mapping,
    infinity_norm_allocation,
    pseudo_inverse,
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


def random_wrenches(n, seed):
    rng = np.random.default_rng(seed)
    return np.hstack((rng.normal(0.0, 15.0, (n, 3)), rng.normal(0.0, 2.0, (n, 3))))


def ry(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(psi):
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def hover_wrench(R, torque=(0.0, 0.0, 0.0)):
    """U = [R^T m g e3; tau] (eq. 2.8) for a 1.8 kg link hovering at attitude R."""
    return np.concatenate((R.T @ np.array([0.0, 0.0, MASS_KG * G]), torque))


def near_zero_wrenches(n, seed):
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


def below_margin_per_side(lam):
    mag = np.abs(lam)
    return [int(np.sum(mag[side] < EPS1 - 10 * MARGIN_TOL_N)) for side in SIDES]


def check_allocator_step(alloc, U_asked, keep=None):
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
    for s, c in enumerate(below_margin_per_side(r.lambda_beta)):
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

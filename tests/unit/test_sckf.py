import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.estimation.chain import ERR_DIM
from companion.estimation.constraints import constraint_residual
from companion.estimation.sckf import (
    CAParams,
    block_diag_covariance,
    constraint_apply,
    constraint_apply_dense,
    constraint_apply_structured,
)
from companion.estimation.so3 import retract

from ..chains import consistent_chain, perturbed_chain, random_covariances

METHODS = ["dense", "structured"]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("n", [2, 3, 5, 8, 12])
@pytest.mark.parametrize("seed", range(4))
def test_ca_drives_residual_below_eps(method, n, seed):
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(seed), n)
    params = CAParams(eps=0.01)
    before = np.linalg.norm(constraint_residual(p, v, q, w, d))
    res = constraint_apply(p, v, q, w, d, P, params, method)
    after = np.linalg.norm(constraint_residual(res.p, res.v, res.q, w, d))
    assert before > params.eps
    assert res.converged and res.iterations >= 1
    assert after <= params.eps
    assert res.residual_history[0] == pytest.approx(before)
    assert res.residual_history[-1] == pytest.approx(after)
    assert len(res.residual_history) == res.iterations + 1
    np.testing.assert_allclose(np.linalg.norm(res.q, axis=1), 1.0, atol=1e-12)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("n", [1, 2, 6])
def test_consistent_chain_is_left_unchanged(method, n):
    rng = np.random.default_rng(7)
    p, v, q, w, d = consistent_chain(rng, n)
    P = random_covariances(rng, n)
    res = constraint_apply(p, v, q, w, d, P, CAParams(), method)
    assert res.iterations == 0 and res.converged
    np.testing.assert_array_equal(res.p, p)
    np.testing.assert_array_equal(res.v, v)
    np.testing.assert_array_equal(res.q, q)
    np.testing.assert_array_equal(res.P, P)


@pytest.mark.parametrize("n", [2, 3, 4, 7, 12, 20])
@pytest.mark.parametrize("eps", [1e-2, 1e-5])
def test_structured_equals_dense_reference(n, eps):
    """The block-tridiagonal evaluation reproduces Alg. 1's Joseph-form iterates."""
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(n), n)
    params = CAParams(eps=eps)
    dense = constraint_apply_dense(p, v, q, w, d, P, params)
    fast = constraint_apply_structured(p, v, q, w, d, P, params)
    assert dense.iterations == fast.iterations
    np.testing.assert_allclose(fast.residual_history, dense.residual_history, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(fast.p, dense.p, atol=1e-10)
    np.testing.assert_allclose(fast.v, dense.v, atol=1e-10)
    np.testing.assert_allclose(fast.q, dense.q, atol=1e-10)
    np.testing.assert_allclose(fast.P, dense.P, atol=1e-7 * np.abs(P).max())
    # the cross-covariances with the end links (the global step's covariance needs them)
    np.testing.assert_allclose(fast.P_ends, dense.P_ends, atol=1e-7 * np.abs(P).max())
    full = dense.P_full.reshape(n, 9, n, 9)
    np.testing.assert_array_equal(dense.P_ends[0], full[:, :, 0, :])
    np.testing.assert_array_equal(dense.P_ends[1], full[:, :, -1, :])


def test_dense_covariance_blocks_match_full_matrix():
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(11), 4)
    res = constraint_apply_dense(p, v, q, w, d, P)
    for i in range(4):
        s = slice(ERR_DIM * i, ERR_DIM * (i + 1))
        np.testing.assert_array_equal(res.P[i], res.P_full[s, s])
    np.testing.assert_allclose(res.P_full, res.P_full.T, atol=0)


def test_first_iteration_is_one_kalman_update_with_weakening():
    """One CA iteration equals a textbook Kalman update with R = alpha C P C^T (Alg. 1, j = 0)."""
    from companion.estimation.constraints import constraint_jacobian

    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(12), 3)
    params = CAParams(eps=0.0, max_iter=1)
    res = constraint_apply_dense(p, v, q, w, d, P, params)
    C = constraint_jacobian(q, w, d)
    PE = block_diag_covariance(P)
    Rw = params.alpha * C @ PE @ C.T
    K = PE @ C.T @ np.linalg.inv(C @ PE @ C.T + Rw)
    dx = (-K @ constraint_residual(p, v, q, w, d)).reshape(3, 9)
    np.testing.assert_allclose(res.p, p + dx[:, :3], atol=1e-12)
    np.testing.assert_allclose(res.v, v + dx[:, 3:6], atol=1e-12)
    np.testing.assert_allclose(res.q, retract(q, dx[:, 6:]), atol=1e-12)
    np.testing.assert_allclose(res.P_full, PE - K @ C @ PE, atol=1e-12)
    assert not res.converged and res.iterations == 1


@pytest.mark.parametrize("method", METHODS)
def test_translation_does_not_change_corrections(method):
    rng = np.random.default_rng(13)
    p, v, q, w, d, P = perturbed_chain(rng, 6)
    shift = np.array([120.0, -45.0, 7.5])
    a = constraint_apply(p, v, q, w, d, P, CAParams(), method)
    b = constraint_apply(p + shift, v, q, w, d, P, CAParams(), method)
    np.testing.assert_allclose(b.p - (p + shift), a.p - p, atol=1e-9)
    np.testing.assert_allclose(b.v, a.v, atol=1e-12)
    np.testing.assert_allclose(b.q, a.q, atol=1e-12)
    np.testing.assert_allclose(b.P, a.P, atol=1e-12)


def test_iteration_cap_reports_not_converged():
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(14), 5)
    res = constraint_apply(p, v, q, w, d, P, CAParams(eps=1e-12, max_iter=3))
    assert res.iterations == 3 and not res.converged


@pytest.mark.parametrize(
    "kwargs, match",
    [({"alpha": 0.0}, "alpha"), ({"eps": -1.0}, "eps"), ({"max_iter": 0}, "max_iter"), ({"alpha": np.nan}, "alpha")],
)
def test_params_are_validated(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CAParams(**kwargs)


def test_unknown_method_is_rejected():
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(15), 3)
    with pytest.raises(ValueError, match="unknown method"):
        constraint_apply(p, v, q, w, d, P, method="fast")


chains = st.tuples(
    st.integers(2, 9),  # links
    st.integers(0, 2**32 - 1),  # seed
    st.floats(0.01, 1.5),  # position/velocity error sigma
    st.floats(0.0, 0.3),  # attitude error sigma
    st.sampled_from(METHODS),
)


@given(chains)
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_property_covariance_psd_unit_quaternions_and_convergence(case):
    n, seed, pos_sigma, att_sigma, method = case
    rng = np.random.default_rng(seed)
    p, v, q, w, d, P = perturbed_chain(rng, n, pos_sigma, att_sigma)
    params = CAParams(eps=0.01, max_iter=20)
    res = constraint_apply(p, v, q, w, d, P, params, method)
    # Residual converges below eps and never blows up on the way.
    assert res.converged
    assert res.residual_history[-1] <= params.eps
    assert res.residual_history[-1] <= res.residual_history[0]
    # Unit quaternions.
    np.testing.assert_allclose(np.linalg.norm(res.q, axis=1), 1.0, atol=1e-12)
    # Symmetric PSD blocks, never larger than the EKF prior (constraints only add information).
    np.testing.assert_array_equal(res.P, np.swapaxes(res.P, 1, 2))
    scale = np.abs(P).max()
    assert np.linalg.eigvalsh(res.P).min() >= -1e-10 * scale
    assert np.linalg.eigvalsh(P - res.P).min() >= -1e-9 * scale


# -- body-rate noise (CAParams.omega_std_rad_s) ----------------------------------------------------------------
@pytest.mark.parametrize("method", ["dense", "structured"])
def test_rate_noise_gain_is_the_corrected_estimates_derivative(method):
    """``-K D`` of :func:`rate_noise_covariance` is how the converged estimate moves with the
    reported body rates: central differences of the whole constraint application (the weakening
    makes the iterates differ from the exact projection by about 1 %)."""
    from companion.estimation.sckf import _rate_noise_gain, block_diag_covariance
    from companion.estimation.so3 import attitude_error

    n = 4
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(2), n, pos_sigma=0.02, att_sigma=0.01)
    params = CAParams(eps=1e-12, max_iter=60)
    base = constraint_apply(p, v, q, w, d, P, params, method)
    KD = _rate_noise_gain(base.q, w, d, block_diag_covariance(P))
    h = 1e-5
    for k in range(n):
        for j in range(3):
            moved = []
            for sign in (1.0, -1.0):
                w2 = w.copy()
                w2[k, j] += sign * h
                r = constraint_apply(p, v, q, w2, d, P, params, method)
                moved.append(np.concatenate([r.p, r.v, attitude_error(r.q, base.q)], axis=1).reshape(-1))
            np.testing.assert_allclose((moved[0] - moved[1]) / (2 * h), -KD[:, 3 * k + j], atol=0.02 * np.abs(KD).max())


@pytest.mark.parametrize("groups", [((0, 1, 2, 3, 4),), ((0,), (1, 2), (3, 4)), ((0, 1, 2, 3), (4,))],
                         ids=["one-group", "1/2/2", "4/1"])
def test_rate_noise_keeps_the_corrected_covariance_consistent(groups):
    """Monte Carlo (seeded): EKF errors drawn from their covariances and white noise on the
    reported body rates; the semi-distributed estimate's NEES stays near 3 per block when
    ``omega_std_rad_s`` says how noisy the rates are, and velocity is over-confident when the
    rates count as exact."""
    from companion.estimation.semi import semi_distributed_apply
    from companion.estimation.so3 import attitude_error, retract

    from ..chains import consistent_chain

    rng = np.random.default_rng(3)
    n, sigma, samples = 5, 0.05, 150
    p0, v0, q0, w0, d = consistent_chain(rng, n)
    P = np.broadcast_to(np.diag([0.01] * 3 + [0.004] * 3 + [0.0004] * 3), (n, 9, 9)).copy()
    L = np.linalg.cholesky(P)
    nees = np.zeros((2, n, 3))
    for _ in range(samples):
        e = (L @ rng.normal(size=(n, 9, 1)))[..., 0]
        w = w0 + sigma * rng.normal(size=w0.shape)
        for k, std in enumerate((sigma, 0.0)):
            r = semi_distributed_apply(p0 + e[:, :3], v0 + e[:, 3:6], retract(q0, e[:, 6:]), w, d, P, groups,
                                       CAParams(omega_std_rad_s=std))
            err = np.concatenate([r.p - p0, r.v - v0, attitude_error(r.q, q0)], axis=1)
            for b in range(3):
                x = err[:, 3 * b:3 * b + 3]
                nees[k, :, b] += np.einsum("ni,ni->n", x, np.linalg.solve(r.P[:, 3 * b:3 * b + 3, 3 * b:3 * b + 3],
                                                                          x[..., None])[..., 0])
    modelled, exact = nees / samples
    assert np.all((modelled > 2.45) & (modelled < 3.55)), modelled  # 150 samples: 3 +- 0.4
    assert exact[:, 1].max() > 4.0, exact  # the rates' noise unaccounted for: velocity over-confident


def test_rate_noise_params_are_validated():
    with pytest.raises(ValueError, match="omega_std_rad_s"):
        CAParams(omega_std_rad_s=-0.1)
    with pytest.raises(ValueError, match="omega_std_rad_s"):
        CAParams(omega_std_rad_s=float("nan"))

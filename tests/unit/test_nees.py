"""NEES in the run metrics (sitl.metrics.nees_metrics): a consistent estimate lands in the
bounds, an over-confident one does not; truth interpolation at the steps (sitl.steplog)."""

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_rotvec, quat_mul, quat_normalize
from sitl.metrics import correlation_time, nees_metrics, nees_series
from sitl.steplog import attach_truth


def _log(rng, k=800, n=3, scale=1.0):
    """Steps with the truth and two estimates whose errors are drawn from their covariances
    times ``scale`` (1: consistent)."""
    q_true = quat_normalize(rng.normal(size=(k, n, 4)))
    log = {"t_sckf": np.arange(k) * 0.05, "p_true_sckf": rng.normal(size=(k, n, 3)),
           "v_true_sckf": rng.normal(size=(k, n, 3)), "q_true_sckf": q_true}
    for which in ("ekf", "corr"):
        A = rng.normal(size=(k, n, 3, 3, 3)) * 0.1
        P = A @ np.swapaxes(A, -1, -2) + 1e-3 * np.eye(3)
        L = np.linalg.cholesky(P)
        e = scale * (L @ rng.normal(size=(k, n, 3, 3, 1)))[..., 0]  # truth - estimate per block
        log[f"P_{which}_sckf"] = P
        log[f"p_{which}_sckf"] = log["p_true_sckf"] - e[:, :, 0]
        log[f"v_{which}_sckf"] = log["v_true_sckf"] - e[:, :, 1]
        # q_true = Exp(e_att) q_est
        log[f"q_{which}_sckf"] = quat_mul(quat_from_rotvec(-e[:, :, 2]), q_true)
    return log


def test_consistent_errors_land_in_the_bounds_and_overconfidence_does_not():
    rng = np.random.default_rng(0)
    m = nees_metrics(_log(rng), 5.0)
    lo, hi = m["bounds95"]
    assert m["samples"] == 700 and 2.7 < lo < 3.0 < hi < 3.3
    for which in ("ekf", "corrected"):
        for block in ("pos", "vel", "att"):
            assert all(lo <= x <= hi for x in m[which][block]), (which, block, m[which][block])
    bad = nees_metrics(_log(np.random.default_rng(1), scale=2.0), 5.0)
    for block in ("pos", "vel", "att"):
        assert all(x == pytest.approx(12.0, rel=0.15) for x in bad["ekf"][block])


def test_nees_leaves_unknown_estimates_out_and_needs_the_truth():
    log = _log(np.random.default_rng(2), k=50)
    for key in ("p_ekf_sckf", "v_ekf_sckf", "q_ekf_sckf"):  # link 2 out for half a second
        log[key][10:20, 1] = np.nan
    series = nees_series(log, "ekf")
    assert np.all(np.isnan(series[10:20, 1])) and np.all(np.isfinite(series[10:20, [0, 2]]))
    assert np.isfinite(nees_metrics(log, 0.0)["ekf"]["pos"][1])
    del log["v_true_sckf"]
    assert nees_series(log, "ekf") is None and nees_metrics(log, 0.0) is None


def test_truth_is_interpolated_at_the_step_times():
    t = np.arange(6) * 0.02
    p = np.stack([t, 2 * t, 0 * t], axis=1)[:, None, :]
    q = np.stack([quat_from_rotvec(np.array([0.0, 0.0, 0.5 * x])) for x in t])[:, None, :]
    q[3] *= -1  # the same attitude with the other sign
    steps = {"t_sckf": np.array([0.03, 0.05, 0.2]), "x": np.arange(3)}
    out = attach_truth(steps, t, p, 10 * p, q)
    assert out["x"].tolist() == [0, 1]  # 0.2 s is past the truth's end
    np.testing.assert_allclose(out["p_true_sckf"][:, 0], [[0.03, 0.06, 0], [0.05, 0.10, 0]], atol=1e-12)
    np.testing.assert_allclose(out["v_true_sckf"][:, 0], [[0.3, 0.6, 0], [0.5, 1.0, 0]], atol=1e-12)
    want = quat_from_rotvec(np.array([0.0, 0.0, 0.5 * 0.05]))
    got = out["q_true_sckf"][1, 0]
    assert abs(abs(got @ want) - 1.0) < 1e-6


def _ar1(rng, a, k, shape):
    """Unit-variance AR(1) series with coefficient ``a`` along axis 0."""
    w = np.empty((k,) + shape)
    w[0] = rng.normal(size=shape)
    e = rng.normal(size=(k,) + shape) * np.sqrt(1 - a * a)
    for i in range(1, k):
        w[i] = a * w[i - 1] + e[i]
    return w


@pytest.mark.parametrize("a", [0.0, 0.5, 0.9])
def test_correlation_time_of_the_nees_matches_an_ar1_series(a):
    """For whitened errors with autocorrelation a^j the NEES' integrated correlation time is
    (1 + a^2) / (1 - a^2); NaN gaps are left out."""
    w = _ar1(np.random.default_rng(3), a, 20000, (2, 3))
    w[100:200, 0] = np.nan
    tau = correlation_time(w)
    assert tau.shape == (2,)
    assert tau == pytest.approx((1 + a * a) / (1 - a * a), rel=0.15)


def test_effective_bounds_widen_for_correlated_errors_but_not_for_overconfidence():
    """A consistent filter whose errors are correlated over ~20 steps lands outside the
    independent-sample band often but inside the effective one; the same errors with the
    covariance four times too small (NEES 12) are outside both."""
    rng = np.random.default_rng(4)
    k, n = 1200, 3
    log = {"t_sckf": np.arange(k) * 0.05, "p_true_sckf": np.zeros((k, n, 3)), "v_true_sckf": np.zeros((k, n, 3)),
           "q_true_sckf": np.tile([1.0, 0, 0, 0], (k, n, 1))}
    for which, scale in (("ekf", 1.0), ("corr", 2.0)):
        e = scale * _ar1(rng, 0.95, k, (n, 3, 3))  # (k, n, block, 3), covariance identity
        log[f"P_{which}_sckf"] = np.broadcast_to(np.eye(3), (k, n, 3, 3, 3)).copy()
        log[f"p_{which}_sckf"] = -e[:, :, 0]
        log[f"v_{which}_sckf"] = -e[:, :, 1]
        log[f"q_{which}_sckf"] = quat_from_rotvec(e[:, :, 2])  # q_true = Exp(-e) q_est = 1
    m = nees_metrics(log, 0.0)
    for block in ("pos", "vel", "att"):
        assert all(20 < x < 90 for x in m["effective_samples"]["ekf"][block])  # 1200 / 39
        assert all(m["inside95"]["ekf"][block]), (block, m["ekf"][block], m["bounds95_effective"]["ekf"][block])
        assert not any(m["inside95"]["corrected"][block])
    means = [x for block in ("pos", "vel", "att") for x in m["ekf"][block]]
    lo, hi = m["bounds95"]
    assert any(not lo <= x <= hi for x in means)  # the independent band rejects a consistent filter


@pytest.mark.parametrize("n", [2, 4])
def test_relative_errors_tell_a_turn_of_the_whole_chain_from_a_bend_between_neighbours(n):
    """``rms_rel_err`` (sitl.metrics.relative_error_metrics): an estimate of the whole chain
    turned by 1 deg about its first link's centre moves the neighbours' world-frame position
    difference (L sin 1 deg) but neither the neighbour as each link sees it (``pos_body_m``) nor
    the relative attitude; an estimate bent at the joints by 1 deg between neighbours moves all
    three, the body-frame position by the tip's lever arm."""
    from companion.estimation.so3 import quat_to_rotmat
    from sitl.metrics import relative_error_metrics

    rng = np.random.default_rng(n)
    k, L = 50, 1.0
    d = np.array([0.5 * L, 0.0, 0.0])
    yaw = np.zeros((k, n, 3))
    yaw[..., 2] = rng.normal(0.0, 0.3, (k, n))  # (a chain bent in the horizontal plane)
    q_true = quat_from_rotvec(yaw)
    R = quat_to_rotmat(q_true)
    tips = np.einsum("knij,j->kni", R, d)
    p_true = np.concatenate([np.zeros((k, 1, 3)), np.cumsum(tips[:, :-1] + tips[:, 1:], axis=1)], axis=1)
    turn = quat_from_rotvec(np.array([0.0, 0.0, np.radians(1.0)]))
    turned_R = quat_to_rotmat(turn)
    log = {"p_true_sckf": p_true, "q_true_sckf": q_true,
           "p_ekf_sckf": p_true @ turned_R.T, "q_ekf_sckf": quat_mul(turn, q_true)}
    # bent: each link turned 1 deg more than the one before, about its own centre, joints kept
    q_bent = np.stack([quat_mul(q_true[:, i], quat_from_rotvec(np.array([0.0, 0.0, np.radians(i)])))
                       for i in range(n)], axis=1)
    tips_b = np.einsum("knij,j->kni", quat_to_rotmat(q_bent), d)
    log["p_corr_sckf"] = np.concatenate([np.zeros((k, 1, 3)), np.cumsum(tips_b[:, :-1] + tips_b[:, 1:], axis=1)],
                                        axis=1)
    log["q_corr_sckf"] = q_bent
    out = relative_error_metrics(log, np.arange(k), sckf=True)
    horizontal = np.linalg.norm((p_true[:, 1:] - p_true[:, :-1])[..., :2], axis=-1)  # (the turn is about z)
    world = horizontal * 2 * np.sin(np.radians(0.5))
    np.testing.assert_allclose(out["pos_m"]["ekf"], np.sqrt(np.mean(world**2, axis=0)), rtol=1e-9)
    np.testing.assert_allclose(out["pos_body_m"]["ekf"], 0.0, atol=1e-12)
    np.testing.assert_allclose(out["att_deg"]["ekf"], 0.0, atol=1e-9)
    np.testing.assert_allclose(out["att_deg"]["sckf"], 1.0, rtol=1e-6)
    # link i+1's centre, seen from link i: its tip turned 1 deg about link i+1's left tip
    np.testing.assert_allclose(out["pos_body_m"]["sckf"], 0.5 * L * 2 * np.sin(np.radians(0.5)), rtol=1e-6)
    assert np.all(np.array(out["pos_m"]["sckf"]) > 0.0)


@pytest.mark.parametrize("dof", [1, 3, 6])
def test_nees_bounds_are_the_chi_square_quantiles_of_the_mean(dof):
    """scipy.special's chi-square inverse gives scipy.stats' quantiles (the oracle), for whole and
    effective (fractional) sample counts."""
    from scipy.stats import chi2

    from sitl.metrics import nees_bounds95

    k = np.array([1.0, 2.5, 10.0, 400.7, 1e4])
    np.testing.assert_allclose(nees_bounds95(k, dof), np.stack([chi2.ppf(0.025, dof * k) / k,
                                                                chi2.ppf(0.975, dof * k) / k], axis=-1), rtol=1e-12)


def test_a_flights_metrics_and_a_campaigns_summary_do_not_import_scipy_stats():
    """Their chi-square and t quantiles come from scipy.special: scipy.stats, slow to import, would
    lengthen the end of every run."""
    import subprocess
    import sys

    code = ("import sys, numpy as np; import sitl.__main__; from sitl.metrics import nees_bounds95; "
            "from sitl.campaign.summary import metric_stats; nees_bounds95(np.array([5.0])); "
            "metric_stats([1.0, 2.0]); assert 'scipy.stats' not in sys.modules, 'scipy.stats imported'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)

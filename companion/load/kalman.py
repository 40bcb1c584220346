"""The load filters' two steps, EKF and UKF: prediction with eq. 8 and the correction with a
:class:`~.measurements.Measurement`.

* EKF: the nominal state by the midpoint rule, ``P <- F P F^T + Q`` with the linearised error
  dynamics; the correction in Joseph form.
* UKF: sigma points on the manifold (``x [+] columns of chol(c P)``) through the nonlinear
  model, their mean by one Gauss-Newton step from the centre point, the covariance in its
  tangent space.

Every covariance is symmetrised. The reset Jacobian of the error injection is taken as identity
(standard for error-state filters with small corrections). Functional: estimates in, estimates
out; :func:`predict` and :func:`correct` pick the filter by ``kind``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from .estimate import LoadEstimate, LoadFilterConfig, process_noise, symmetrised
from .measurements import Measurement
from .model import LoadParams, VehicleStates, boxminus, boxplus, error_dynamics_jacobian, propagate_nominal

__all__ = ["FilterKind", "FILTER_KINDS", "ekf_predict", "ekf_correct", "ukf_predict", "ukf_correct", "predict",
           "correct"]

FilterKind = Literal["ekf", "ukf"]
FILTER_KINDS: tuple[FilterKind, ...] = ("ekf", "ukf")


def _substeps(dt_s: float, max_step_s: float) -> tuple[int, float]:
    n_sub = max(1, math.ceil(dt_s / max_step_s - 1e-9))
    return n_sub, dt_s / n_sub


def _check_forward(est: LoadEstimate, t_to_s: float) -> float:
    dt = t_to_s - est.stamp_s
    if dt < -1e-12:
        raise ValueError(f"cannot predict backwards ({est.stamp_s} -> {t_to_s})")
    return dt


# --- EKF ---------------------------------------------------------------------------------------


def ekf_predict(est: LoadEstimate, vehicles: VehicleStates, t_to_s: float, params: LoadParams,
                cfg: LoadFilterConfig) -> LoadEstimate:
    """Propagate to ``t_to_s`` with eq. 8 (the vehicles moving from ``vehicles``): per step ``h``,
    the nominal state by the midpoint rule and ``P <- F P F^T + Q(h)`` with
    ``F = I + A h + (A h)^2 / 2``, ``A`` from :func:`~.model.error_dynamics_jacobian`."""
    dt = _check_forward(est, t_to_s)
    if dt <= 0.0:
        return est
    n_sub, h = _substeps(dt, cfg.max_step_s)
    x, P = est.x, est.P
    I = np.eye(P.shape[0])
    Q = process_noise(x, h, cfg)
    for k in range(n_sub):
        t = est.stamp_s + k * h
        Ah = error_dynamics_jacobian(x, vehicles.positions_at(t), params) * h
        F = I + Ah + 0.5 * Ah @ Ah
        x = propagate_nominal(x, vehicles, t, h, params, h)
        P = F @ P @ F.T + Q
    return LoadEstimate(float(t_to_s), x, symmetrised(P))


def ekf_correct(est: LoadEstimate, m: Measurement, gate_chi2: float | None) -> tuple[LoadEstimate, float, bool]:
    """The EKF update with ``m`` (linearised at ``est``): innovation ``z - h(x)``, Joseph form.
    Returns the estimate, the normalised innovation squared and whether it passed the gate
    (a rejected measurement leaves the estimate as it was)."""
    P = est.P
    innov = m.z - m.h(est.x)
    S = symmetrised(m.H @ P @ m.H.T + m.R)
    S_inv = np.linalg.inv(S)
    nis = float(innov @ S_inv @ innov)
    if gate_chi2 is not None and nis > gate_chi2:
        return est, nis, False
    K = P @ m.H.T @ S_inv
    I_KH = np.eye(P.shape[0]) - K @ m.H
    P_new = symmetrised(I_KH @ P @ I_KH.T + K @ m.R @ K.T)
    return LoadEstimate(est.stamp_s, boxplus(est.x, K @ innov), P_new), nis, True


# --- UKF ---------------------------------------------------------------------------------------


def _ukf_weights(N: int, cfg: LoadFilterConfig) -> tuple[np.ndarray, np.ndarray, float]:
    lam = cfg.ukf_alpha**2 * (N + cfg.ukf_kappa) - N
    c = N + lam
    if c <= 0:
        raise ValueError(f"UKF scaling gives n + lambda = {c} <= 0; raise ukf_alpha or ukf_kappa")
    Wm = np.full(2 * N + 1, 0.5 / c)
    Wc = Wm.copy()
    Wm[0] = lam / c
    Wc[0] = lam / c + 1.0 - cfg.ukf_alpha**2 + cfg.ukf_beta
    return Wm, Wc, c


def _sigma_points(est: LoadEstimate, cfg: LoadFilterConfig):
    """Sigma points on the manifold: ``x [+] 0`` and ``x [+] (+-) columns of chol(c P)``."""
    N = est.P.shape[0]
    Wm, Wc, c = _ukf_weights(N, cfg)
    L = np.linalg.cholesky(c * est.P + 1e-15 * np.eye(N))
    dx = np.vstack((np.zeros(N), L.T, -L.T))
    return boxplus(est.x[None, :], dx), Wm, Wc


def _manifold_mean(chi: np.ndarray, Wm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean of points on the manifold and the points' errors about it: one Gauss-Newton
    step from the centre point (the next step is second order in the points' spread)."""
    mean = boxplus(chi[0], Wm @ boxminus(chi, chi[0][None, :]))
    return mean, boxminus(chi, mean[None, :])


def ukf_predict(est: LoadEstimate, vehicles: VehicleStates, t_to_s: float, params: LoadParams,
                cfg: LoadFilterConfig) -> LoadEstimate:
    """Propagate to ``t_to_s``: every sigma point through the nonlinear eq. 8 (midpoint rule),
    their mean on the manifold and covariance in its tangent space, plus ``Q(dt)``."""
    dt = _check_forward(est, t_to_s)
    if dt <= 0.0:
        return est
    chi, Wm, Wc = _sigma_points(est, cfg)
    chi = propagate_nominal(chi, vehicles, est.stamp_s, dt, params, cfg.max_step_s)
    mean, d = _manifold_mean(chi, Wm)
    P = symmetrised((d * Wc[:, None]).T @ d + process_noise(mean, dt, cfg))
    return LoadEstimate(float(t_to_s), mean, P)


def ukf_correct(est: LoadEstimate, m: Measurement, cfg: LoadFilterConfig,
                gate_chi2: float | None) -> tuple[LoadEstimate, float, bool]:
    """The UKF update with ``m``: the sigma points through ``m.h`` (``m.H`` unused), the
    measurement's mean and covariance, the cross covariance with the state's tangent errors. The
    posterior is ``Pxx - K S K^T`` with ``Pxx`` the sigma points' own covariance in the tangent
    space (``P`` itself while every point maps back exactly; not when an attitude spread passes
    pi and wraps): the joint covariance of the points is positive semi-definite, so the
    posterior is too, whatever the data. Returns as :func:`ekf_correct`."""
    chi, Wm, Wc = _sigma_points(est, cfg)
    Z = m.h(chi)
    z_hat = Wm @ Z
    dz = Z - z_hat
    dx = boxminus(chi, est.x[None, :])
    S = symmetrised((dz * Wc[:, None]).T @ dz + m.R)
    Pxz = (dx * Wc[:, None]).T @ dz
    S_inv = np.linalg.inv(S)
    innov = m.z - z_hat
    nis = float(innov @ S_inv @ innov)
    if gate_chi2 is not None and nis > gate_chi2:
        return est, nis, False
    K = Pxz @ S_inv
    Pxx = (dx * Wc[:, None]).T @ dx
    P_new = symmetrised(Pxx - K @ S @ K.T)
    return LoadEstimate(est.stamp_s, boxplus(est.x, K @ innov), P_new), nis, True


# --- by kind -----------------------------------------------------------------------------------


def predict(kind: FilterKind, est: LoadEstimate, vehicles: VehicleStates, t_to_s: float, params: LoadParams,
            cfg: LoadFilterConfig) -> LoadEstimate:
    """:func:`ekf_predict` or :func:`ukf_predict`."""
    return (ekf_predict if kind == "ekf" else ukf_predict)(est, vehicles, t_to_s, params, cfg)


def correct(kind: FilterKind, est: LoadEstimate, m: Measurement, cfg: LoadFilterConfig,
            gate_chi2: float | None) -> tuple[LoadEstimate, float, bool]:
    """:func:`ekf_correct` or :func:`ukf_correct`."""
    if kind == "ekf":
        return ekf_correct(est, m, gate_chi2)
    return ukf_correct(est, m, cfg, gate_chi2)

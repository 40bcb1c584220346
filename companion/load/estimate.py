"""The load filters' tuning, their estimate, the prior and the process noise.

:class:`LoadFilterConfig` is the ``[load.filter]`` table of a slung-load scenario;
:class:`LoadEstimate` the nominal state (13 + n) and error-state covariance (12 + n) at a time
(the slices of :mod:`.model`); :func:`initial_estimate` the prior; :func:`process_noise` the
discrete noise of a prediction step. numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtri

from .model import (
    ERR_ATT,
    ERR_OMEGA,
    ERR_POS,
    ERR_VEL,
    NOM_OMEGA,
    NOM_POS,
    NOM_QUAT,
    NOM_VEL,
    LoadParams,
    LoadState,
    VehicleStates,
    error_dim,
    error_tension_slice,
    nominal_tension_slice,
    pack_state,
    static_tensions,
)

__all__ = ["LoadFilterConfig", "LoadEstimate", "initial_estimate", "process_noise", "symmetrised", "with_vehicle_bias"]


@dataclass(frozen=True)
class LoadFilterConfig:
    """Tuning of the load filters.

    Process noise as continuous white-noise densities: on the load's acceleration
    (``accel_noise_m_s2_rthz``, m/s^2/sqrt(Hz): unmodelled forces, cable stretch, wind, and the
    vehicles' position noise in the cable directions), its body angular acceleration
    (``ang_accel_noise_rad_s2_rthz``) and the random walk of each tension (``tension_walk_n_rts``,
    N/sqrt(s)). ``max_step_s`` bounds the integration step; ``lag_s`` how late an image may
    arrive (older ones are dropped and counted).

    What the filter fuses: every image's eq. 4 measurement, with ``marker_attitude`` also the
    load's attitude the marker shows (needs the vehicles' attitudes in their samples;
    :func:`~.measurements.image_measurement`); with ``cable_lengths``, after every accepted image
    the length of each taut cable (tension estimated above ``cable_taut_fraction`` of an equal
    share of the weight) with standard deviation ``cable_length_sigma_m``
    (:func:`~.measurements.cable_measurement`). ``gate_probability``: an image whose normalised
    innovation squared exceeds the chi-square quantile of this probability (for the image's
    degrees of freedom) is rejected (``None`` = no gate).

    ``vehicle_bias_std_m``: the standard deviation (horizontal, vertical) of each vehicle's
    position bias, independent between vehicles (GNSS multipath, an RTK fix's offset). Every
    measurement of the load sees the load relative to the vehicles, so the mean of their biases
    moves the load's absolute position unobserved; the filter's output adds its covariance to
    the position's (:func:`with_vehicle_bias`).

    ``ukf_alpha/beta/kappa``: the scaled unscented transform (``alpha = 1, kappa = 0``: 2N points
    at ``sqrt(N) sigma``, zero mean weight at the centre). The noise defaults are tuned on the
    synthetic scenario (:mod:`sitl.scenarios.slung_load.synthetic`); a flight with more
    unmodelled force (drag, gusts) needs larger ones.
    """

    accel_noise_m_s2_rthz: float = 0.05
    ang_accel_noise_rad_s2_rthz: float = 0.3
    tension_walk_n_rts: float = 0.3
    max_step_s: float = 0.02
    lag_s: float = 0.5
    gate_probability: float | None = 0.999
    vehicle_bias_std_m: tuple[float, float] = (0.0, 0.0)
    marker_attitude: bool = True
    cable_lengths: bool = True
    cable_length_sigma_m: float = 0.005
    cable_taut_fraction: float = 0.2
    ukf_alpha: float = 1.0
    ukf_beta: float = 2.0
    ukf_kappa: float = 0.0

    def __post_init__(self) -> None:
        for name in ("accel_noise_m_s2_rthz", "ang_accel_noise_rad_s2_rthz", "tension_walk_n_rts", "lag_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"LoadFilterConfig.{name} must be >= 0 and finite, got {v}")
        for name in ("max_step_s", "ukf_alpha", "cable_length_sigma_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"LoadFilterConfig.{name} must be positive, got {v}")
        if self.gate_probability is not None and not 0.0 < self.gate_probability < 1.0:
            raise ValueError(f"LoadFilterConfig.gate_probability must be in (0, 1) or None, got {self.gate_probability}")
        if len(self.vehicle_bias_std_m) != 2 or not all(math.isfinite(v) and v >= 0 for v in self.vehicle_bias_std_m):
            raise ValueError(f"LoadFilterConfig.vehicle_bias_std_m: (horizontal, vertical) >= 0, got "
                             f"{self.vehicle_bias_std_m}")
        if not 0.0 <= self.cable_taut_fraction < 1.0:
            raise ValueError(f"LoadFilterConfig.cable_taut_fraction must be in [0, 1), got {self.cable_taut_fraction}")

    def gate_chi2(self, dof: int) -> float | None:
        """The gate on a measurement's normalised innovation squared for ``dof`` degrees of
        freedom (``None``: no gate)."""
        if self.gate_probability is None:
            return None
        return float(chdtri(dof, 1.0 - self.gate_probability))


@dataclass(frozen=True)
class LoadEstimate:
    """A filter's estimate at ``stamp_s``: nominal vector ``x`` (13 + n) and error-state
    covariance ``P`` (12 + n, 12 + n); named views below."""

    stamp_s: float
    x: np.ndarray
    P: np.ndarray

    @property
    def n_cables(self) -> int:
        return self.x.shape[0] - 13

    @property
    def pos_w_m(self) -> np.ndarray:
        return self.x[NOM_POS]

    @property
    def vel_w_m_s(self) -> np.ndarray:
        return self.x[NOM_VEL]

    @property
    def q_wxyz(self) -> np.ndarray:
        return self.x[NOM_QUAT]

    @property
    def omega_b_rad_s(self) -> np.ndarray:
        return self.x[NOM_OMEGA]

    @property
    def tension_n(self) -> np.ndarray:
        return self.x[nominal_tension_slice(self.n_cables)]

    @property
    def pos_cov_m2(self) -> np.ndarray:
        return self.P[ERR_POS, ERR_POS]

    @property
    def att_cov_rad2(self) -> np.ndarray:
        return self.P[ERR_ATT, ERR_ATT]


def symmetrised(P: np.ndarray) -> np.ndarray:
    """``(P + P^T) / 2``."""
    return 0.5 * (P + P.T)


def initial_estimate(stamp_s: float, pos_w_m, q_wxyz, vehicles: VehicleStates, params: LoadParams, *,
                     pos_sigma_m: float = 0.1, vel_sigma_m_s: float = 0.2, att_sigma_rad: float = 0.1,
                     omega_sigma_rad_s: float = 0.3, tension_sigma_n: float | None = None) -> LoadEstimate:
    """An estimate at rest at the given pose, tensions from the static balance in that geometry
    (:func:`~.load_model.static_tensions`), with diagonal covariance from the sigmas
    (``tension_sigma_n`` defaults to half the load's weight)."""
    n = params.n_cables
    if vehicles.pos_w_m.shape[0] != n:
        raise ValueError(f"{vehicles.pos_w_m.shape[0]} vehicles for {n} cables")
    x = pack_state(LoadState(pos_w_m, np.zeros(3), q_wxyz, np.zeros(3), np.zeros(n)))
    x[nominal_tension_slice(n)] = static_tensions(x, vehicles.positions_at(stamp_s), params)
    if tension_sigma_n is None:
        tension_sigma_n = 0.5 * params.mass_kg * params.gravity_m_s2
    sig = np.empty(error_dim(n))
    sig[ERR_POS], sig[ERR_VEL], sig[ERR_ATT] = pos_sigma_m, vel_sigma_m_s, att_sigma_rad
    sig[ERR_OMEGA], sig[error_tension_slice(n)] = omega_sigma_rad_s, tension_sigma_n
    if not np.all(np.isfinite(sig)) or np.any(sig <= 0):
        raise ValueError("initial sigmas must be positive")
    return LoadEstimate(float(stamp_s), x, np.diag(sig**2))


def process_noise(x: np.ndarray, dt_s: float, cfg: LoadFilterConfig) -> np.ndarray:
    """Discrete process noise over ``dt_s``: ``G Qc G^T dt`` with the densities on velocity,
    body angular velocity and tensions (first order in ``dt``)."""
    n = x.shape[-1] - 13
    Q = np.zeros((error_dim(n), error_dim(n)))
    Q[ERR_VEL, ERR_VEL] = np.eye(3) * cfg.accel_noise_m_s2_rthz**2 * dt_s
    Q[ERR_OMEGA, ERR_OMEGA] = np.eye(3) * cfg.ang_accel_noise_rad_s2_rthz**2 * dt_s
    ts = error_tension_slice(n)
    Q[ts, ts] = np.eye(n) * cfg.tension_walk_n_rts**2 * dt_s
    return Q


def with_vehicle_bias(est: LoadEstimate, cfg: LoadFilterConfig) -> LoadEstimate:
    """``est`` with the covariance of the mean of the vehicles' position biases
    (``diag(h^2, h^2, v^2) / n`` from ``cfg.vehicle_bias_std_m``) added to its position block:
    a bias common to every measurement of the load is not observed by them, so it adds to the
    posterior (the filter's state is the load relative to the vehicles' positions)."""
    h, v = cfg.vehicle_bias_std_m
    if not (h or v):
        return est
    P = est.P.copy()
    P[ERR_POS, ERR_POS] += np.diag([h * h, h * h, v * v]) / est.n_cables
    return LoadEstimate(est.stamp_s, est.x, P)

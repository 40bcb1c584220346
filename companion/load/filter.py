"""The slung load's pose on SE(3): error-state EKF, UKF with sigma points on the manifold,
an unfiltered baseline, and late images (the report's sec. IV).

Model, state and slices: :mod:`companion.load.model` (eq. 8 dynamics with estimated cable
tensions in the prediction, eq. 4 measurement). What differs from the report:

* the dynamics are in the prediction, not folded into a control input (the report's eq. 5/7),
  so the EKF (linearised ``A``, ``H``) and the UKF (sigma points through the nonlinear model)
  are different filters and give different numbers;
* the attitude is a quaternion with a 3-d world-frame error (``q = Exp(dtheta) (x) q_hat``),
  not roll-pitch-yaw, and the load's orientation is estimated;
* images may arrive late: :class:`LoadPoseFilter` keeps the processed events of the last
  ``lag_s`` seconds with the estimate after each, rolls back to the last estimate before a late
  image's capture time and replays the later events (re-propagation), so a late image gives the
  same estimate as one that arrived in order;
* optional chi-square gating of each image (a PnP spike, e.g. P3P's when the marker is small in
  the image, is rejected instead of pulling the estimate).

Functional core (no clocks, no I/O): :func:`ekf_predict`, :func:`ekf_update`,
:func:`ukf_predict`, :func:`ukf_update`, :func:`cable_length_update` and :func:`solve_load_pose`
(the unfiltered baseline, a weighted Kabsch/Horn solve of eq. 4 over the vehicles);
thin classes on top: :class:`LoadPoseFilter` (time line and late images) and
:class:`UnfilteredLoadPose`.

The EKF's covariance update is in Joseph form and every covariance is symmetrised. The reset
Jacobian of the error injection is taken as identity (standard for error-state filters with
small corrections).
"""

from __future__ import annotations

import bisect
import logging
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from companion.estimation.so3 import quat_to_rotmat, rotmat_to_quat

from .model import (
    ERR_ATT,
    ERR_OMEGA,
    ERR_POS,
    ERR_VEL,
    NOM_OMEGA,
    NOM_POS,
    NOM_QUAT,
    NOM_VEL,
    LoadObservation,
    LoadParams,
    LoadState,
    VehicleStates,
    boxminus,
    boxplus,
    cable_length_jacobian,
    cable_lengths,
    error_dim,
    error_dynamics_jacobian,
    error_tension_slice,
    nominal_tension_slice,
    pack_state,
    propagate_nominal,
    static_tensions,
    vehicle_in_load,
    vehicle_in_load_jacobian,
)

__all__ = [
    "LoadFilterConfig",
    "LoadEstimate",
    "initial_estimate",
    "process_noise",
    "ekf_predict",
    "ekf_update",
    "ukf_predict",
    "ukf_update",
    "cable_length_update",
    "solve_load_pose",
    "LoadPoseFilter",
    "UnfilteredLoadPose",
]

log = logging.getLogger(__name__)

FilterKind = Literal["ekf", "ukf"]


@dataclass(frozen=True)
class LoadFilterConfig:
    """Tuning of the load filters.

    Process noise as continuous white-noise densities: on the load's acceleration
    (``accel_noise_m_s2_rthz``, m/s^2/sqrt(Hz): unmodelled forces, cable stretch, wind, and the
    vehicles' position noise in the cable directions), its body angular acceleration
    (``ang_accel_noise_rad_s2_rthz``) and the random walk of each tension (``tension_walk_n_rts``,
    N/sqrt(s)). ``max_step_s`` bounds the integration step; ``lag_s`` how late an image may
    arrive (older ones are dropped and counted). ``gate_chi2``: reject an image whose normalised
    innovation squared exceeds it (3 dof; ``None`` = no gate). ``cable_length_sigma_m``: if set,
    each image also applies the taut-cable length of that vehicle's cable as a measurement with
    this standard deviation. ``ukf_alpha/beta/kappa``: the scaled unscented transform
    (``alpha = 1, kappa = 0``: 2N points at ``sqrt(N) sigma``, zero mean weight at the centre).
    The noise defaults are tuned on the synthetic scenario (``sitl/load_synthetic.py``, pose NEES
    about 4 of 6 there); a flight with more unmodelled force (drag, gusts) needs larger ones.
    """

    accel_noise_m_s2_rthz: float = 0.05
    ang_accel_noise_rad_s2_rthz: float = 0.3
    tension_walk_n_rts: float = 0.3
    max_step_s: float = 0.02
    lag_s: float = 0.5
    gate_chi2: float | None = 16.27  # chi2(3) at 99.9 %
    cable_length_sigma_m: float | None = None
    ukf_alpha: float = 1.0
    ukf_beta: float = 2.0
    ukf_kappa: float = 0.0

    def __post_init__(self) -> None:
        for name in ("accel_noise_m_s2_rthz", "ang_accel_noise_rad_s2_rthz", "tension_walk_n_rts", "lag_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"LoadFilterConfig.{name} must be >= 0 and finite, got {v}")
        for name in ("max_step_s", "ukf_alpha"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"LoadFilterConfig.{name} must be positive, got {v}")
        for name in ("gate_chi2", "cable_length_sigma_m"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"LoadFilterConfig.{name} must be positive or None, got {v}")


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


def _sym(P: np.ndarray) -> np.ndarray:
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


def _substeps(dt_s: float, max_step_s: float) -> tuple[int, float]:
    n_sub = max(1, math.ceil(dt_s / max_step_s - 1e-9))
    return n_sub, dt_s / n_sub


# --- EKF ---------------------------------------------------------------------------------------


def ekf_predict(est: LoadEstimate, vehicles: VehicleStates, t_to_s: float, params: LoadParams,
                cfg: LoadFilterConfig) -> LoadEstimate:
    """Propagate to ``t_to_s`` with eq. 8 (the vehicles moving from ``vehicles``): per step ``h``,
    the nominal state by the midpoint rule and ``P <- F P F^T + Q(h)`` with
    ``F = I + A h + (A h)^2 / 2``, ``A`` from :func:`~.load_model.error_dynamics_jacobian`."""
    dt = t_to_s - est.stamp_s
    if dt < -1e-12:
        raise ValueError(f"cannot predict backwards ({est.stamp_s} -> {t_to_s})")
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
    P = _sym(P)
    return LoadEstimate(float(t_to_s), x, P)


def _ekf_correct(est: LoadEstimate, innov: np.ndarray, H: np.ndarray, R: np.ndarray,
                 gate_chi2: float | None) -> tuple[LoadEstimate, float, bool]:
    P = est.P
    S = _sym(H @ P @ H.T + R)
    S_inv = np.linalg.inv(S)
    nis = float(innov @ S_inv @ innov)
    if gate_chi2 is not None and nis > gate_chi2:
        return est, nis, False
    K = P @ H.T @ S_inv
    I_KH = np.eye(P.shape[0]) - K @ H
    P_new = _sym(I_KH @ P @ I_KH.T + K @ R @ K.T)  # Joseph form
    return LoadEstimate(est.stamp_s, boxplus(est.x, K @ innov), P_new), nis, True


def _vehicle_position(obs: LoadObservation, vehicles: VehicleStates) -> tuple[np.ndarray, np.ndarray]:
    if obs.vehicle >= vehicles.pos_w_m.shape[0]:
        raise ValueError(f"observation of vehicle {obs.vehicle}, only {vehicles.pos_w_m.shape[0]} vehicles")
    return vehicles.positions_at(obs.stamp_s)[obs.vehicle], vehicles.pos_cov_m2[obs.vehicle]


def ekf_update(est: LoadEstimate, obs: LoadObservation, vehicles: VehicleStates,
               cfg: LoadFilterConfig) -> tuple[LoadEstimate, float, bool]:
    """Eq. 4 update with one image (``est`` already at ``obs.stamp_s``): innovation
    ``y - R^T (t - p)``, noise ``cov_y + R^T cov_t R`` (the vehicle's position noise).
    Returns the estimate, the normalised innovation squared and whether it was accepted."""
    t_w, cov_t = _vehicle_position(obs, vehicles)
    H, Ht = vehicle_in_load_jacobian(est.x, t_w)
    innov = obs.vehicle_in_load_m - vehicle_in_load(est.x, t_w)
    return _ekf_correct(est, innov, H, obs.cov_m2 + Ht @ cov_t @ Ht.T, cfg.gate_chi2)


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
    dt = t_to_s - est.stamp_s
    if dt < -1e-12:
        raise ValueError(f"cannot predict backwards ({est.stamp_s} -> {t_to_s})")
    if dt <= 0.0:
        return est
    chi, Wm, Wc = _sigma_points(est, cfg)
    chi = propagate_nominal(chi, vehicles, est.stamp_s, dt, params, cfg.max_step_s)
    mean, d = _manifold_mean(chi, Wm)
    P = _sym((d * Wc[:, None]).T @ d + process_noise(mean, dt, cfg))
    return LoadEstimate(float(t_to_s), mean, P)


def _ukf_correct(est: LoadEstimate, z: np.ndarray, h_batch, R: np.ndarray, cfg: LoadFilterConfig,
                 gate_chi2: float | None) -> tuple[LoadEstimate, float, bool]:
    chi, Wm, Wc = _sigma_points(est, cfg)
    Z = h_batch(chi)
    z_hat = Wm @ Z
    dz = Z - z_hat
    dx = boxminus(chi, est.x[None, :])
    S = _sym((dz * Wc[:, None]).T @ dz + R)
    Pxz = (dx * Wc[:, None]).T @ dz
    S_inv = np.linalg.inv(S)
    innov = z - z_hat
    nis = float(innov @ S_inv @ innov)
    if gate_chi2 is not None and nis > gate_chi2:
        return est, nis, False
    K = Pxz @ S_inv
    P_new = _sym(est.P - K @ S @ K.T)
    return LoadEstimate(est.stamp_s, boxplus(est.x, K @ innov), P_new), nis, True


def ukf_update(est: LoadEstimate, obs: LoadObservation, vehicles: VehicleStates,
               cfg: LoadFilterConfig) -> tuple[LoadEstimate, float, bool]:
    """Eq. 4 update with one image through sigma points (``est`` already at ``obs.stamp_s``);
    the vehicle's position noise is added as ``R^T cov_t R`` at the mean."""
    t_w, cov_t = _vehicle_position(obs, vehicles)
    Rt = quat_to_rotmat(est.x[NOM_QUAT]).T
    return _ukf_correct(est, obs.vehicle_in_load_m, lambda chi: vehicle_in_load(chi, t_w),
                        obs.cov_m2 + Rt @ cov_t @ Rt.T, cfg, cfg.gate_chi2)


def cable_length_update(kind: FilterKind, est: LoadEstimate, vehicle: int, vehicles: VehicleStates,
                        params: LoadParams, cfg: LoadFilterConfig) -> LoadEstimate:
    """The taut-cable pseudo-measurement ``|t_i - p - R r_i| = L_i`` for one cable (no gate)."""
    if cfg.cable_length_sigma_m is None:
        return est
    t_all = vehicles.positions_at(est.stamp_s)
    H, u = cable_length_jacobian(est.x, t_all, params)
    R = np.array([[cfg.cable_length_sigma_m**2 + u[vehicle] @ vehicles.pos_cov_m2[vehicle] @ u[vehicle]]])
    z = params.cable_length_m[vehicle : vehicle + 1]
    if kind == "ekf":
        innov = z - cable_lengths(est.x, t_all, params)[vehicle : vehicle + 1]
        return _ekf_correct(est, innov, H[vehicle : vehicle + 1], R, None)[0]
    return _ukf_correct(est, z, lambda chi: cable_lengths(chi, t_all, params)[:, vehicle : vehicle + 1],
                        R, cfg, None)[0]


_PREDICT = {"ekf": ekf_predict, "ukf": ukf_predict}
_UPDATE = {"ekf": ekf_update, "ukf": ukf_update}


# --- time line with late images ----------------------------------------------------------------

_OBS, _VEH = 0, 1  # at equal stamps an image is applied before the vehicles' sample


@dataclass
class _Event:
    stamp_s: float
    rank: int
    payload: object
    after: LoadEstimate | None = None
    nis: float = math.nan
    accepted: bool = False

    @property
    def key(self) -> tuple[float, int]:
        return (self.stamp_s, self.rank)


@dataclass
class FilterStats:
    """Counters of a :class:`LoadPoseFilter`."""

    images: int = 0
    accepted: int = 0
    rejected: int = 0
    late: int = 0
    dropped_too_late: int = 0
    replayed_events: int = 0
    nis_sum: float = 0.0

    @property
    def mean_nis(self) -> float:
        """Mean normalised innovation squared of the images applied (3 for a consistent filter)."""
        n = self.accepted + self.rejected
        return self.nis_sum / n if n else math.nan


class LoadPoseFilter:
    """EKF or UKF of the load's pose over a time line of vehicle samples and images.

    ``push_vehicles`` advances the estimate to the sample's time (applying every image captured
    before it, in capture order); ``push_observation`` queues an image captured after the
    current time, or, if it is late (captured before the current time, arriving now), rolls back
    to the last kept estimate before its capture time and replays the later events with it:
    buffering and re-propagation, exact up to rounding. Events older than ``cfg.lag_s`` before
    the latest time are forgotten; images older than that are dropped (``stats.dropped_too_late``).
    """

    def __init__(self, kind: FilterKind, params: LoadParams, cfg: LoadFilterConfig, initial: LoadEstimate) -> None:
        if kind not in _PREDICT:
            raise ValueError(f"kind must be 'ekf' or 'ukf', got {kind!r}")
        if initial.n_cables != params.n_cables:
            raise ValueError(f"initial estimate has {initial.n_cables} cables, params {params.n_cables}")
        self.kind: FilterKind = kind
        self.params = params
        self.cfg = cfg
        self._base = initial  # estimate before every kept event
        self._events: list[_Event] = []  # processed, in key order
        self._pending: list[_Event] = []  # images captured after the latest processed event
        self._vehicles: list[VehicleStates] = []
        self.stats = FilterStats()

    @property
    def estimate(self) -> LoadEstimate:
        """The estimate after the latest processed event."""
        return self._events[-1].after if self._events else self._base

    def _vehicles_at(self, t_s: float) -> VehicleStates:
        stamps = [v.stamp_s for v in self._vehicles]
        i = bisect.bisect_right(stamps, t_s + 1e-12) - 1
        if i < 0:
            raise ValueError(f"no vehicle sample at or before t = {t_s}")
        return self._vehicles[i]

    def _apply(self, est: LoadEstimate, ev: _Event) -> LoadEstimate:
        if est.stamp_s < ev.stamp_s:
            est = _PREDICT[self.kind](est, self._vehicles_at(est.stamp_s), ev.stamp_s, self.params, self.cfg)
        if ev.rank == _OBS:
            obs: LoadObservation = ev.payload  # type: ignore[assignment]
            vehicles = self._vehicles_at(obs.stamp_s)
            est, nis, ok = _UPDATE[self.kind](est, obs, vehicles, self.cfg)
            ev.nis, ev.accepted = nis, ok
            self.stats.nis_sum += nis
            if ok:
                self.stats.accepted += 1
                est = cable_length_update(self.kind, est, obs.vehicle, vehicles, self.params, self.cfg)
            else:
                self.stats.rejected += 1
                log.debug("image of vehicle %d at %.3f s rejected (NIS %.1f)", obs.vehicle, obs.stamp_s, nis)
        return est

    def _process(self, events: list[_Event]) -> None:
        est = self.estimate
        for ev in events:
            est = self._apply(est, ev)
            ev.after = est
            self._events.append(ev)

    def push_vehicles(self, vehicles: VehicleStates) -> LoadEstimate:
        """A sample of every vehicle (stamps increasing); returns the estimate at its time."""
        if vehicles.pos_w_m.shape[0] != self.params.n_cables:
            raise ValueError(f"{vehicles.pos_w_m.shape[0]} vehicles for {self.params.n_cables} cables")
        if self._vehicles and vehicles.stamp_s <= self._vehicles[-1].stamp_s:
            raise ValueError(f"vehicle samples must arrive in time order ({vehicles.stamp_s} after "
                             f"{self._vehicles[-1].stamp_s})")
        if vehicles.stamp_s < self.estimate.stamp_s:
            raise ValueError(f"vehicle sample at {vehicles.stamp_s} before the estimate ({self.estimate.stamp_s})")
        self._vehicles.append(vehicles)
        ready = [e for e in self._pending if e.stamp_s <= vehicles.stamp_s]
        self._pending = [e for e in self._pending if e.stamp_s > vehicles.stamp_s]
        self._process(ready + [_Event(vehicles.stamp_s, _VEH, vehicles)])
        self._forget(vehicles.stamp_s - self.cfg.lag_s)
        return self.estimate

    def push_observation(self, obs: LoadObservation) -> None:
        """An image's measurement, possibly late (its ``stamp_s`` is the capture time)."""
        self.stats.images += 1
        ev = _Event(obs.stamp_s, _OBS, obs)
        if obs.stamp_s < self._base.stamp_s or not self._vehicles or obs.stamp_s < self._vehicles[0].stamp_s:
            self.stats.dropped_too_late += 1
            log.debug("image of vehicle %d at %.3f s is older than the kept history; dropped", obs.vehicle, obs.stamp_s)
            return
        if not self._events or ev.key > self._events[-1].key:
            # captured after the latest vehicle sample: applied when time gets there
            bisect.insort(self._pending, ev, key=lambda e: e.key)
            return
        # late: roll back to the last event before it and replay
        self.stats.late += 1
        keys = [e.key for e in self._events]
        i = bisect.bisect_left(keys, ev.key)
        replay = self._events[i:]
        self._events = self._events[:i]
        for e in replay:
            e.after = None
            if e.rank == _OBS:  # its update is undone and redone
                self.stats.nis_sum -= e.nis
                if e.accepted:
                    self.stats.accepted -= 1
                else:
                    self.stats.rejected -= 1
        self.stats.replayed_events += len(replay)
        self._process([ev] + replay)

    def _forget(self, cutoff_s: float) -> None:
        """Drop events before ``cutoff_s``; the estimate after the last dropped one becomes the base."""
        k = 0
        while k < len(self._events) - 1 and self._events[k].stamp_s < cutoff_s:
            k += 1
        if k:
            self._base = self._events[k - 1].after  # type: ignore[assignment]
            self._events = self._events[k:]
        # keep the vehicle sample in force at the base time and everything after it
        stamps = [v.stamp_s for v in self._vehicles]
        j = bisect.bisect_right(stamps, self._base.stamp_s + 1e-12) - 1
        if j > 0:
            self._vehicles = self._vehicles[j:]


# --- unfiltered baseline -----------------------------------------------------------------------


def solve_load_pose(vehicle_in_load_m: np.ndarray, vehicle_w_m: np.ndarray,
                    weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4 solved without a filter: the load pose ``(p, q_wxyz)`` with ``t_i ~ R y_i + p``
    for three or more vehicles (weighted least squares: Kabsch/Horn with an SVD).
    ``ValueError`` if fewer than three or (nearly) collinear."""
    y = np.asarray(vehicle_in_load_m, dtype=float)
    t = np.asarray(vehicle_w_m, dtype=float)
    if y.shape != t.shape or y.ndim != 2 or y.shape[1] != 3:
        raise ValueError(f"vehicle_in_load_m and vehicle_w_m must both be (k, 3), got {y.shape}, {t.shape}")
    if y.shape[0] < 3:
        raise ValueError(f"need three or more vehicles, got {y.shape[0]}")
    w = np.ones(len(y)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (len(y),) or np.any(w <= 0):
        raise ValueError("weights must be positive, one per vehicle")
    w = w / w.sum()
    y_c, t_c = w @ y, w @ t
    Y, T = y - y_c, t - t_c
    H = (Y * w[:, None]).T @ T
    U, s, Vt = np.linalg.svd(H)
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise ValueError("vehicles (nearly) collinear: the rotation about their line is unobservable")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return t_c - R @ y_c, rotmat_to_quat(R)


class UnfilteredLoadPose:
    """The unfiltered baseline: the latest image of every vehicle (captured within ``window_s``
    of the newest) solved for the pose by :func:`solve_load_pose`, weighted by the inverse trace
    of each image's covariance, vehicles' positions taken at each image's capture time. No
    dynamics, no memory beyond the latest images: what the cameras alone give. The solved pose
    refers to ``stamp_s``, the mean capture time of the images used (with a moving load, images of
    different times mix: part of this baseline's error)."""

    def __init__(self, n_vehicles: int, window_s: float = 0.1) -> None:
        if n_vehicles < 3:
            raise ValueError(f"the unfiltered solve needs three or more vehicles, got {n_vehicles}")
        if not window_s > 0:
            raise ValueError(f"window_s must be positive, got {window_s}")
        self.window_s = window_s
        self._latest: list[tuple[LoadObservation, np.ndarray] | None] = [None] * n_vehicles
        self.pos_w_m: np.ndarray | None = None
        self.q_wxyz: np.ndarray | None = None
        self.stamp_s: float | None = None

    def push(self, obs: LoadObservation, vehicles: VehicleStates) -> bool:
        """Add one image (with the vehicle samples in force at its capture time); returns whether
        a new pose was solved."""
        if obs.vehicle >= len(self._latest):
            raise ValueError(f"observation of vehicle {obs.vehicle}, only {len(self._latest)} vehicles")
        cur = self._latest[obs.vehicle]
        if cur is not None and cur[0].stamp_s > obs.stamp_s:
            return False
        self._latest[obs.vehicle] = (obs, vehicles.positions_at(obs.stamp_s)[obs.vehicle])
        newest = max(o.stamp_s for o, _ in filter(None, self._latest))
        use = [e for e in self._latest if e is not None and newest - e[0].stamp_s <= self.window_s]
        if len(use) < 3:
            return False
        try:
            p, q = solve_load_pose(np.array([o.vehicle_in_load_m for o, _ in use]), np.array([t for _, t in use]),
                                   np.array([1.0 / np.trace(o.cov_m2) for o, _ in use]))
        except ValueError:
            return False
        self.pos_w_m, self.q_wxyz, self.stamp_s = p, q, float(np.mean([o.stamp_s for o, _ in use]))
        return True


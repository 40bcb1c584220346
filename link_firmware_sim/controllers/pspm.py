"""Passive set-position modulation (PSPM) of operator set poses in E(3) and SO(3) (thesis sec. 2.3.4, refs. [34, 35]).

The slave (the ODAR) runs the spring-damper law of sec. 2.3.4 on the *modulated* set pose
``(p_bar, R_bar)``::

    f   = -K_v pdot - K_p (p - p_bar) + m g e3                       (world; gravity compensated)
    tau = -K_w omega - K_R log(R_bar^T R)^v                           (body)

(the thesis writes ``K_R theta / (2 sin theta) (R_bar^T R - R^T R_bar)^v``, which is
``K_R log(R_bar^T R)^v``). At every new operator sample ``k`` (times ``T_k``), PSPM picks the set
pose closest to the operator's ``(p_d(k), R_d(k))`` that the virtual energy reservoirs can pay for:

    min |p_d(k) - p_bar(k)|   s.t.  E_t(k) = E_t(k-1) + D_t,min(k-1) - dP_t(k) >= 0
    dP_t(k) = 1/2 |p(T_k) - p_bar(k)|^2_Kp - 1/2 |p(T_k) - p_bar(k-1)|^2_Kp
    D_t,min(k-1) = 1/(T_k - T_k-1) sum_i K_v,i (p_i^max - p_i^min)^2   over [T_k-1, T_k)

    min |log(R_bar(k)^T R_d(k))^v|  s.t.  E_r(k) = E_r(k-1) + D_r(k-1) - dP_r(k) >= 0
    dP_r(k) = 1/2 |log(R_bar(k)^T R(T_k))^v|^2_KR - 1/2 |log(R_bar(k-1)^T R(T_k))^v|^2_KR
    D_r(k-1) = sum_i K_w,i omega_i^2 (T_k - T_k-1)

and each reservoir is capped at ``E_t^max`` / ``E_r^max`` (the excess is discarded). Readings:

* ``D_r``: the thesis's one-sample rectangle; here the sum of ``K_w omega^2 dt`` over the control
  ticks of the interval (the same when the operator's rate equals the control rate). It is an
  approximation of the damper's dissipation, not a lower bound like ``D_t,min``.
* The position problem is the Euclidean projection of ``p_d`` on the ellipsoid
  ``1/2 |x - p|^2_Kp <= E + D + 1/2 |p - p_bar(k-1)|^2_Kp`` (:func:`project_to_ellipsoid`, exact).
  The rotation problem is solved in the tangent space at ``R(T_k)``: ``R_bar = R Exp(y)`` with
  ``y`` the same projection of ``log(R^T R_d)`` on ``1/2 |y|^2_KR <= budget`` (exact for an
  isotropic ``K_R``: the closest point then lies on the geodesic; for an anisotropic one it is
  the projection in those coordinates). Either way the energy constraint holds exactly, so the
  reservoirs never go negative (``tests/unit/test_pspm.py`` checks it with random inputs).

The master side (sec. 2.3.4, last pair): ``p_d = eta p_h + p_0``, ``R_d = R_h`` and the haptic
feedback ``f_h = -B_ht pdot_h - K_ht (p_d - p_bar) + K_hf f_e^``, ``tau_h = -B_hr omega_h -
K_hr (R_bar^T R_d - R_d^T R_bar)^v + K_htau tau_e^`` (:func:`haptic_feedback`).

Pure functions of numpy arrays (no clock: times and ``dt_s`` are arguments) plus
:class:`PspmModulator`, a thin holder of the state, and :class:`PspmSlave`, the slave law as a
firmware controller (``SKL_PSPM_EN``, :class:`~link_firmware_sim.firmware.FirmwareConfig`
``pspm_mode``: every pose target is then an operator set pose, modulated by PSPM).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat, quat_to_rotvec, rotmat_to_quat
from companion.skeleton.body import GRAVITY_M_S2

from .base import Controller
from .common import require_gains, vee

__all__ = [
    "PspmGains",
    "PspmState",
    "HapticGains",
    "project_to_ellipsoid",
    "so3_log",
    "pspm_init",
    "pspm_observe",
    "pspm_update",
    "slave_wrench",
    "master_set_pose",
    "haptic_feedback",
    "PspmModulator",
    "PspmSlave",
]


@dataclass(frozen=True)
class PspmGains:
    """Slave spring-damper gains (diagonal) and the reservoirs' caps and initial energies [J]."""

    kp_n_m: tuple[float, float, float] = (11.0, 11.0, 11.0)
    kv_ns_m: tuple[float, float, float] = (4.0, 4.0, 4.0)
    kR_nm: tuple[float, float, float] = (6.0, 6.0, 6.0)
    kw_nms: tuple[float, float, float] = (0.6, 0.6, 0.6)
    e_max_t_j: float = 2.0
    e_max_r_j: float = 1.0
    e0_t_j: float = 0.0
    e0_r_j: float = 0.0

    def __post_init__(self) -> None:
        for name in ("kp_n_m", "kv_ns_m", "kR_nm", "kw_nms"):
            require_gains(name, getattr(self, name), 3, positive=True)
        for name in ("e_max_t_j", "e_max_r_j", "e0_t_j", "e0_r_j"):
            require_gains(name, getattr(self, name))
        if self.e0_t_j > self.e_max_t_j or self.e0_r_j > self.e_max_r_j:
            raise ValueError("the initial reservoir energies must not exceed their caps")


@dataclass(frozen=True)
class PspmState:
    """Modulated set pose, reservoirs [J], and what the current interval has seen: the position's
    per-axis extremes and the rotational damper's dissipation [J]; ``t_s``: the last update's time."""

    p_bar_w_m: np.ndarray
    q_bar_wxyz: np.ndarray
    energy_t_j: float
    energy_r_j: float
    p_max_w_m: np.ndarray
    p_min_w_m: np.ndarray
    diss_r_j: float
    t_s: float
    #: the last update's reservoir bookkeeping: dissipation credited and spring energy jump [J]
    last: dict = field(default_factory=dict)


def project_to_ellipsoid(b: np.ndarray, k: np.ndarray, budget: float) -> np.ndarray:
    """The point ``y`` closest to ``b`` (Euclidean) with ``1/2 y^T diag(k) y <= budget``.

    KKT: ``y = b / (1 + mu k)`` with ``mu >= 0`` solving ``1/2 sum k_i b_i^2 / (1 + mu k_i)^2 =
    budget``, monotone in ``mu`` (bisection)."""
    b = np.asarray(b, dtype=float)
    k = np.asarray(k, dtype=float)
    budget = max(float(budget), 0.0)
    g = lambda mu: 0.5 * float(np.sum(k * (b / (1.0 + mu * k)) ** 2))  # noqa: E731
    if g(0.0) <= budget:
        return b.copy()
    if budget <= 0.0:
        return np.zeros_like(b)
    lo, hi = 0.0, 1.0
    while g(hi) > budget:
        hi *= 4.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) > budget else (lo, mid)
    return b / (1.0 + hi * k)  # the feasible end: the constraint holds


def so3_log(R: np.ndarray) -> np.ndarray:
    """``log(R)^v``: the rotation vector of ``R`` (angle in [0, pi])."""
    return quat_to_rotvec(rotmat_to_quat(R))


def pspm_init(p_w_m, q_wxyz, gains: PspmGains, t_s: float) -> PspmState:
    """Start with the set pose at the slave's pose and the initial reservoirs."""
    p = np.asarray(p_w_m, dtype=float)
    return PspmState(p.copy(), np.asarray(q_wxyz, dtype=float).copy(), gains.e0_t_j, gains.e0_r_j, p.copy(), p.copy(),
                     0.0, t_s)


def pspm_observe(state: PspmState, gains: PspmGains, p_w_m, omega_b_rad_s, dt_s: float) -> PspmState:
    """A control tick between updates: the position's extremes and the rotational dissipation."""
    p = np.asarray(p_w_m, dtype=float)
    w = np.asarray(omega_b_rad_s, dtype=float)
    return PspmState(state.p_bar_w_m, state.q_bar_wxyz, state.energy_t_j, state.energy_r_j,
                     np.maximum(state.p_max_w_m, p), np.minimum(state.p_min_w_m, p),
                     state.diss_r_j + float(np.sum(np.asarray(gains.kw_nms) * w * w)) * dt_s, state.t_s, state.last)


def pspm_update(state: PspmState, gains: PspmGains, p_d_w_m, q_d_wxyz, p_w_m, q_wxyz, t_s: float) -> PspmState:
    """A new operator sample ``(p_d, q_d)`` at ``t_s`` with the slave at ``(p, q)``: the modulated set pose."""
    p = np.asarray(p_w_m, dtype=float)
    kp, kR = np.asarray(gains.kp_n_m, dtype=float), np.asarray(gains.kR_nm, dtype=float)
    interval = t_s - state.t_s
    p_max, p_min = np.maximum(state.p_max_w_m, p), np.minimum(state.p_min_w_m, p)
    d_t = float(np.sum(np.asarray(gains.kv_ns_m) * (p_max - p_min) ** 2)) / interval if interval > 0 else 0.0
    # translation: the ellipsoid about p that E + D + the current spring energy pays for
    spring_old = 0.5 * float(np.sum(kp * (p - state.p_bar_w_m) ** 2))
    avail_t = state.energy_t_j + d_t
    y = project_to_ellipsoid(np.asarray(p_d_w_m, dtype=float) - p, kp, avail_t + spring_old)
    p_bar = p + y
    dP_t = 0.5 * float(np.sum(kp * y * y)) - spring_old
    e_t = min(max(avail_t - dP_t, 0.0), gains.e_max_t_j)  # max(): rounding only (the projection is feasible)
    # rotation: tangent space at R, R_bar = R Exp(y_r)
    R = quat_to_rotmat(np.asarray(q_wxyz, dtype=float))
    spring_old_r = 0.5 * float(np.sum(kR * so3_log(quat_to_rotmat(state.q_bar_wxyz).T @ R) ** 2))
    avail_r = state.energy_r_j + state.diss_r_j
    b = so3_log(R.T @ quat_to_rotmat(np.asarray(q_d_wxyz, dtype=float)))
    y_r = project_to_ellipsoid(b, kR, avail_r + spring_old_r)
    R_bar = R @ quat_to_rotmat(quat_from_rotvec(y_r))
    dP_r = 0.5 * float(np.sum(kR * so3_log(R_bar.T @ R) ** 2)) - spring_old_r
    e_r = min(max(avail_r - dP_r, 0.0), gains.e_max_r_j)
    last = {"d_t_j": d_t, "dP_t_j": dP_t, "d_r_j": state.diss_r_j, "dP_r_j": dP_r,
            "modulated_m": float(np.linalg.norm(np.asarray(p_d_w_m) - p_bar))}
    return PspmState(p_bar, rotmat_to_quat(R_bar), e_t, e_r, p.copy(), p.copy(), 0.0, t_s, last)


def slave_wrench(p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, p_bar_w_m, q_bar_wxyz, gains: PspmGains,
                 mass_kg: float) -> np.ndarray:
    """The slave law of sec. 2.3.4 as the body-frame wrench ``U = [R^T f; tau]`` (gravity compensated)."""
    R = quat_to_rotmat(np.asarray(q_wxyz, dtype=float))
    f = (-np.asarray(gains.kv_ns_m) * v_w_m_s - np.asarray(gains.kp_n_m) * (np.asarray(p_w_m) - p_bar_w_m)
         + np.array([0.0, 0.0, mass_kg * GRAVITY_M_S2]))
    tau = (-np.asarray(gains.kw_nms) * omega_b_rad_s
           - np.asarray(gains.kR_nm) * so3_log(quat_to_rotmat(np.asarray(q_bar_wxyz)).T @ R))
    return np.concatenate((R.T @ f, tau))


@dataclass(frozen=True)
class HapticGains:
    """Master-side mapping and haptic feedback gains (diagonal, sec. 2.3.4)."""

    eta: float = 1.0
    p0_w_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    b_ht_ns_m: float = 2.0
    k_ht_n_m: float = 20.0
    k_hf: float = 0.5
    b_hr_nms: float = 0.05
    k_hr_nm: float = 0.5
    k_htau: float = 0.2


def master_set_pose(p_h_m, q_h_wxyz, gains: HapticGains) -> tuple[np.ndarray, np.ndarray]:
    """``p_d = eta p_h + p_0``, ``R_d = R_h``."""
    return gains.eta * np.asarray(p_h_m, dtype=float) + np.asarray(gains.p0_w_m), np.asarray(q_h_wxyz, dtype=float)


def haptic_feedback(v_h_m_s, omega_h_rad_s, p_d_w_m, q_d_wxyz, p_bar_w_m, q_bar_wxyz, f_e_hat_n, tau_e_hat_nm,
                    gains: HapticGains) -> tuple[np.ndarray, np.ndarray]:
    """The operator's force and torque ``(f_h, tau_h)``: what PSPM withheld, felt as a spring, plus the
    (estimated) external wrench."""
    R_d, R_bar = quat_to_rotmat(np.asarray(q_d_wxyz)), quat_to_rotmat(np.asarray(q_bar_wxyz))
    E = R_bar.T @ R_d
    f_h = (-gains.b_ht_ns_m * np.asarray(v_h_m_s) - gains.k_ht_n_m * (np.asarray(p_d_w_m) - p_bar_w_m)
           + gains.k_hf * np.asarray(f_e_hat_n))
    tau_h = -gains.b_hr_nms * np.asarray(omega_h_rad_s) - gains.k_hr_nm * vee(E - E.T) + gains.k_htau * np.asarray(tau_e_hat_nm)
    return f_h, tau_h


class PspmModulator:
    """PSPM with its state: :meth:`observe` every control tick, :meth:`update` per operator sample."""

    def __init__(self, gains: PspmGains):
        self.gains = gains
        self.state: PspmState | None = None

    def observe(self, p_w_m, q_wxyz, omega_b_rad_s, t_s: float, dt_s: float) -> None:
        if self.state is None:
            self.state = pspm_init(p_w_m, q_wxyz, self.gains, t_s)
        self.state = pspm_observe(self.state, self.gains, p_w_m, omega_b_rad_s, dt_s)

    def update(self, p_d_w_m, q_d_wxyz, p_w_m, q_wxyz, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        if self.state is None:
            self.state = pspm_init(p_w_m, q_wxyz, self.gains, t_s)
        self.state = pspm_update(self.state, self.gains, p_d_w_m, q_d_wxyz, p_w_m, q_wxyz, t_s)
        return self.state.p_bar_w_m, self.state.q_bar_wxyz


class PspmSlave(Controller):
    """The slave law of sec. 2.3.4 (:func:`slave_wrench`) as the firmware's controller,
    ``ctrl(p, v, q, omega, target, dt) -> U``, on the target's pose (the modulated set pose under
    PSPM; the target's velocity, acceleration and rates are not used: the slave law has none). With
    a modulator it also does the modulator's per-tick bookkeeping (:func:`pspm_observe`) once the
    modulator has a state (from the first operator sample on)."""

    def __init__(self, gains: PspmGains, mass_kg: float, modulator: PspmModulator | None = None):
        if not (math.isfinite(mass_kg) and mass_kg > 0):
            raise ValueError(f"mass_kg must be positive, got {mass_kg!r}")
        self.gains = gains
        self.mass_kg = mass_kg
        self.modulator = modulator

    def reset(self) -> None:
        """Arming: the modulator starts again at the slave's pose with its initial reservoirs."""
        if self.modulator is not None:
            self.modulator.state = None

    def __call__(self, p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target, dt_s: float) -> np.ndarray:
        mod = self.modulator
        if mod is not None and mod.state is not None:
            mod.state = pspm_observe(mod.state, self.gains, p_w_m, omega_b_rad_s, dt_s)
        return slave_wrench(p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target.p_w_m, target.q_wxyz, self.gains,
                            self.mass_kg)

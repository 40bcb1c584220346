"""Hybrid pose/wrench control of one ODAR link and its momentum-based external-wrench observer (thesis sec. 2.3.3).

Coordinates are those of (2.9): ``qdot = [pdot_w; omega_b]`` (world linear velocity, body rate),
``M = diag(m I, J)``, ``C qdot = [0; omega x J omega]``, ``G = [m g e3; 0]``, the control wrench
``w = [f_w; tau_b]`` (``U = [R^T f_w; tau_b]`` goes to the allocator) and the external wrench
``w_e = [f_e,w; tau_e,b]``, so that ``M qddot + C qdot + G + A^T lambda_c = w + w_e``.

**Observer** (sec. 2.3.3, the unnumbered pair after the hybrid law; refs. [32, 33])::

    w_e^ = k_e ( M qdot - int_0^t (w - C qdot - G + w_e^) ds - M qdot(0) )
    lambda_c^ = -(A A^T)^-1 A w_e^

(the initial momentum is subtracted so that ``w_e^(0) = 0``; the thesis's formula assumes rest).
Its error obeys ``d/dt w~ = -k_e w~ + k_e d/dt w_e``: a first-order low-pass of the true external
wrench with time constant ``1/k_e`` per axis. Discretised with the integral updated after the
estimate (explicit Euler), which is stable for ``k_e dt < 2``. The applied wrench ``w`` is what the
rotors produce; the firmware passes ``B lambda_cmd`` (the clipped commands), optionally through a
first-order lag of the ESC's time constant (``actuator_time_constant_s``).

**Hybrid law** (sec. 2.3.3)::

    w = M Delta Omega (qdd_d - K_d edot - K_p e - K_i e_i) + C qdot + G + A^T [lambda_d - K_f int(lambda_c^ - lambda_d)]

with ``Delta`` a basis of the null space of the Pfaffian ``A`` (``A Delta = 0``), ``Omega =
(Delta^T M Delta)^-1 Delta^T M``, ``e = [p - p_d; e_R]``, ``edot = [v - v_d; omega - omega'_d]``,
``e_i = [int(e_p); e_RI]`` (the SO(3) integral of sec. 2.3.2 with ``c_2``) and ``qdd_d = [a_d;
wdot'_d]``. The thesis writes ``Omega`` on every error term (``e_phi = Omega e``); ``M Delta
Omega`` of the stacked terms is the same. Readings:

* ``K_d, K_p, K_i`` are scalars in the thesis; here they are 6-vectors acting on the stacked
  errors before the projection (with equal entries the law is the thesis's exactly; translation
  and rotation differ by orders of magnitude in stiffness, so they get their own values).
* ``Delta`` is recomputed every call from ``A``; ``Delta_dot`` (which the thesis keeps in
  ``qdd_d`` and the Coriolis term) is dropped: ``A`` depends on the attitude only through the
  contact point's lever arm, and the attitude is held in the free directions.
* With no contact (``A`` with zero rows) ``Delta = I`` and the law is a computed-torque SE(3) PID.

One contact: a point ``r_b`` of the body pressed along the world unit normal ``n_w`` (into the
surface). Its Pfaffian row is ``A = [n_w^T, (r_b x R^T n_w)^T]`` (the tip's velocity along
``n_w`` is zero) and ``lambda_c`` is the force the link applies along ``n_w``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_finite_positive
from companion.estimation.so3 import quat_to_rotmat
from companion.messages import ContactTarget, PoseTarget  # ContactTarget: one schema, also on MAVLink
from companion.skeleton.body import GRAVITY_M_S2, LinkInertia

from .base import Controller
from .common import E3, limit_length, require_gains
from .se3_control import attitude_error_so3, c2_bound

__all__ = [
    "ContactTarget",
    "HybridGains",
    "HybridIntegrals",
    "ObserverConfig",
    "ObserverState",
    "contact_pfaffian",
    "null_basis",
    "m_projector",
    "generalized_mass",
    "coriolis_gravity",
    "observer_step",
    "contact_force_estimate",
    "hybrid_control",
    "MomentumObserver",
    "HybridController",
]

# Named slices of the 6-vectors (qdot, wrenches, gains): linear part, angular part.
LIN = slice(0, 3)
ANG = slice(3, 6)

@dataclass(frozen=True)
class HybridGains:
    """Gains of the hybrid law (6-vectors: ``[translation x3, rotation x3]``, per unit of ``M``).

    Defaults: translation about 2 rad/s (as the impedance defaults on a 2.6 kg link), rotation
    about 4.4 rad/s, both damped about 0.8; the force integral ``K_f`` [1/s].
    """

    kp_1_s2: tuple[float, ...] = (4.2, 4.2, 4.2, 19.0, 19.0, 19.0)
    kd_1_s: tuple[float, ...] = (3.4, 3.4, 3.4, 7.0, 7.0, 7.0)
    ki_1_s3: tuple[float, ...] = (0.8, 0.8, 0.8, 2.0, 2.0, 2.0)
    kf_1_s: float = 3.0
    #: c_2 of the SO(3) integral (sec. 2.3.2); ``None``: 0.9 x the bound for ``M``-scaled gains
    c2: float | None = None
    pos_integral_limit_ms: float = 2.0
    att_integral_limit_rad: float = 1.0
    force_integral_limit_ns: float = 20.0
    #: the position error taken at most this long [m], as eq. 1's (control.ImpedanceGains)
    pos_error_limit_m: float = 2.0

    def __post_init__(self) -> None:
        require_finite_positive(self, "pos_error_limit_m")
        for name in ("kp_1_s2", "kd_1_s", "ki_1_s3"):
            require_gains(name, getattr(self, name), 6)
        for name in ("kf_1_s", "pos_integral_limit_ms", "att_integral_limit_rad", "force_integral_limit_ns"):
            require_gains(name, getattr(self, name))
        if self.c2 is not None:
            require_gains("c2", self.c2)

    def resolved_c2(self, inertia: LinkInertia) -> float:
        if self.c2 is not None:
            return self.c2
        J = np.asarray(inertia.inertia_kgm2)
        # the rotational loop's torque gains are J K_p, J K_d: use the smallest per-axis values
        return 0.9 * c2_bound(float(min(J * self.kp_1_s2[ANG])), float(min(J * self.kd_1_s[ANG])), inertia)


@dataclass(frozen=True)
class HybridIntegrals:
    """``int(e_p)`` [m s], ``e_RI`` [rad] and ``int(lambda_c^ - lambda_d)`` [N s] (one per contact)."""

    pos_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    att_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    force_n_s: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class ObserverConfig:
    """Momentum observer: gain ``k_e`` [1/s] per axis ``[force x3, torque x3]`` and the ESC lag
    assumed on the commanded wrench [s] (0: the command is applied at once)."""

    gain_1_s: tuple[float, ...] = (8.0, 8.0, 8.0, 8.0, 8.0, 8.0)
    actuator_time_constant_s: float = 0.05

    def __post_init__(self) -> None:
        require_gains("gain_1_s", self.gain_1_s, 6)
        if not (math.isfinite(self.actuator_time_constant_s) and self.actuator_time_constant_s >= 0):
            raise ValueError(f"actuator_time_constant_s must be >= 0, got {self.actuator_time_constant_s!r}")


@dataclass(frozen=True)
class ObserverState:
    """``int(w - C qdot - G + w_e^) ds + M qdot(0)`` [N s | N m s], the estimate ``w_e^``
    ``[f_e,w; tau_e,b]`` and the lagged applied wrench ``[f_w; tau_b]``."""

    integral: np.ndarray
    wrench_e: np.ndarray = field(default_factory=lambda: np.zeros(6))
    applied: np.ndarray | None = None


# -- functional core ------------------------------------------------------------------------------


def generalized_mass(inertia: LinkInertia) -> np.ndarray:
    """``M = diag(m I, J)`` of (2.9)."""
    return np.diag(np.concatenate((np.full(3, inertia.mass_kg), np.asarray(inertia.inertia_kgm2, dtype=float))))


def coriolis_gravity(inertia: LinkInertia, omega_b_rad_s: np.ndarray) -> np.ndarray:
    """``C qdot + G = [m g e3; omega x J omega]`` of (2.9)."""
    J = np.asarray(inertia.inertia_kgm2, dtype=float)
    return np.concatenate((inertia.mass_kg * GRAVITY_M_S2 * E3, np.cross(omega_b_rad_s, J * omega_b_rad_s)))


def contact_pfaffian(contact: ContactTarget | None, R: np.ndarray) -> np.ndarray:
    """``A`` (n_p x 6): ``[n_w^T, (r_b x R^T n_w)^T]`` for one contact, (0 x 6) for none."""
    if contact is None:
        return np.zeros((0, 6))
    n = np.asarray(contact.normal_w, dtype=float)
    return np.concatenate((n, np.cross(np.asarray(contact.contact_b_m, dtype=float), R.T @ n)))[None, :]


def null_basis(A: np.ndarray) -> np.ndarray:
    """``Delta`` (6 x (6 - n_p)): an orthonormal basis of ``null(A)`` (``A`` full row rank)."""
    if A.shape[0] == 0:
        return np.eye(6)
    _, s, Vt = np.linalg.svd(A)
    if s.min() < 1e-9:
        raise ValueError("the Pfaffian constraint matrix A is rank deficient")
    return Vt[A.shape[0]:].T


def m_projector(Delta: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``Delta Omega`` with ``Omega = (Delta^T M Delta)^-1 Delta^T M``: the ``M``-orthogonal
    projector onto ``range(Delta)``."""
    return Delta @ np.linalg.solve(Delta.T @ M @ Delta, Delta.T @ M)


def _qdot(v_w_m_s: np.ndarray, omega_b_rad_s: np.ndarray) -> np.ndarray:
    return np.concatenate((v_w_m_s, omega_b_rad_s))


def observer_step(
    state: ObserverState,
    config: ObserverConfig,
    inertia: LinkInertia,
    v_w_m_s: np.ndarray,
    omega_b_rad_s: np.ndarray,
    applied_w: np.ndarray,
    dt_s: float,
) -> ObserverState:
    """One observer step: the estimate ``w_e^`` at this instant and the integral advanced by ``dt_s``.

    ``applied_w``: the wrench commanded of the rotors ``[f_w; tau_b]`` (lagged here by
    ``config.actuator_time_constant_s``)."""
    tau = config.actuator_time_constant_s
    if state.applied is None or tau <= 0.0:
        applied = np.asarray(applied_w, dtype=float) if tau <= 0.0 or state.applied is None else state.applied
    else:
        a = 1.0 - math.exp(-dt_s / tau)
        applied = state.applied + a * (np.asarray(applied_w, dtype=float) - state.applied)
    M_diag = np.diag(generalized_mass(inertia))
    momentum = M_diag * _qdot(v_w_m_s, omega_b_rad_s)
    k = np.asarray(config.gain_1_s, dtype=float)
    w_e = k * (momentum - state.integral)
    integral = state.integral + dt_s * (applied - coriolis_gravity(inertia, omega_b_rad_s) + w_e)
    return ObserverState(integral, w_e, applied)


def observer_init(inertia: LinkInertia, v_w_m_s: np.ndarray, omega_b_rad_s: np.ndarray) -> ObserverState:
    """Start the observer at the current momentum (``w_e^ = 0``)."""
    return ObserverState(np.diag(generalized_mass(inertia)) * _qdot(np.asarray(v_w_m_s, float),
                                                                     np.asarray(omega_b_rad_s, float)))


def contact_force_estimate(A: np.ndarray, wrench_e: np.ndarray) -> np.ndarray:
    """``lambda_c^ = -(A A^T)^-1 A w_e^``: the force the link applies along each contact normal."""
    if A.shape[0] == 0:
        return np.zeros(0)
    return -np.linalg.solve(A @ A.T, A @ wrench_e)


def hybrid_control(
    p_w_m: np.ndarray,
    v_w_m_s: np.ndarray,
    q_wxyz: np.ndarray,
    omega_b_rad_s: np.ndarray,
    target: PoseTarget,
    contact: ContactTarget | None,
    lambda_hat_n: np.ndarray,
    gains: HybridGains,
    inertia: LinkInertia,
    integrals: HybridIntegrals,
    dt_s: float,
    c2: float | None = None,
) -> tuple[np.ndarray, HybridIntegrals]:
    """The hybrid law (module docstring): body-frame ``U = [R^T f; tau]`` and the updated integrals.

    ``lambda_hat_n``: the observer's contact-force estimate (one per contact row of ``A``)."""
    if c2 is None:
        c2 = gains.resolved_c2(inertia)
    R = quat_to_rotmat(q_wxyz)
    R_d = target.R_d
    RtRd = R.T @ R_d
    M = generalized_mass(inertia)
    A = contact_pfaffian(contact, R)
    P = m_projector(null_basis(A), M)
    e_R = attitude_error_so3(R, R_d)
    w_d = RtRd @ target.omega_d_rad_s
    e = np.concatenate((limit_length((p_w_m - target.p_w_m).tolist(), gains.pos_error_limit_m), e_R))
    edot = np.concatenate((v_w_m_s - target.v_w_m_s, omega_b_rad_s - w_d))
    pos_int = np.clip(integrals.pos_m_s + e[LIN] * dt_s, -gains.pos_integral_limit_ms, gains.pos_integral_limit_ms)
    att_int = np.clip(integrals.att_rad + (edot[ANG] + c2 * e_R) * dt_s,
                      -gains.att_integral_limit_rad, gains.att_integral_limit_rad)
    e_i = np.concatenate((pos_int, att_int))
    qdd_d = np.concatenate((target.a_w_m_s2, RtRd @ target.omega_dot_d_rad_s2))
    kp, kd, ki = (np.asarray(g, dtype=float) for g in (gains.kp_1_s2, gains.kd_1_s, gains.ki_1_s3))
    w = M @ P @ (qdd_d - kd * edot - kp * e - ki * e_i) + coriolis_gravity(inertia, omega_b_rad_s)
    n_p = A.shape[0]
    force_int = integrals.force_n_s if integrals.force_n_s.shape == (n_p,) else np.zeros(n_p)
    if n_p:
        lam_d = np.array([contact.force_n])
        force_int = np.clip(force_int + (np.asarray(lambda_hat_n, dtype=float) - lam_d) * dt_s,
                            -gains.force_integral_limit_ns, gains.force_integral_limit_ns)
        w = w + A.T @ (lam_d - gains.kf_1_s * force_int)
    w[LIN] += target.force_ff_w_n
    w[ANG] += RtRd @ target.torque_ff_b_nm
    return np.concatenate((R.T @ w[LIN], w[ANG])), HybridIntegrals(pos_int, att_int, force_int)


# -- thin classes ----------------------------------------------------------------------------------


class MomentumObserver:
    """The momentum observer with its state (:func:`observer_step`)."""

    def __init__(self, config: ObserverConfig, inertia: LinkInertia):
        self.config = config
        self.inertia = inertia
        self.state: ObserverState | None = None

    @property
    def wrench_e(self) -> np.ndarray:
        """Latest estimate ``[f_e,w; tau_e,b]`` (zeros before the first step)."""
        return np.zeros(6) if self.state is None else self.state.wrench_e

    def reset(self) -> None:
        self.state = None

    def step(self, v_w_m_s, omega_b_rad_s, applied_w, dt_s: float) -> np.ndarray:
        if self.state is None:
            self.state = observer_init(self.inertia, v_w_m_s, omega_b_rad_s)
        self.state = observer_step(self.state, self.config, self.inertia, np.asarray(v_w_m_s, float),
                                   np.asarray(omega_b_rad_s, float), applied_w, dt_s)
        return self.state.wrench_e


class HybridController(Controller):
    """The hybrid law as the firmware's controller: its integrators (``c_2`` resolved once), the
    momentum observer it runs (:attr:`observer`, stepped by :meth:`observe` with the wrench the
    rotors produce) and the commanded :attr:`contact` (``None``: pose control only), whose force
    it estimates from the observer (:meth:`contact_estimate`)."""

    def __init__(self, gains: HybridGains, inertia: LinkInertia, observer: ObserverConfig = ObserverConfig()):
        self.gains = gains
        self.inertia = inertia
        self.c2 = gains.resolved_c2(inertia)
        self.integrals = HybridIntegrals()
        self.observer = MomentumObserver(observer, inertia)
        self.contact: ContactTarget | None = None

    def reset(self) -> None:
        self.integrals = HybridIntegrals()
        self.observer.reset()

    def contact_estimate(self, q_wxyz) -> np.ndarray:
        """The observer's estimate of the contact force (one per contact; empty without one)."""
        if self.contact is None:
            return np.zeros(0)
        return contact_force_estimate(contact_pfaffian(self.contact, quat_to_rotmat(q_wxyz)), self.observer.wrench_e)

    def __call__(self, p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target: PoseTarget, dt_s: float) -> np.ndarray:
        return self.command(p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target, self.contact,
                            self.contact_estimate(q_wxyz), dt_s)

    def command(self, p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target: PoseTarget, contact: ContactTarget | None,
                lambda_hat_n, dt_s: float) -> np.ndarray:
        """:func:`hybrid_control` with the integrators, for a given contact and force estimate."""
        U, self.integrals = hybrid_control(p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target, contact, lambda_hat_n,
                                           self.gains, self.inertia, self.integrals, dt_s, self.c2)
        return U

    def observe(self, v_w_m_s, q_wxyz, omega_b_rad_s, applied_b: np.ndarray, dt_s: float) -> None:
        """The momentum observer's step with the applied wrench in its frames, ``[R u; tau]``."""
        self.observer.step(v_w_m_s, omega_b_rad_s,
                           np.concatenate((quat_to_rotmat(q_wxyz) @ applied_b[:3], applied_b[3:])), dt_s)

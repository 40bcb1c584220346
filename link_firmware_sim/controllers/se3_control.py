"""SE(3) PID pose-tracking control of one ODAR link (thesis sec. 2.3.2, with the SO(3) integral of its ref. [31]).

Thesis sec. 2.3.2 (the unnumbered pair after (2.8)), on the fully actuated model (2.7)::

    f   = m pdd_d - k_d e_p' - k_p e_p - k_I int(e_p) + m g e3                        (world)
    tau = J wdot'_d + w'_d x J w'_d - k_w (w - w'_d) - k_R e_R - k_RI e_RI             (body)

    e_p = p - p_d,   e_R = 1/2 (R_d^T R - R^T R_d)^v,   w'_d = R^T R_d w_d,   wdot'_d = R^T R_d wdot_d
    e_RI = int (w - w'_d + c_2 e_R) dt                                               (ref. [31])

Readings, stated because they matter:

* The thesis prints ``e_R := 1/2 k_R (...)^v`` and then multiplies by ``k_R`` again; the gain
  appears once here (``e_R`` is the geometric attitude error of [31], ``e_R ~ dtheta`` for small
  errors, half of eq. 1's).
* ``c_2`` "decided as in [31]": [31] (Goodarzi, Lee, Lee, ECC 2013) picks ``c_2`` small enough
  that its Lyapunov function ``V = 1/2 e_w.J e_w + k_R Psi + c_2 e_R.J e_w`` (plus the integral
  term) is positive definite with a negative-definite derivative. With ``Psi >= 1/2 |e_R|^2`` and
  ``|d/dt e_R| <= |e_w|`` the two conditions are, derived here for ``J = diag`` with extreme
  eigenvalues ``l_m <= l_M`` (:func:`c2_bound`)::

      c_2 < sqrt(k_R l_m) / l_M                      (V > 0)
      c_2 < 4 k_R k_w / (k_w^2 + 4 k_R l_M)          (dV/dt < 0 on the PD part)

  ``Se3PidGains.c2`` defaults to ``None``: 0.9 times that bound for the link's inertia; a given
  value is checked against it. We could not read [31]'s own inequality in the sources available,
  so the bound is our derivation along its proof, not a quotation.
* The thesis's ``omega_d`` is in the ``R_d`` frame, as ``PoseTarget.omega_d_rad_s`` is; the
  feed-forward ``J wdot'_d + w'_d x J w'_d`` is printed without the ``-J (w x w'_d)`` transport
  term of [31]; we keep the printed law (the difference is second order in the rate error).

Integrals have symmetric clamps (anti-windup), as the impedance controller's. The whole-chain
feed-forward of :class:`~companion.messages.PoseTarget` is added as in :mod:`.impedance`.

Pure functions of numpy arrays (no clock: ``dt_s`` is an argument) plus :class:`Se3PidController`,
a thin holder of the integrator state; ``tests/unit/test_se3_hybrid.py`` checks that they agree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_finite_positive
from companion.estimation.so3 import quat_to_rotmat
from companion.messages import PoseTarget
from companion.skeleton.body import GRAVITY_M_S2, LinkInertia

from .base import Controller
from .common import E3, limit_length, require_gains, vee

__all__ = [
    "Se3PidGains",
    "Se3PidIntegrals",
    "attitude_error_so3",
    "c2_bound",
    "resolved_c2",
    "se3_pid_control",
    "Se3PidController",
]

@dataclass(frozen=True)
class Se3PidGains:
    """Gains of sec. 2.3.2 (per world axis for translation, scalars for rotation).

    Defaults give the same closed-loop bandwidth as the impedance controller's defaults (eq. 1's
    ``k_R = 3`` on an error twice as large is ``k_R = 6`` here), with the position integral on.
    """

    kp_n_m: tuple[float, float, float] = (11.0, 11.0, 11.0)
    kd_ns_m: tuple[float, float, float] = (9.0, 9.0, 9.0)
    ki_n_ms: tuple[float, float, float] = (2.0, 2.0, 2.0)
    kR_nm: float = 6.0
    kw_nms: float = 1.2
    kRI_nm_s: float = 0.6
    #: c_2 of [31]; ``None``: 0.9 x :func:`c2_bound` of the link
    c2: float | None = None
    pos_integral_limit_ms: float = 2.0
    att_integral_limit_rad: float = 1.0
    #: the position error taken at most this long [m], as eq. 1's (control.ImpedanceGains)
    pos_error_limit_m: float = 2.0

    def __post_init__(self) -> None:
        require_finite_positive(self, "pos_error_limit_m")
        for name in ("kp_n_m", "kd_ns_m", "ki_n_ms"):
            require_gains(name, getattr(self, name), 3)
        for name in ("kR_nm", "kw_nms", "kRI_nm_s", "pos_integral_limit_ms", "att_integral_limit_rad"):
            require_gains(name, getattr(self, name))
        if self.c2 is not None:
            require_gains("c2", self.c2)


@dataclass(frozen=True)
class Se3PidIntegrals:
    """Integrator states: ``int(e_p) dt`` [m s] and ``e_RI`` of [31] [rad]."""

    pos_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    att_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))


def c2_bound(kR_nm: float, kw_nms: float, inertia: LinkInertia) -> float:
    """Largest ``c_2`` for which the Lyapunov argument of [31] holds (module docstring)."""
    lm, lM = min(inertia.inertia_kgm2), max(inertia.inertia_kgm2)
    if kR_nm <= 0 or kw_nms <= 0:
        return 0.0
    return min(math.sqrt(kR_nm * lm) / lM, 4.0 * kR_nm * kw_nms / (kw_nms**2 + 4.0 * kR_nm * lM))


def resolved_c2(gains: Se3PidGains, inertia: LinkInertia) -> float:
    """``gains.c2`` checked against :func:`c2_bound`, or 0.9 times the bound when not given."""
    bound = c2_bound(gains.kR_nm, gains.kw_nms, inertia)
    if gains.c2 is None:
        return 0.9 * bound
    if gains.c2 >= bound and gains.c2 > 0:
        raise ValueError(f"c2 = {gains.c2:g} must be below {bound:.4g} for k_R = {gains.kR_nm:g}, "
                         f"k_w = {gains.kw_nms:g} and this link's inertia (ref. [31], se3_control docstring)")
    return gains.c2


def attitude_error_so3(R: np.ndarray, R_d: np.ndarray) -> np.ndarray:
    """``e_R = 1/2 (R_d^T R - R^T R_d)^v`` (sec. 2.3.2, [31]): ``~ dtheta`` (body) for small errors."""
    E = R_d.T @ R
    return 0.5 * vee(E - E.T)


def _clamp(v: np.ndarray, limit: float) -> np.ndarray:
    return np.clip(v, -limit, limit)


def se3_pid_control(
    p_w_m: np.ndarray,
    v_w_m_s: np.ndarray,
    q_wxyz: np.ndarray,
    omega_b_rad_s: np.ndarray,
    target: PoseTarget,
    gains: Se3PidGains,
    inertia: LinkInertia,
    integrals: Se3PidIntegrals,
    dt_s: float,
    c2: float | None = None,
) -> tuple[np.ndarray, Se3PidIntegrals]:
    """Sec. 2.3.2: the body-frame wrench ``U = [R^T f; tau]`` and the updated integrals.

    ``c2``: the resolved ``c_2`` (:func:`resolved_c2`; computed here when ``None``).
    """
    if c2 is None:
        c2 = resolved_c2(gains, inertia)
    R = quat_to_rotmat(q_wxyz)
    R_d = target.R_d
    m = inertia.mass_kg
    J = np.asarray(inertia.inertia_kgm2, dtype=float)
    kp, kd, ki = (np.asarray(g, dtype=float) for g in (gains.kp_n_m, gains.kd_ns_m, gains.ki_n_ms))
    # Translation (world).
    e_p = np.array(limit_length((p_w_m - target.p_w_m).tolist(), gains.pos_error_limit_m))
    e_v = v_w_m_s - target.v_w_m_s
    pos_int = _clamp(integrals.pos_m_s + e_p * dt_s, gains.pos_integral_limit_ms)
    f_w = m * target.a_w_m_s2 - kd * e_v - kp * e_p - ki * pos_int + m * GRAVITY_M_S2 * E3 + target.force_ff_w_n
    # Rotation (body).
    RtRd = R.T @ R_d
    e_R = attitude_error_so3(R, R_d)
    w_d = RtRd @ target.omega_d_rad_s
    wdot_d = RtRd @ target.omega_dot_d_rad_s2
    e_w = omega_b_rad_s - w_d
    att_int = _clamp(integrals.att_rad + (e_w + c2 * e_R) * dt_s, gains.att_integral_limit_rad)
    tau = (J * wdot_d + np.cross(w_d, J * w_d) - gains.kw_nms * e_w - gains.kR_nm * e_R
           - gains.kRI_nm_s * att_int + RtRd @ target.torque_ff_b_nm)
    return np.concatenate((R.T @ f_w, tau)), Se3PidIntegrals(pos_int, att_int)


class Se3PidController(Controller):
    """Sec. 2.3.2 with its integrator state (``c_2`` resolved once at construction)."""

    def __init__(self, gains: Se3PidGains, inertia: LinkInertia):
        self.gains = gains
        self.inertia = inertia
        self.c2 = resolved_c2(gains, inertia)
        self.integrals = Se3PidIntegrals()

    def reset(self) -> None:
        self.integrals = Se3PidIntegrals()

    def __call__(self, p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target: PoseTarget, dt_s: float) -> np.ndarray:
        U, self.integrals = se3_pid_control(p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target, self.gains,
                                            self.inertia, self.integrals, dt_s, self.c2)
        return U

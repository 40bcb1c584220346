"""Decentralised impedance controller of one link (paper eq. 1, thesis eq. 3.1).

Translation (body-frame force command)::

    u = R^T (m g e3 + m a_d - k_d (v - v_d) - k_p (p - p_d) - k_i int(p - p_d))

Rotation (body-frame torque command)::

    e_R = (R_d^T R - R^T R_d)^v,   e_w = w - R^T R_d w_d,   e_I = int(e_w + gamma_I e_R) dt
    tau = S(w) J w - k_R e_R - k_w e_w - k_I e_I - J (S(w) R^T R_d w_d - R^T R_d wdot_d)

Two readings of the printed equation, stated here because they matter:

* Eq. 1 prints ``+ k_d e_p' + k_p e_p`` with ``e_p := p - p_d``; that is positive feedback.
  The thesis's ODAR pose controller (sec. 2.3.2) has the stabilising signs used above, so
  eq. 1's signs are a typo. ``k_i`` (position integral, from sec. 2.3.2) defaults to 0,
  leaving eq. 1 exactly.
* Eq. 1's feed-forward term writes ``R_d w_d`` where the body-frame expression needs
  ``R^T R_d w_d`` (the desired rate mapped into the current body frame, as in ``e_w``); we
  use the latter (the geometric SO(3) controller the paper builds on).

``e_R`` is eq. 1's, without a 1/2 factor: for small errors ``e_R ~ 2 dtheta``.

Pure functions of numpy arrays: no clocks (``dt`` is an argument), no state except the
integrals the caller passes in and gets back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from companion.estimation.so3 import quat_to_rotmat

__all__ = [
    "GRAVITY_M_S2",
    "ImpedanceGains",
    "LinkInertia",
    "PoseTarget",
    "ControlIntegrals",
    "vee",
    "impedance_control",
]

GRAVITY_M_S2 = 9.80665
_E3 = np.array([0.0, 0.0, 1.0])


def _triple(name: str, value) -> None:
    if len(value) != 3 or not all(math.isfinite(x) and x >= 0 for x in value):
        raise ValueError(f"{name} must be three finite non-negative numbers, got {value!r}")


@dataclass(frozen=True)
class ImpedanceGains:
    """Gains of eq. 1 (per world axis for translation, scalar for rotation).

    Defaults suit a 1 m, 1.8 kg LASDRA link: about 2.5 rad/s critically damped in
    translation, about 5 rad/s in pitch/yaw.
    """

    kp_n_m: tuple[float, float, float] = (11.0, 11.0, 11.0)
    kd_ns_m: tuple[float, float, float] = (9.0, 9.0, 9.0)
    ki_n_ms: tuple[float, float, float] = (0.0, 0.0, 0.0)
    kR_nm: float = 3.0
    kw_nms: float = 1.2
    kI_nm_s: float = 0.3
    gamma_I: float = 0.5
    pos_integral_limit_ms: float = 2.0
    att_integral_limit_rad: float = 1.0

    def __post_init__(self) -> None:
        for name in ("kp_n_m", "kd_ns_m", "ki_n_ms"):
            _triple(name, getattr(self, name))
        for name in ("kR_nm", "kw_nms", "kI_nm_s", "gamma_I", "pos_integral_limit_ms", "att_integral_limit_rad"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be a finite non-negative number, got {val!r}")

    @cached_property
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(kp, kd, ki) as arrays (computed once: the controller runs at 500 Hz)."""
        return np.array(self.kp_n_m), np.array(self.kd_ns_m), np.array(self.ki_n_ms)


@dataclass(frozen=True)
class LinkInertia:
    """Mass [kg] and principal inertia [kg m^2] of a link (body frame at the centre of mass)."""

    mass_kg: float
    inertia_kgm2: tuple[float, float, float]

    def __post_init__(self) -> None:
        if not self.mass_kg > 0:
            raise ValueError(f"mass_kg must be positive, got {self.mass_kg}")
        if len(self.inertia_kgm2) != 3 or not all(x > 0 for x in self.inertia_kgm2):
            raise ValueError(f"inertia_kgm2 must be three positive numbers, got {self.inertia_kgm2!r}")

    @cached_property
    def J(self) -> np.ndarray:
        return np.diag(self.inertia_kgm2)


@dataclass(frozen=True)
class PoseTarget:
    """Desired motion of a link (world frame z-up; body rates in the desired body frame).

    ``omega_d_rad_s`` and ``omega_dot_d_rad_s2`` are ``w_d`` and ``wdot_d`` of eq. 1:
    ``w_d = (R_d^T dR_d/dt)^v``.
    """

    p_w_m: np.ndarray
    q_wxyz: np.ndarray
    v_w_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    a_w_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega_d_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega_dot_d_rad_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def hold(cls, p_w_m, q_wxyz) -> PoseTarget:
        """Hold a pose: zero velocity, acceleration and rates."""
        return cls(np.array(p_w_m, dtype=float), np.array(q_wxyz, dtype=float))

    @cached_property
    def R_d(self) -> np.ndarray:
        """Desired rotation matrix (computed once per target)."""
        return quat_to_rotmat(self.q_wxyz)


@dataclass(frozen=True)
class ControlIntegrals:
    """Integrator states: position error [m s] and ``e_I`` of eq. 1 [rad]."""

    pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    att: np.ndarray = field(default_factory=lambda: np.zeros(3))


def vee(S: np.ndarray) -> np.ndarray:
    """Inverse of the skew map: ``vee(S(w)) = w``."""
    return np.array([S[2, 1], S[0, 2], S[1, 0]])


def _clamp(x: np.ndarray, limit: float) -> np.ndarray:
    """Symmetric clamp (anti-windup); ``np.clip`` costs several microseconds on 3-vectors."""
    if abs(x).max() <= limit:
        return x
    return np.minimum(np.maximum(x, -limit), limit)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3-vector cross product (``np.cross`` costs ~50 us per call on 3-vectors)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def impedance_control(
    p_w_m: np.ndarray,
    v_w_m_s: np.ndarray,
    q_wxyz: np.ndarray,
    omega_b_rad_s: np.ndarray,
    target: PoseTarget,
    gains: ImpedanceGains,
    inertia: LinkInertia,
    integrals: ControlIntegrals,
    dt_s: float,
) -> tuple[np.ndarray, ControlIntegrals]:
    """Eq. 1: the body-frame wrench command ``U = [u; tau]`` and the updated integrals."""
    R = quat_to_rotmat(q_wxyz)
    Rd = target.R_d
    m = inertia.mass_kg
    J = inertia.J
    kp, kd, ki = gains.arrays
    e_p = p_w_m - target.p_w_m
    pos_int = _clamp(integrals.pos + e_p * dt_s, gains.pos_integral_limit_ms)
    f_w = m * (target.a_w_m_s2 + GRAVITY_M_S2 * _E3) - kd * (v_w_m_s - target.v_w_m_s) - kp * e_p - ki * pos_int
    RtRd = R.T @ Rd
    E = RtRd.T - RtRd  # R_d^T R - R^T R_d
    e_R = np.array([E[2, 1], E[0, 2], E[1, 0]])
    w_d_body = RtRd @ target.omega_d_rad_s
    e_w = omega_b_rad_s - w_d_body
    att_int = _clamp(integrals.att + (e_w + gains.gamma_I * e_R) * dt_s, gains.att_integral_limit_rad)
    tau = (
        _cross(omega_b_rad_s, J @ omega_b_rad_s)
        - gains.kR_nm * e_R
        - gains.kw_nms * e_w
        - gains.kI_nm_s * att_int
        - J @ (_cross(omega_b_rad_s, w_d_body) - RtRd @ target.omega_dot_d_rad_s2)
    )
    return np.concatenate((R.T @ f_w, tau)), ControlIntegrals(pos_int, att_int)

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

The target's whole-chain feed-forward (``force_ff_w_n`` added to ``f_w``, ``torque_ff_b_nm``
mapped from the desired to the current body frame, ``R^T R_d tau_ff``, added to ``tau``) carries
what the cables and the joints' passive torques need of this link's rotors (thesis sec. 3.2's
Newton-Euler chain); it is zero unless the companion computes it.

Pure functions of numpy arrays: no clocks (``dt`` is an argument), no state except the
integrals the caller passes in and gets back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_finite_positive
from companion.estimation.so3 import rotmat_tuple
from companion.messages import PoseTarget
from companion.skeleton.body import GRAVITY_M_S2, LinkInertia

from . import _fast

__all__ = [
    "ImpedanceGains",
    "ControlIntegrals",
    "vee",
    "weight_wrench",
    "impedance_control",
    "impedance_control_compiled",
]


def _triple(name: str, value) -> None:
    if len(value) != 3 or not all(math.isfinite(x) and x >= 0 for x in value):
        raise ValueError(f"{name} must be three finite non-negative numbers, got {value!r}")


@dataclass(frozen=True)
class ImpedanceGains:
    """Gains of eq. 1 (per world axis for translation, scalar for rotation).

    Defaults suit a 1 m, 1.8 kg LASDRA link: about 2.5 rad/s critically damped in
    translation, about 5 rad/s in pitch/yaw.

    ``pos_error_limit_m`` (an addition to eq. 1, IMP_PERR_MAX): the position error ``p - p_d`` is
    taken at most this long (its direction kept), as ArduPilot's position controller limits its
    leash and PX4 its velocity setpoint. Eq. 1 itself has no limit: a target 30 m off asked for
    300 N and the link flew at it at 15 m/s and overshot by 13 m. With 2 m the stiffness term is
    at most 22 N and the link closes a far target at about ``k_p L / k_d`` = 2.4 m/s. Tracking
    errors in flight are centimetres to a few decimetres: the limit is not reached there.
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
    pos_error_limit_m: float = 2.0

    def __post_init__(self) -> None:
        for name in ("kp_n_m", "kd_ns_m", "ki_n_ms"):
            _triple(name, getattr(self, name))
        for name in ("kR_nm", "kw_nms", "kI_nm_s", "gamma_I", "pos_integral_limit_ms", "att_integral_limit_rad"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be a finite non-negative number, got {val!r}")
        require_finite_positive(self, "pos_error_limit_m")


@dataclass(frozen=True)
class ControlIntegrals:
    """Integrator states: position error [m s] and ``e_I`` of eq. 1 [rad]."""

    pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    att: np.ndarray = field(default_factory=lambda: np.zeros(3))


def limit_length(e, limit: float) -> tuple:
    """``e`` (3 floats) as a tuple, shortened to length ``limit`` if longer (the position error's
    limit of eq. 1 and of sec. 2.3.2's controller, ``pos_error_limit_m``)."""
    n = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    if n <= limit:
        return tuple(e)
    k = limit / n
    return (e[0] * k, e[1] * k, e[2] * k)


def weight_wrench(inertia: LinkInertia, q_wxyz: np.ndarray) -> np.ndarray:
    """Body-frame wrench ``U = [R^T m g e3; 0]`` that carries the link's weight at attitude ``q``
    (``R^T e3`` is R's third row; the firmware's step-by-step path calls this every tick)."""
    mg = inertia.mass_kg * GRAVITY_M_S2
    r3 = rotmat_tuple(np.asarray(q_wxyz, dtype=float).tolist())[6:]
    return np.array((r3[0] * mg, r3[1] * mg, r3[2] * mg, 0.0, 0.0, 0.0))


def vee(S: np.ndarray) -> np.ndarray:
    """Inverse of the skew map: ``vee(S(w)) = w``."""
    return np.array([S[2, 1], S[0, 2], S[1, 0]])


# Eq. 1 runs at 500 Hz per link on 3-vectors and 3x3 matrices, where numpy's per-call
# overhead (about a microsecond) dominates the arithmetic; it is evaluated on plain floats
# (row-major 3x3 tuples) and returns one array. tests/test_control.py checks it against a
# direct numpy evaluation of eq. 1.


def _mv(M, v) -> tuple:
    return (
        M[0] * v[0] + M[1] * v[1] + M[2] * v[2],
        M[3] * v[0] + M[4] * v[1] + M[5] * v[2],
        M[6] * v[0] + M[7] * v[1] + M[8] * v[2],
    )


def _mtv(M, v) -> tuple:
    """M^T v."""
    return (
        M[0] * v[0] + M[3] * v[1] + M[6] * v[2],
        M[1] * v[0] + M[4] * v[1] + M[7] * v[2],
        M[2] * v[0] + M[5] * v[1] + M[8] * v[2],
    )


def _mtm(A, B) -> tuple:
    """A^T B."""
    return tuple(
        A[i] * B[j] + A[3 + i] * B[3 + j] + A[6 + i] * B[6 + j] for i in range(3) for j in range(3)
    )


def _cross(a, b) -> tuple:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _clamp(values, limit: float) -> np.ndarray:
    """Symmetric clamp (anti-windup) of a 3-vector."""
    return np.array([min(max(c, -limit), limit) for c in values])


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
    p, v, w = p_w_m.tolist(), v_w_m_s.tolist(), omega_b_rad_s.tolist()
    pd, vd, ad = target.p_w_m.tolist(), target.v_w_m_s.tolist(), target.a_w_m_s2.tolist()
    wd, wdd = target.omega_d_rad_s.tolist(), target.omega_dot_d_rad_s2.tolist()
    R = rotmat_tuple(q_wxyz.tolist())
    Rd = target.R_tuple
    m = inertia.mass_kg
    Jx, Jy, Jz = inertia.inertia_kgm2
    kp, kd, ki = gains.kp_n_m, gains.kd_ns_m, gains.ki_n_ms
    # Translation: f_w = m g e3 + m a_d - k_d (v - v_d) - k_p (p - p_d) - k_i int(p - p_d) (+ f_ff).
    e_p = limit_length((p[0] - pd[0], p[1] - pd[1], p[2] - pd[2]), gains.pos_error_limit_m)
    pos = integrals.pos
    pos_int = _clamp([pos[i] + e_p[i] * dt_s for i in range(3)], gains.pos_integral_limit_ms)
    gz = GRAVITY_M_S2
    f_ff = target.force_ff_w_n.tolist()
    f_w = tuple(
        m * (ad[i] + (gz if i == 2 else 0.0)) - kd[i] * (v[i] - vd[i]) - kp[i] * e_p[i] - ki[i] * pos_int[i] + f_ff[i]
        for i in range(3)
    )
    u = _mtv(R, f_w)
    # Rotation.
    RtRd = _mtm(R, Rd)  # R^T R_d
    # e_R = (R_d^T R - R^T R_d)^v = vee(RtRd^T - RtRd)
    e_R = (RtRd[5] - RtRd[7], RtRd[6] - RtRd[2], RtRd[1] - RtRd[3])
    w_db = _mv(RtRd, wd)  # desired rate in the body frame
    e_w = (w[0] - w_db[0], w[1] - w_db[1], w[2] - w_db[2])
    gI = gains.gamma_I
    att = integrals.att
    att_int = _clamp([att[i] + (e_w[i] + gI * e_R[i]) * dt_s for i in range(3)], gains.att_integral_limit_rad)
    Jw = (Jx * w[0], Jy * w[1], Jz * w[2])
    gyro = _cross(w, Jw)
    wxwd = _cross(w, w_db)
    rd = _mv(RtRd, wdd)
    ff = (Jx * (wxwd[0] - rd[0]), Jy * (wxwd[1] - rd[1]), Jz * (wxwd[2] - rd[2]))
    tau_ff = _mv(RtRd, target.torque_ff_b_nm.tolist())  # whole-chain feed-forward, desired -> body frame
    kR, kw, kI = gains.kR_nm, gains.kw_nms, gains.kI_nm_s
    tau = [gyro[i] - kR * e_R[i] - kw * e_w[i] - kI * att_int[i] - ff[i] + tau_ff[i] for i in range(3)]
    return np.array((*u, *tau)), ControlIntegrals(pos_int, att_int)


def impedance_control_compiled(
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
    """:func:`impedance_control` (eq. 1) by the compiled kernel :func:`._fast.impedance_kernel`:
    the same arguments and numbers (to rounding). The target, gains and inertia are packed into
    arrays once per object (kept with it, as ``cached_property`` does)."""
    out = _fast.impedance_kernel(
        np.asarray(p_w_m, dtype=float), np.asarray(v_w_m_s, dtype=float), np.asarray(q_wxyz, dtype=float),
        np.asarray(omega_b_rad_s, dtype=float), _fast.packed(target, _fast.pack_target),
        _fast.packed(gains, _fast.pack_gains), _fast.packed(inertia, _fast.pack_inertia), integrals.pos,
        integrals.att, float(dt_s), GRAVITY_M_S2, np.empty(12))
    return out[:6], ControlIntegrals(out[6:9], out[9:12])

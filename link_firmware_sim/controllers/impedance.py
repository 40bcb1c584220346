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

:func:`impedance_control` is eq. 1 in readable numpy: the specification, which the firmware runs
without the compiled kernels, and which ``tests/unit/test_fast_paths.py`` compares the kernel
(:func:`link_firmware_sim.kernels.impedance.impedance_kernel`) with. A pure function (no clocks:
``dt`` is an argument; no state except the integrals the caller passes in and gets back).
:class:`ImpedanceController` is eq. 1 as the firmware's controller: its gains, the link's inertia and
its integrals in one array, with the one dispatch between the kernel and the specification.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_finite_positive
from companion.estimation.so3 import cross, quat_to_rotmat
from companion.kernels.jit import ENABLED
from companion.messages import PoseTarget
from companion.skeleton.body import GRAVITY_M_S2, LinkInertia

from ..kernels.impedance import impedance_kernel
from ..kernels.layouts import CTL_ATT_INT, CTL_POS_INT, CTL_SIZE, TGT_SIZE
from .base import Controller
from .common import E3, limit_length, require_gains, vee

__all__ = ["ImpedanceGains", "ControlIntegrals", "impedance_control", "pack_target", "pack_gains",
           "ImpedanceController"]

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
            require_gains(name, getattr(self, name), 3)
        for name in ("kR_nm", "kw_nms", "kI_nm_s", "gamma_I", "pos_integral_limit_ms", "att_integral_limit_rad"):
            require_gains(name, getattr(self, name))
        require_finite_positive(self, "pos_error_limit_m")


@dataclass(frozen=True)
class ControlIntegrals:
    """Integrator states: position error [m s] and ``e_I`` of eq. 1 [rad]."""

    pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    att: np.ndarray = field(default_factory=lambda: np.zeros(3))


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
    R, R_d = quat_to_rotmat(q_wxyz), quat_to_rotmat(target.q_wxyz)
    J = np.diag(inertia.inertia_kgm2)
    m = inertia.mass_kg
    w = np.asarray(omega_b_rad_s, dtype=float)
    # translation: f_w = m g e3 + m a_d - k_d (v - v_d) - k_p e_p - k_i int(e_p) + f_ff, e_p = p - p_d limited
    e_p = np.array(limit_length(np.asarray(p_w_m, dtype=float) - target.p_w_m, gains.pos_error_limit_m))
    pos_int = np.clip(integrals.pos + e_p * dt_s, -gains.pos_integral_limit_ms, gains.pos_integral_limit_ms)
    f_w = (m * GRAVITY_M_S2 * E3 + m * target.a_w_m_s2 - np.array(gains.kd_ns_m) * (v_w_m_s - target.v_w_m_s)
           - np.array(gains.kp_n_m) * e_p - np.array(gains.ki_n_ms) * pos_int + target.force_ff_w_n)
    # rotation: e_R = (R_d^T R - R^T R_d)^v, e_w = w - R^T R_d w_d, e_I = int(e_w + gamma_I e_R)
    RtRd = R.T @ R_d
    e_R = vee(RtRd.T - RtRd)
    w_d = RtRd @ target.omega_d_rad_s  # the desired rate in the body frame
    e_w = w - w_d
    att_int = np.clip(integrals.att + (e_w + gains.gamma_I * e_R) * dt_s, -gains.att_integral_limit_rad,
                      gains.att_integral_limit_rad)
    tau = (cross(w, J @ w) - gains.kR_nm * e_R - gains.kw_nms * e_w - gains.kI_nm_s * att_int
           - J @ (cross(w, w_d) - RtRd @ target.omega_dot_d_rad_s2)
           + RtRd @ target.torque_ff_b_nm)  # the whole-chain feed-forward, desired -> body frame
    return np.concatenate((R.T @ f_w, tau)), ControlIntegrals(pos_int, att_int)


def pack_target(target: PoseTarget) -> np.ndarray:
    """A :class:`~companion.messages.PoseTarget` as eq. 1's kernel reads it (``TGT_*``)."""
    return np.concatenate((target.p_w_m, target.v_w_m_s, target.a_w_m_s2, target.omega_d_rad_s,
                           target.omega_dot_d_rad_s2, target.R_tuple, target.force_ff_w_n,
                           target.torque_ff_b_nm)).astype(float)


def pack_gains(gains: ImpedanceGains, inertia: LinkInertia) -> np.ndarray:
    """The gains and the link's inertia as eq. 1's kernel reads them (``CTL_*`` up to the integrals):
    kp, kd, ki (3 each), kR, kw, kI, gamma_I, the position and attitude integrals' limits, the
    position error's limit; mass, principal inertia, gravity."""
    return np.array((*gains.kp_n_m, *gains.kd_ns_m, *gains.ki_n_ms, gains.kR_nm, gains.kw_nms, gains.kI_nm_s,
                     gains.gamma_I, gains.pos_integral_limit_ms, gains.att_integral_limit_rad,
                     gains.pos_error_limit_m, inertia.mass_kg, *inertia.inertia_kgm2, GRAVITY_M_S2), dtype=float)


class ImpedanceController(Controller):
    """Eq. 1 as the firmware's controller: by the kernel when ``compiled`` (default: when numba is
    installed and not turned off, :data:`~companion.kernels.jit.ENABLED`), else by the
    specification :func:`impedance_control`. Its gains, the link's inertia and its integrals are
    one array, :attr:`state` (``CTL_*`` of :mod:`link_firmware_sim.kernels.layouts`), which the
    firmware's fused tick reads and updates in place (:attr:`tick_state`)."""

    def __init__(self, gains: ImpedanceGains, inertia: LinkInertia, compiled: bool | None = None):
        self.compiled = ENABLED if compiled is None else bool(compiled)
        self.inertia = inertia
        self.state = np.zeros(CTL_SIZE)
        self.gains = gains
        self._target: PoseTarget | None = None
        self._target_packed = np.zeros(TGT_SIZE)

    @property
    def gains(self) -> ImpedanceGains:
        return self._gains

    @gains.setter
    def gains(self, gains: ImpedanceGains) -> None:
        """New gains (a parameter change): the integrals are kept."""
        self._gains = gains
        self.state[:CTL_POS_INT] = pack_gains(gains, self.inertia)

    @property
    def tick_state(self) -> np.ndarray | None:
        return self.state if self.compiled else None

    @property
    def integrals(self) -> ControlIntegrals:
        """A copy of the integrals (position [m s], ``e_I`` [rad])."""
        return ControlIntegrals(self.state[CTL_POS_INT:CTL_POS_INT + 3].copy(),
                                self.state[CTL_ATT_INT:CTL_ATT_INT + 3].copy())

    @integrals.setter
    def integrals(self, integrals: ControlIntegrals) -> None:
        self.state[CTL_POS_INT:CTL_POS_INT + 3] = integrals.pos
        self.state[CTL_ATT_INT:CTL_ATT_INT + 3] = integrals.att

    def reset(self) -> None:
        self.state[CTL_POS_INT:CTL_ATT_INT + 3] = 0.0

    def __call__(self, p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target: PoseTarget, dt_s: float) -> np.ndarray:
        if not self.compiled:
            U, self.integrals = impedance_control(p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target, self.gains,
                                                  self.inertia, self.integrals, dt_s)
            return U
        if target is not self._target:  # (targets change at 50 Hz, the controller runs at 500 Hz)
            self._target_packed[:] = pack_target(target)
            self._target = target
        U = np.empty(6)
        impedance_kernel(np.asarray(p_w_m, dtype=float), np.asarray(v_w_m_s, dtype=float),
                         np.asarray(q_wxyz, dtype=float), np.asarray(omega_b_rad_s, dtype=float), self._target_packed,
                         self.state, float(dt_s), U)
        return U

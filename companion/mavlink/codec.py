"""MAVLink codec of the typed messages (:mod:`companion.messages`) and the HIL sensor set.

Typed messages use the stack's frames (world ENU, body FLU, seconds); MAVLink messages use local
NED, body FRD and microseconds. Every conversion goes through :mod:`.frames`. Decoding validates:
non-finite numbers, a non-unit quaternion or a covariance that is not positive definite raise
:class:`MessageError` (the caller counts and drops the message).
"""

from __future__ import annotations

import math

import numpy as np

from companion.messages import (
    STATE_FLAG_ARMED,
    STATE_FLAG_CORRECTION_ACTIVE,
    STATE_FLAG_EKF_OK,
    ContactTarget,
    Correction,
    ExternalWrench,
    LinkState,
    MessageError,
    PoseTarget,
    check_bounded,
    check_finite,
    check_pd,
    check_unit_quat,
)

from .dialect import load_dialect
from .frames import enu_ned, error_cov_enu_ned, flu_frd, pack_upper, quat_enu_flu_to_ned_frd, quat_ned_frd_to_enu_flu, unpack_upper

__all__ = [
    "MessageError",
    "STATE_FLAG_EKF_OK",
    "STATE_FLAG_ARMED",
    "STATE_FLAG_CORRECTION_ACTIVE",
    "usec",
    "seconds",
    "encode_link_state",
    "decode_link_state",
    "encode_correction",
    "decode_correction",
    "encode_target_feedforward",
    "decode_target_feedforward",
    "encode_external_wrench",
    "decode_external_wrench",
    "CONTACT_RELEASE",
    "encode_contact_command",
    "decode_contact_command",
]

_D = load_dialect()
if (STATE_FLAG_EKF_OK, STATE_FLAG_ARMED, STATE_FLAG_CORRECTION_ACTIVE) != (
        _D.SKELETON_STATE_FLAGS_EKF_OK, _D.SKELETON_STATE_FLAGS_ARMED, _D.SKELETON_STATE_FLAGS_CORRECTION_ACTIVE):
    raise RuntimeError("companion.messages STATE_FLAG_* differ from the dialect's SKELETON_STATE_FLAGS")


def usec(t_s: float) -> int:
    return int(round(t_s * 1e6))


def seconds(t_us: int) -> float:
    return t_us * 1e-6


def encode_link_state(state: LinkState, flags: int = STATE_FLAG_EKF_OK, reset_counter: int = 0,
                      correction_seq: int = 0, correction_latency_us: int = 0):
    """SKELETON_LINK_STATE of a :class:`LinkState`."""
    return _D.MAVLink_skeleton_link_state_message(
        time_usec=usec(state.time_s),
        p_ned=enu_ned(state.p_w_m).tolist(),
        v_ned=enu_ned(state.v_w_m_s).tolist(),
        q=quat_enu_flu_to_ned_frd(state.q_wxyz).tolist(),
        rates_frd=flu_frd(state.omega_b_rad_s).tolist(),
        covariance=pack_upper(error_cov_enu_ned(state.P)),
        reset_counter=reset_counter & 0xFF,
        flags=flags,
        correction_seq=correction_seq & 0xFFFF,
        correction_latency_us=min(max(int(correction_latency_us), 0), 0xFFFFFFFF),
    )


def decode_link_state(msg, link: int) -> LinkState:
    """:class:`LinkState` of a SKELETON_LINK_STATE; :class:`MessageError` if unusable."""
    P = check_pd("covariance", error_cov_enu_ned(unpack_upper(check_finite("covariance", msg.covariance))))
    return LinkState(
        link=link,
        time_s=seconds(msg.time_usec),
        p_w_m=enu_ned(check_finite("p_ned", msg.p_ned)),
        v_w_m_s=enu_ned(check_finite("v_ned", msg.v_ned)),
        q_wxyz=quat_ned_frd_to_enu_flu(check_unit_quat("q", msg.q)),
        omega_b_rad_s=flu_frd(check_finite("rates_frd", msg.rates_frd)),
        P=P,
    )


def encode_correction(corr: Correction, target_system: int, target_component: int = 1, valid: bool = True):
    """SKELETON_CORRECTION of a :class:`Correction`."""
    return _D.MAVLink_skeleton_correction_message(
        target_system=target_system,
        target_component=target_component,
        ekf_time_usec=usec(corr.ekf_time_s),
        dp_ned=enu_ned(corr.dp_w_m).tolist(),
        dv_ned=enu_ned(corr.dv_w_m_s).tolist(),
        dtheta_ned=enu_ned(corr.dtheta_w_rad).tolist(),
        seq=corr.seq & 0xFFFF,
        valid=1 if valid else 0,
    )


def decode_correction(msg, link: int) -> Correction | None:
    """:class:`Correction` of a SKELETON_CORRECTION (``None`` for ``valid = 0``: withdraw)."""
    if not msg.valid:
        return None
    dtheta = check_finite("dtheta_ned", msg.dtheta_ned)
    if float(np.linalg.norm(dtheta)) > math.pi:
        raise MessageError(f"dtheta_ned: {np.linalg.norm(dtheta):.3g} rad is not a small-angle correction")
    return Correction(
        link=link,
        ekf_time_s=seconds(msg.ekf_time_usec),
        dp_w_m=enu_ned(check_finite("dp_ned", msg.dp_ned)),
        dv_w_m_s=enu_ned(check_finite("dv_ned", msg.dv_ned)),
        dtheta_w_rad=enu_ned(dtheta),
        seq=int(msg.seq),
    )


def encode_target_feedforward(target: PoseTarget, time_boot_ms: int, target_system: int, target_component: int = 1):
    """SKELETON_TARGET_FEEDFORWARD: ``target``'s angular acceleration and feed-forward wrench."""
    return _D.MAVLink_skeleton_target_feedforward_message(
        time_boot_ms=time_boot_ms & 0xFFFFFFFF, target_system=target_system, target_component=target_component,
        ang_accel_frd=flu_frd(target.omega_dot_d_rad_s2).tolist(), force_ned=enu_ned(target.force_ff_w_n).tolist(),
        torque_frd=flu_frd(target.torque_ff_b_nm).tolist())


#: Plausibility bounds of the decoders here (a corrupt or mis-scaled field, not a control limit:
#: the firmware's own bound on a commanded contact force is SKL_CT_FMAX)
WRENCH_FORCE_LIMIT_N = 1e4
WRENCH_TORQUE_LIMIT_NM = 1e4
ANG_ACCEL_LIMIT_RAD_S2 = 1e4
CONTACT_FORCE_LIMIT_N = 1e3
CONTACT_POINT_LIMIT_M = 10.0


def decode_target_feedforward(msg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(omega_dot_d FLU, force_ff world ENU, torque_ff FLU)`` of a SKELETON_TARGET_FEEDFORWARD;
    :class:`MessageError` on a non-finite value or one beyond its plausibility bound."""
    return (flu_frd(check_bounded("ang_accel_frd", msg.ang_accel_frd, ANG_ACCEL_LIMIT_RAD_S2)),
            enu_ned(check_bounded("force_ned", msg.force_ned, WRENCH_FORCE_LIMIT_N)),
            flu_frd(check_bounded("torque_frd", msg.torque_frd, WRENCH_TORQUE_LIMIT_NM)))


#: MAV_CMD_SKELETON_SET_CONTACT param1 that releases the contact (pose control only)
CONTACT_RELEASE = -1.0
_UNIT_TOL = 1e-3  # float32 on the wire: a normal within this of unit length is renormalised


def _contact_pair(force_n: float, setpoint_n: float) -> tuple[float, float]:
    """Both NaN (no contact) or both finite, the setpoint in [0, CONTACT_FORCE_LIMIT_N]."""
    force_n, setpoint_n = float(force_n), float(setpoint_n)
    if math.isnan(setpoint_n) and math.isnan(force_n):
        return force_n, setpoint_n
    if not (math.isfinite(force_n) and math.isfinite(setpoint_n)):
        raise MessageError("contact_force / contact_force_setpoint: both finite or both NaN (no contact)")
    if not 0.0 <= setpoint_n <= CONTACT_FORCE_LIMIT_N:
        raise MessageError(f"contact_force_setpoint: {setpoint_n:g} N outside [0, {CONTACT_FORCE_LIMIT_N:g}]")
    if abs(force_n) > CONTACT_FORCE_LIMIT_N:
        raise MessageError(f"contact_force: {force_n:g} N exceeds {CONTACT_FORCE_LIMIT_N:g}")
    return force_n, setpoint_n


def encode_external_wrench(wrench: ExternalWrench):
    """SKELETON_EXTERNAL_WRENCH of an :class:`ExternalWrench` (world ENU / body FLU inside, NED / FRD
    out); :class:`MessageError` on non-finite or implausible values (nothing is sent)."""
    f = check_bounded("force_w_n", wrench.force_w_n, WRENCH_FORCE_LIMIT_N)
    tau = check_bounded("torque_b_nm", wrench.torque_b_nm, WRENCH_TORQUE_LIMIT_NM)
    lam, lam_d = _contact_pair(wrench.contact_force_n, wrench.contact_force_cmd_n)
    return _D.MAVLink_skeleton_external_wrench_message(
        time_usec=usec(wrench.time_s), force_ned=enu_ned(f).tolist(), torque_frd=flu_frd(tau).tolist(),
        contact_force=lam, contact_force_setpoint=lam_d)


def decode_external_wrench(msg, link: int) -> ExternalWrench:
    """:class:`ExternalWrench` of a SKELETON_EXTERNAL_WRENCH; :class:`MessageError` if unusable."""
    lam, lam_d = _contact_pair(msg.contact_force, msg.contact_force_setpoint)
    return ExternalWrench(
        link=link, time_s=seconds(msg.time_usec),
        force_w_n=enu_ned(check_bounded("force_ned", msg.force_ned, WRENCH_FORCE_LIMIT_N)),
        torque_b_nm=flu_frd(check_bounded("torque_frd", msg.torque_frd, WRENCH_TORQUE_LIMIT_NM)),
        contact_force_n=lam, contact_force_cmd_n=lam_d)


def encode_contact_command(contact: ContactTarget | None, target_system: int, target_component: int = 1,
                           confirmation: int = 0):
    """COMMAND_LONG MAV_CMD_SKELETON_SET_CONTACT commanding ``contact`` (``None``: release it)."""
    if contact is None:
        params = [CONTACT_RELEASE] + [0.0] * 6
    else:
        params = [float(contact.force_n), *enu_ned(np.asarray(contact.normal_w, dtype=float)).tolist(),
                  *flu_frd(np.asarray(contact.contact_b_m, dtype=float)).tolist()]
    return _D.MAVLink_command_long_message(target_system, target_component, _D.MAV_CMD_SKELETON_SET_CONTACT,
                                           confirmation & 0xFF, *params)


def decode_contact_command(msg) -> ContactTarget | None:
    """The :class:`ContactTarget` of a COMMAND_LONG MAV_CMD_SKELETON_SET_CONTACT (``None``: release).

    :class:`MessageError` naming the parameter when the force is not -1 or in
    ``[0, CONTACT_FORCE_LIMIT_N]``, the normal is not a unit vector (within 1e-3; renormalised), or
    the contact point is not finite or farther than ``CONTACT_POINT_LIMIT_M`` from the centre."""
    if msg.get_type() != "COMMAND_LONG" or msg.command != _D.MAV_CMD_SKELETON_SET_CONTACT:
        raise MessageError(f"{msg.get_type()} is not a COMMAND_LONG MAV_CMD_SKELETON_SET_CONTACT")
    force = float(msg.param1)
    if force == CONTACT_RELEASE:
        return None
    if not (math.isfinite(force) and 0.0 <= force <= CONTACT_FORCE_LIMIT_N):
        raise MessageError(f"param1 (force): {force:g} N is neither -1 (release) nor in [0, {CONTACT_FORCE_LIMIT_N:g}]")
    n = check_finite("param2-4 (normal)", [msg.param2, msg.param3, msg.param4])
    norm = float(np.linalg.norm(n))
    if abs(norm - 1.0) > _UNIT_TOL:
        raise MessageError(f"param2-4 (normal): length {norm:.4g} is not 1")
    r = check_bounded("param5-7 (contact point)", [msg.param5, msg.param6, msg.param7], CONTACT_POINT_LIMIT_M)
    return ContactTarget(enu_ned(n / norm), flu_frd(r), force)

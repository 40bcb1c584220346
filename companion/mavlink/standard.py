"""Codec of the standard (common.xml) messages the stack exchanges, in one place, both ways.

* ``ODOMETRY``: a link's EKF output with covariance (what a stock PX4 publishes; the companion
  reads it in ``standard`` mode) and the companion's corrected pose as external vision (what
  PX4's EKF2 fuses with ``EKF2_EV_CTRL``). Frame ``MAV_FRAME_LOCAL_NED`` (the values are
  north-east-down in the shared local frame), child frame ``MAV_FRAME_BODY_FRD`` (velocity and
  rates in the body frame); ``pose_covariance`` is x, y, z, roll, pitch, yaw (21 floats, row-major
  upper triangle), ``velocity_covariance`` vx, vy, vz, rates.
* ``VISION_POSITION_ESTIMATE``: the external-vision pose in its older form (local NED position,
  roll/pitch/yaw of body FRD in NED).
* ``SET_POSITION_TARGET_LOCAL_NED`` and ``SET_ATTITUDE_TARGET``: a link's pose target
  (:class:`~companion.messages.PoseTarget`).

Inside the stack the frames are world ENU and body FLU (:mod:`.frames` converts). Decoders
validate and raise :class:`~companion.messages.MessageError` naming the field; the caller counts
and drops the message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.estimation.chain import ERR_P, ERR_TH, ERR_V
from companion.estimation.so3 import quat_from_euler_zyx, quat_to_rotmat
from companion.messages import LinkState, MessageError, PoseTarget, check_bounded, check_finite, check_pd, check_unit_quat

from .dialect import load_dialect
from .frames import enu_ned, error_cov_enu_ned, flu_frd, quat_enu_flu_to_ned_frd, quat_ned_frd_to_enu_flu

__all__ = [
    "UPPER_6",
    "POSE_ROWS",
    "ExternalPose",
    "encode_odometry",
    "decode_odometry",
    "decode_external_pose",
    "encode_vision_position_estimate",
    "euler_zyx",
    "heading_ned",
    "encode_position_target",
    "decode_position_target_yaw",
    "decode_position_target",
    "encode_attitude_target",
    "decode_attitude_target",
    "POSITION_TARGET_MASK",
]

_D = load_dialect()
#: Row-major upper triangle of a 6x6 matrix: the order of ODOMETRY's 21 covariance floats.
UPPER_6 = np.triu_indices(6)
#: Rows of the 9x9 ``[dp; dv; dtheta]`` covariance that form ODOMETRY's pose (x, y, z, attitude).
POSE_ROWS = np.r_[ERR_P, ERR_TH]
#: Variance sent for the body rates (the EKF does not estimate them as states) [rad^2/s^2].
RATE_VARIANCE = 1e-4
#: SET_POSITION_TARGET_LOCAL_NED type_mask: position, velocity and acceleration used; yaw and
#: yaw rate ignored (the attitude comes with SET_ATTITUDE_TARGET).
POSITION_TARGET_MASK = 0b0000_1100_0000_0000
#: ... and with yaw and yaw rate used: the whole target a stock PX4 takes (standard mode)
POSITION_YAW_TARGET_MASK = 0
_MASK_YAW = 0b0100_0000_0000
_MASK_YAW_RATE = 0b1000_0000_0000
_MASK_VEL = 0b0000_0011_1000
_MASK_ACC = 0b0001_1100_0000
_MASK_RATES = 0b0000_0111
_MASK_ATTITUDE = 0b1000_0000
#: Plausibility bounds of a decoded target, each a vector's norm (a corrupt or mis-scaled field,
#: not a control limit): position from the local origin, velocity, acceleration, body rates
TARGET_POSITION_LIMIT_M = 1e5
TARGET_VELOCITY_LIMIT_M_S = 1e3
TARGET_ACCEL_LIMIT_M_S2 = 1e3
TARGET_RATE_LIMIT_RAD_S = 1e3


def _upper6(M: np.ndarray) -> list[float]:
    return np.asarray(M, dtype=float)[UPPER_6].tolist()


#: ODOMETRY's covariance triangles: where each diagonal element is (row-major upper triangle)
DIAG_6 = np.flatnonzero(UPPER_6[0] == UPPER_6[1])


def _full6(values, name: str, needed: int = 6) -> np.ndarray:
    """The 6x6 covariance of an ODOMETRY triangle. Unknown (MessageError): a NaN first element
    (MAVLink's rule), or one of the first ``needed`` variances not finite. A NaN elsewhere is a
    term the sender does not estimate, taken as zero: PX4 fills the diagonal only, NaN off it and
    for the body rates' variances."""
    a = np.asarray(values, dtype=float)
    if not (np.isfinite(a[DIAG_6[:needed]]).all() and not np.isinf(a).any()):
        raise MessageError(f"{name}: covariance unknown (NaN)")
    M = np.zeros((6, 6))
    M[UPPER_6] = np.where(np.isnan(a), 0.0, a)
    return M + np.triu(M, 1).T


def encode_odometry(state: LinkState, time_usec: int, *, estimator_type: int, rates_known: bool = True,
                    px4: bool = False):
    """ODOMETRY of a :class:`LinkState` (world ENU / body FLU inside, LOCAL_NED / BODY_FRD out).

    The attitude block of the 9x9 covariance is the world-frame small-angle error covariance,
    sent as the roll/pitch/yaw covariance (exact for small errors near level). ``rates_known =
    False`` sends NaN body rates (external vision has none). ``px4``: as PX4's EKF2 publishes it
    (its ODOMETRY stream): the velocity in LOCAL_NED (``child_frame_id``), the variances only, NaN
    off the diagonal and for the body rates."""
    P = error_cov_enu_ned(state.P)
    q = quat_enu_flu_to_ned_frd(state.q_wxyz)
    R = quat_to_rotmat(q)
    rates = flu_frd(state.omega_b_rad_s).tolist() if rates_known else [math.nan] * 3
    pose_cov = _upper6(P[np.ix_(POSE_ROWS, POSE_ROWS)])
    if px4:
        velocity, child = enu_ned(state.v_w_m_s), _D.MAV_FRAME_LOCAL_NED
        diag = np.full(21, math.nan)
        pose_cov, vel_cov = diag.copy(), diag.copy()
        pose_cov[DIAG_6] = np.diag(P[np.ix_(POSE_ROWS, POSE_ROWS)])
        vel_cov[DIAG_6[:3]] = np.diag(P[ERR_V, ERR_V])
        pose_cov, vel_cov = pose_cov.tolist(), vel_cov.tolist()
    else:
        velocity, child = R.T @ enu_ned(state.v_w_m_s), _D.MAV_FRAME_BODY_FRD
        vel = np.zeros((6, 6))
        vel[:3, :3] = R.T @ P[ERR_V, ERR_V] @ R
        vel[3:, 3:] = np.eye(3) * RATE_VARIANCE
        vel_cov = _upper6(vel)
    return _D.MAVLink_odometry_message(
        time_usec, _D.MAV_FRAME_LOCAL_NED, child, *enu_ned(state.p_w_m).tolist(), q.tolist(),
        *velocity.tolist(), *rates, pose_cov, vel_cov, 0, estimator_type, 100,
    )


@dataclass(frozen=True)
class ExternalPose:
    """The pose of an external-vision message (world ENU, body FLU); ``v_w_m_s`` is ``None`` when
    the message carries no velocity (VISION_POSITION_ESTIMATE)."""

    time_s: float
    p_w_m: np.ndarray
    v_w_m_s: np.ndarray | None
    q_wxyz: np.ndarray


def _odometry_kinematics(msg) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(p, v, q, omega)`` in ENU / FLU, validated (frame ids, finite values, unit quaternion).
    The velocity comes in the body frame (``child_frame_id`` MAV_FRAME_BODY_FRD) or in the local
    one (MAV_FRAME_LOCAL_NED: PX4's EKF2 output)."""
    if msg.frame_id != _D.MAV_FRAME_LOCAL_NED:
        raise MessageError(f"ODOMETRY.frame_id: {msg.frame_id} (expected MAV_FRAME_LOCAL_NED, {_D.MAV_FRAME_LOCAL_NED})")
    if msg.child_frame_id not in (_D.MAV_FRAME_BODY_FRD, _D.MAV_FRAME_LOCAL_NED):
        raise MessageError(f"ODOMETRY.child_frame_id: {msg.child_frame_id} (expected MAV_FRAME_BODY_FRD, "
                           f"{_D.MAV_FRAME_BODY_FRD}, or MAV_FRAME_LOCAL_NED, {_D.MAV_FRAME_LOCAL_NED})")
    p = check_finite("ODOMETRY.x/y/z", (msg.x, msg.y, msg.z))
    v = check_finite("ODOMETRY.vx/vy/vz", (msg.vx, msg.vy, msg.vz))
    q = check_unit_quat("ODOMETRY.q", msg.q)
    rates = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
    if msg.child_frame_id == _D.MAV_FRAME_BODY_FRD:
        v = quat_to_rotmat(q) @ v
    return enu_ned(p), enu_ned(v), quat_ned_frd_to_enu_flu(q), flu_frd(rates)


def decode_odometry(msg, link: int) -> LinkState:
    """A stock autopilot's ODOMETRY as a :class:`LinkState` of 0-based ``link``.

    The 9x9 covariance is assembled from the pose covariance (position and attitude) and the
    velocity covariance (rotated to the local frame when it is the body frame's); ODOMETRY does
    not carry the position-velocity cross terms, so they are zero, and a term the sender leaves
    NaN (PX4: everything off the diagonal, the rates' variances) is zero too."""
    p, v, q, w = _odometry_kinematics(msg)
    if not np.isfinite(w).all():
        raise MessageError("ODOMETRY.rollspeed/pitchspeed/yawspeed: non-finite value")
    pose = _full6(msg.pose_covariance, "ODOMETRY.pose_covariance")
    vel = _full6(msg.velocity_covariance, "ODOMETRY.velocity_covariance", needed=3)
    P = np.zeros((9, 9))
    P[np.ix_(POSE_ROWS, POSE_ROWS)] = pose
    if msg.child_frame_id == _D.MAV_FRAME_BODY_FRD:
        R = quat_to_rotmat(quat_enu_flu_to_ned_frd(q))
        P[ERR_V, ERR_V] = R @ vel[:3, :3] @ R.T
    else:
        P[ERR_V, ERR_V] = vel[:3, :3]
    P = check_pd("ODOMETRY covariance", error_cov_enu_ned(P))
    return LinkState(link, msg.time_usec * 1e-6, p, v, q, w, P)


def decode_external_pose(msg) -> ExternalPose:
    """The pose of an external-vision ODOMETRY or VISION_POSITION_ESTIMATE (no covariance needed;
    VISION_POSITION_ESTIMATE has no velocity: ``v`` is ``None``); :class:`MessageError` on a
    non-finite value, a non-unit quaternion or an angle beyond 2 pi."""
    if msg.get_type() == "ODOMETRY":
        p, v, q, _ = _odometry_kinematics(msg)
        return ExternalPose(msg.time_usec * 1e-6, p, v, q)
    if msg.get_type() == "VISION_POSITION_ESTIMATE":
        p = check_finite("VISION_POSITION_ESTIMATE.x/y/z", (msg.x, msg.y, msg.z))
        rpy = check_finite("VISION_POSITION_ESTIMATE.roll/pitch/yaw", (msg.roll, msg.pitch, msg.yaw))
        if np.any(np.abs(rpy) > 2.0 * math.pi):
            raise MessageError(f"VISION_POSITION_ESTIMATE.roll/pitch/yaw: {rpy.tolist()} beyond 2 pi")
        q_ned = quat_from_euler_zyx(rpy[2], rpy[1], rpy[0])
        return ExternalPose(msg.usec * 1e-6, enu_ned(p), None, quat_ned_frd_to_enu_flu(q_ned))
    raise MessageError(f"{msg.get_type()}: not an external-vision message")


def euler_zyx(q_wxyz) -> tuple[float, float, float]:
    """``(roll, pitch, yaw)`` of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (MAVLink's Euler angles when
    ``q`` is a body-FRD-to-NED quaternion)."""
    R = quat_to_rotmat(np.asarray(q_wxyz, dtype=float))
    return (math.atan2(R[2, 1], R[2, 2]), -math.asin(max(-1.0, min(1.0, R[2, 0]))), math.atan2(R[1, 0], R[0, 0]))


def heading_ned(q_wxyz) -> float:
    """The NED heading [rad, clockwise from north] of an ENU-world / FLU-body attitude: the yaw of
    its body-FRD-to-NED quaternion."""
    return euler_zyx(quat_enu_flu_to_ned_frd(q_wxyz))[2]


def encode_vision_position_estimate(state: LinkState, time_usec: int):
    """VISION_POSITION_ESTIMATE of a corrected pose (its 9x9 covariance's pose block)."""
    q = quat_enu_flu_to_ned_frd(state.q_wxyz)
    P = error_cov_enu_ned(state.P)
    return _D.MAVLink_vision_position_estimate_message(time_usec, *enu_ned(state.p_w_m).tolist(), *euler_zyx(q),
                                                       _upper6(P[np.ix_(POSE_ROWS, POSE_ROWS)]), 0)


def encode_position_target(target: PoseTarget, time_boot_ms: int, target_system: int, target_component: int = 1,
                           yaw: bool = False):
    """SET_POSITION_TARGET_LOCAL_NED: position, velocity and acceleration of ``target``; with
    ``yaw``, its heading and heading rate too (NED yaw of the target attitude, and the rate about
    the down axis of its angular velocity): all a stock PX4 takes beside a position, since a
    SET_ATTITUDE_TARGET in offboard mode is an attitude setpoint with its own thrust."""
    yaw_ned = yaw_rate = 0.0
    if yaw:
        yaw_ned = heading_ned(target.q_wxyz)
        yaw_rate = -float((target.R_d @ np.asarray(target.omega_d_rad_s, dtype=float))[2])  # (ENU up -> NED down)
    return _D.MAVLink_set_position_target_local_ned_message(
        time_boot_ms & 0xFFFFFFFF, target_system, target_component, _D.MAV_FRAME_LOCAL_NED,
        POSITION_YAW_TARGET_MASK if yaw else POSITION_TARGET_MASK,
        *enu_ned(target.p_w_m).tolist(), *enu_ned(target.v_w_m_s).tolist(), *enu_ned(target.a_w_m_s2).tolist(),
        yaw_ned, yaw_rate)


def decode_position_target(msg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(p, v, a)`` ENU of a SET_POSITION_TARGET_LOCAL_NED (masked-out velocity or acceleration: 0);
    :class:`MessageError` on a non-finite value or one beyond its ``TARGET_*_LIMIT``, masked or not.
    Its heading: :func:`decode_position_target_yaw`."""
    if msg.coordinate_frame != _D.MAV_FRAME_LOCAL_NED:
        raise MessageError(f"SET_POSITION_TARGET_LOCAL_NED.coordinate_frame: {msg.coordinate_frame} (LOCAL_NED only)")
    name = "SET_POSITION_TARGET_LOCAL_NED"
    p = check_bounded(f"{name}.x/y/z", (msg.x, msg.y, msg.z), TARGET_POSITION_LIMIT_M)
    v = check_bounded(f"{name}.vx/vy/vz", (msg.vx, msg.vy, msg.vz), TARGET_VELOCITY_LIMIT_M_S)
    a = check_bounded(f"{name}.afx/afy/afz", (msg.afx, msg.afy, msg.afz), TARGET_ACCEL_LIMIT_M_S2)
    mask = msg.type_mask
    return (enu_ned(p), enu_ned(v) if not mask & _MASK_VEL else np.zeros(3),
            enu_ned(a) if not mask & _MASK_ACC else np.zeros(3))


def decode_position_target_yaw(msg) -> tuple[float, float] | None:
    """``(yaw, yaw rate)`` NED of a SET_POSITION_TARGET_LOCAL_NED whose yaw is not masked out (a
    masked yaw rate: 0), else ``None``; :class:`MessageError` on a non-finite one, or a rate beyond
    ``TARGET_RATE_LIMIT_RAD_S``."""
    if msg.type_mask & _MASK_YAW:
        return None
    yaw = float(check_finite("SET_POSITION_TARGET_LOCAL_NED.yaw", (msg.yaw,))[0])
    rate = float(check_bounded("SET_POSITION_TARGET_LOCAL_NED.yaw_rate", (msg.yaw_rate,), TARGET_RATE_LIMIT_RAD_S)[0])
    return yaw, 0.0 if msg.type_mask & _MASK_YAW_RATE else rate


def encode_attitude_target(target: PoseTarget, time_boot_ms: int, target_system: int, target_component: int = 1):
    """SET_ATTITUDE_TARGET: attitude and body rates (FRD) of ``target``; thrust unused."""
    rates = flu_frd(target.omega_d_rad_s).tolist()
    return _D.MAVLink_set_attitude_target_message(
        time_boot_ms=time_boot_ms & 0xFFFFFFFF, target_system=target_system, target_component=target_component,
        type_mask=0, q=quat_enu_flu_to_ned_frd(target.q_wxyz).tolist(), body_roll_rate=rates[0],
        body_pitch_rate=rates[1], body_yaw_rate=rates[2], thrust=0.0)


def decode_attitude_target(msg) -> tuple[np.ndarray, np.ndarray]:
    """``(q, omega)`` ENU/FLU of a SET_ATTITUDE_TARGET (rates masked out: 0); :class:`MessageError`
    on a non-finite or non-unit quaternion, or rates beyond ``TARGET_RATE_LIMIT_RAD_S``."""
    if msg.type_mask & _MASK_ATTITUDE:
        raise MessageError("SET_ATTITUDE_TARGET.type_mask: the attitude is masked out (rate-only targets are not "
                           "supported)")
    q = check_unit_quat("SET_ATTITUDE_TARGET.q", msg.q)
    rates = check_bounded("SET_ATTITUDE_TARGET body rates", (msg.body_roll_rate, msg.body_pitch_rate,
                                                              msg.body_yaw_rate), TARGET_RATE_LIMIT_RAD_S)
    if msg.type_mask & _MASK_RATES:
        rates = np.zeros(3)
    return quat_ned_frd_to_enu_flu(q), flu_frd(rates)

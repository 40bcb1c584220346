"""Per-link SE(3) error-state EKF of the simulated Pixhawk (paper eq. 2).

Nominal state ``x = [p; v; q; b_a; b_g]`` (16 numbers): world-frame position [m] and
velocity [m/s] of the link centre, body-to-world attitude (Hamilton, w first), accelerometer
bias [m/s^2] and gyro bias [rad/s] (body frame). Error state
``dx = [dp; dv; dtheta; db_a; db_g]`` (15 numbers) with the world-frame attitude error of
DESIGN.md sec. 4 (``q = dq(dtheta) (x) q_hat``), the convention of the SCKF (paper sec. III-A)
and of Sola, "Quaternion kinematics for the error-state Kalman filter" (2017), sec. 7
("global angular error"). The first 9 error states are the paper's ``[p~; v~; dtheta]``;
:func:`sckf_view` exposes them with their 9x9 covariance block.

World frame z-up, gravity ``[0, 0, -g]``; accelerometers measure specific force
``f = R^T (a - g)`` in the body frame.

This module is the functional core and the specification of the EKF's kernels
(:mod:`link_firmware_sim.kernels.ekf`): ``ekf_predict``, the measurement models (a
:class:`Measurement`: residual, Jacobian or error block, covariance) and the Kalman update
(``kalman_update``, ``kalman_update_block``), and ``ekf_update_*`` composing them: ``(x, P, ...) ->
(x, P[, info])``, no state, no clocks, readable numpy. The stateful filter on top, with the one
dispatch between this code and the kernels, is :class:`~.link_ekf.LinkEkf`. Covariance updates use
the Joseph form and keep ``P`` symmetric. The state layout and the tuning: :mod:`.ekf_config`.

Biases are estimated only if their process noise / initial variance is non-zero; with both
zero the filter reduces exactly to the paper's 9-state EKF.

Barometer: the first barometric height after start-up (or after a position reset) fixes the
barometer's offset to the EKF's height, as PX4's baro height reference does, but as a state: the
nominal state grows by the offset ``b`` (``X_BARO``), the error state by its error (``E_BARO``),
whose covariance row is that of the height error it was taken against (``b = h_baro - z``, so
``db = -dz - noise``). The barometer then measures ``z + b`` (:func:`ekf_update_baro`): it tells
the filter how the height changes, never where it is better than the GNSS height the offset was
taken against, and the covariance says so; ``b`` walks with the barometer's drift
(``EkfNoise.baro_bias_m2_s``). Without barometer samples the state stays at 16 / 15 numbers and
every operation is the one it was.

Magnetometer: :func:`ekf_update_mag_heading` fuses the heading of the measured field, rotated into
the world with the estimated attitude (tilt compensation), against the known declination, with
the Jacobian of that heading with respect to the attitude error (:func:`mag_heading_jacobian`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from companion.estimation.so3 import (attitude_error, quat_from_rotvec, quat_mul, quat_normalize, quat_to_rotmat,
                                      retract, skew)
from companion.skeleton.body import GRAVITY_W_M_S2

from .ekf_config import (E_BA, E_BARO, E_BG, E_P, E_PZ, E_SCKF, E_TH, E_V, NE, NE_BARO, NX, NX_BARO, X_BA, X_BARO,
                         X_BG, X_P, X_Q, X_V, EkfConfig, EkfNoise, UpdateInfo)

__all__ = ["GRAVITY_W_M_S2", "Measurement", "ekf_init", "ekf_predict", "error_transition", "inject_error",
           "innovation_test", "kalman_update", "kalman_update_block", "kalman_apply", "as_covariance",
           "attitude_variance", "position_measurement", "velocity_measurement", "attitude_measurement",
           "heading_measurement", "baro_measurement", "mag_heading_measurement", "ekf_update_position",
           "ekf_reset_position", "ekf_reset_velocity", "ekf_reset_attitude", "ekf_update_velocity",
           "ekf_update_attitude", "ekf_update_heading",
           "heading_jacobian", "ekf_add_baro_offset", "ekf_remove_baro_offset", "ekf_update_baro",
           "ekf_update_mag_heading", "mag_heading_jacobian", "sckf_view"]

_GRAVITY_W = np.array(GRAVITY_W_M_S2, dtype=float)


def ekf_init(p_w_m, v_w_m_s, q_wxyz, config: EkfConfig = EkfConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Initial state (zero biases) and diagonal covariance from ``config``."""
    x = np.zeros(NX)
    x[X_P] = p_w_m
    x[X_V] = v_w_m_s
    x[X_Q] = quat_normalize(np.asarray(q_wxyz, dtype=float))
    P = np.zeros((NE, NE))
    P[E_P, E_P] = config.init_pos_var_m2 * np.eye(3)
    P[E_V, E_V] = config.init_vel_var_m2_s2 * np.eye(3)
    P[E_TH, E_TH] = config.init_att_var_rad2 * np.eye(3)
    P[E_BA, E_BA] = config.init_accel_bias_var * np.eye(3)
    P[E_BG, E_BG] = config.init_gyro_bias_var * np.eye(3)
    return x, P


def error_transition(x, gyro_b_rad_s, accel_b_m_s2, dt_s: float) -> np.ndarray:
    """Error-state transition ``F`` (15x15) of :func:`ekf_predict`.

    World-frame attitude error (Sola 2017, sec. 7): ``dp' = dv``,
    ``dv' = -S(R f) dtheta - R db_a``, ``dtheta' = -R db_g``, biases constant; discretised
    like the nominal state (the position picks up the ``dt^2/2`` acceleration terms).
    """
    R = quat_to_rotmat(x[X_Q])
    S = skew(R @ (np.asarray(accel_b_m_s2, dtype=float) - x[X_BA]))  # S(f_w)
    h = 0.5 * dt_s * dt_s
    F = np.eye(NE)
    F[E_P, E_V] = dt_s * np.eye(3)
    F[E_P, E_TH] = -h * S
    F[E_P, E_BA] = -h * R
    F[E_V, E_TH] = -dt_s * S
    F[E_V, E_BA] = -dt_s * R
    F[E_TH, E_BG] = -dt_s * R
    return F


def ekf_predict(x, P, gyro_b_rad_s, accel_b_m_s2, dt_s: float, noise: EkfNoise) -> tuple[np.ndarray, np.ndarray]:
    """IMU propagation over ``dt_s`` (gyro rate and specific force in the body frame).

    Nominal: ``p += v dt + a dt^2/2``, ``v += a dt`` with ``a = R (f - b_a) + g``, and
    ``q <- q (x) Exp((w - b_g) dt)``; biases (and the barometer's offset) constant. Covariance
    ``F P F^T + Q dt`` with :func:`error_transition` (identity on the barometer's offset) and the
    process noise densities, symmetrised.
    """
    if not dt_s > 0.0:
        raise ValueError(f"dt_s must be positive, got {dt_s!r}")
    a = quat_to_rotmat(x[X_Q]) @ (np.asarray(accel_b_m_s2, dtype=float) - x[X_BA]) + _GRAVITY_W
    xn = np.array(x, dtype=float)
    xn[X_P] = x[X_P] + x[X_V] * dt_s + 0.5 * dt_s * dt_s * a
    xn[X_V] = x[X_V] + a * dt_s
    xn[X_Q] = quat_normalize(quat_mul(x[X_Q], quat_from_rotvec((np.asarray(gyro_b_rad_s, dtype=float) - x[X_BG]) * dt_s)))
    n = len(P)
    F = np.eye(n)
    F[:NE, :NE] = error_transition(x, gyro_b_rad_s, accel_b_m_s2, dt_s)
    Q = np.concatenate((noise.densities, [noise.baro_bias_m2_s] * (n - NE)))
    Pn = F @ P @ F.T + np.diag(Q * dt_s)
    return xn, 0.5 * (Pn + Pn.T)


def inject_error(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """Nominal state corrected by an error state ``dx`` (attitude on the left, world frame)."""
    xn = x.copy()
    xn[X_P] += dx[E_P]
    xn[X_V] += dx[E_V]
    xn[X_Q] = retract(x[X_Q], dx[E_TH])
    xn[X_BA] += dx[E_BA]
    xn[X_BG] += dx[E_BG]
    if len(dx) > NE:
        xn[NX:] += dx[NE:]
    return xn


def innovation_test(r: np.ndarray, S_diag: np.ndarray, gate_sigma: float) -> float:
    """PX4-style innovation test ratio: the largest ``r_k^2 / (gate^2 S_kk)``."""
    return float(np.max(r * r / (gate_sigma * gate_sigma * S_diag)))


def kalman_update(x, P, r, H, Rm, gate_sigma: float):
    """Gated Kalman update with residual ``r = z - h(x)``, Jacobian ``H`` (m x n) and the
    measurement's covariance ``Rm``, Joseph-form covariance: ``(x, P, UpdateInfo)`` (unchanged if
    the gate rejects it)."""
    PHt = P @ H.T
    S = H @ PHt + Rm
    test = innovation_test(r, np.diag(S), gate_sigma)
    if not math.isfinite(test) or test > 1.0:
        return x, P, UpdateInfo(False, r, test)
    K = np.linalg.solve(S, PHt.T).T
    IKH = np.eye(len(P)) - K @ H
    Pn = IKH @ P @ IKH.T + K @ Rm @ K.T
    return inject_error(x, K @ r), 0.5 * (Pn + Pn.T), UpdateInfo(True, r, test)


def kalman_update_block(x, P, r, block: slice, Rm, gate_sigma: float):
    """:func:`kalman_update` for ``H`` selecting the error-state ``block`` (GPS, attitude).

    Same Joseph form without forming ``H``: ``P H^T = P[:, b]``, ``S = P[b, b] + R``,
    ``A = (I - K H) P = P - K P[b, :]`` and ``A (I - K H)^T = A - A[:, b] K^T``.
    """
    PHt = P[:, block]
    S = PHt[block] + Rm
    test = innovation_test(r, np.diag(S), gate_sigma)
    if not math.isfinite(test) or test > 1.0:
        return x, P, UpdateInfo(False, r, test)
    K = np.linalg.solve(S, PHt.T).T
    A = P - K @ P[block]
    Pn = A - A[:, block] @ K.T + K @ Rm @ K.T
    return inject_error(x, K @ r), 0.5 * (Pn + Pn.T), UpdateInfo(True, r, test)


class Measurement(NamedTuple):
    """A measurement linearised at the state: residual ``r = z - h(x)`` (m,), covariance ``Rm``
    (m x m), and either the error-state ``block`` it measures (``H`` selects it) or its Jacobian
    ``H`` (m x n)."""

    r: np.ndarray
    Rm: np.ndarray
    block: slice | None = None
    H: np.ndarray | None = None


#: what an update that has nothing to measure reports (the heading of a vertical body axis or field)
NOT_MEASURED = UpdateInfo(False, np.array([0.0]), math.inf)


def kalman_apply(x, P, m: Measurement | None, gate_sigma: float):
    """``m`` fused by :func:`kalman_update_block` or :func:`kalman_update`; ``None``: nothing to
    measure (not accepted, the state unchanged)."""
    if m is None:
        return x, P, NOT_MEASURED
    if m.block is not None:
        return kalman_update_block(x, P, m.r, m.block, m.Rm, gate_sigma)
    return kalman_update(x, P, m.r, m.H, m.Rm, gate_sigma)


def attitude_variance(config: EkfConfig) -> float | np.ndarray:
    """The attitude reference's variance as :func:`ekf_update_attitude` takes it: the scalar
    ``att_var_rad2``, or per world axis ``[tilt, tilt, yaw]`` when the heading has its own."""
    if config.att_yaw_var_rad2 is None:
        return config.att_var_rad2
    return np.array([config.att_var_rad2, config.att_var_rad2, config.att_yaw_var_rad2])


def as_covariance(var, dim: int) -> np.ndarray:
    """Scalar, per-axis vector or full matrix variance as a (dim, dim) matrix."""
    a = np.asarray(var, dtype=float)
    if a.ndim == 0:
        return float(a) * np.eye(dim)
    if a.ndim == 1:
        return np.diag(a)
    return a


def _check_meas(z, name: str, size: int) -> np.ndarray:
    a = np.asarray(z, dtype=float)
    if a.shape != (size,) or not np.isfinite(a).all():
        raise ValueError(f"{name}: expected {size} finite numbers, got {a!r}")
    return a


def position_measurement(x, pos_w_m, var_m2) -> Measurement:
    """A GPS position (world frame, metres)."""
    z = _check_meas(pos_w_m, "position", 3)
    return Measurement(z - x[X_P], as_covariance(var_m2, 3), E_P)


def velocity_measurement(x, vel_w_m_s, var_m2_s2) -> Measurement:
    """A GPS velocity (world frame, m/s)."""
    z = _check_meas(vel_w_m_s, "velocity", 3)
    return Measurement(z - x[X_V], as_covariance(var_m2_s2, 3), E_V)


def attitude_measurement(x, q_meas_wxyz, var_rad2) -> Measurement:
    """An attitude reference (AHRS-like quaternion, normalised): the residual is the world-frame
    rotation vector from the estimate to the measurement, so ``H = [0 0 I 0 0]``; ``var_rad2`` is
    per axis."""
    z = quat_normalize(_check_meas(q_meas_wxyz, "attitude quaternion", 4))
    return Measurement(attitude_error(z, x[X_Q]), as_covariance(var_rad2, 3), E_TH)


def heading_jacobian(q_wxyz) -> np.ndarray:
    """``d yaw / d dtheta`` (1x3) for yaw = atan2(R10, R00) and world-frame errors.

    With ``R <- (I + S(dtheta)) R``: ``dR00 = -R10 dth_z + R20 dth_y`` and
    ``dR10 = R00 dth_z - R20 dth_x``, so
    ``d yaw = (-R20 R00 dth_x - R20 R10 dth_y + (R00^2 + R10^2) dth_z) / (R00^2 + R10^2)``.
    """
    R = quat_to_rotmat(q_wxyz)
    h = R[0, 0] ** 2 + R[1, 0] ** 2
    return np.array([-R[2, 0] * R[0, 0] / h, -R[2, 0] * R[1, 0] / h, 1.0])


def heading_measurement(x, yaw_rad: float, var_rad2: float) -> Measurement | None:
    """A heading (magnetometer-like): the yaw of the body x axis about world z; ``None`` (nothing
    to measure) while that axis is vertical."""
    if not math.isfinite(yaw_rad):
        raise ValueError(f"heading: expected a finite angle, got {yaw_rad!r}")
    R = quat_to_rotmat(x[X_Q])
    if R[0, 0] ** 2 + R[1, 0] ** 2 < 1e-6:
        return None  # heading undefined: skip rather than divide by zero
    yaw_hat = math.atan2(R[1, 0], R[0, 0])
    r = np.array([(yaw_rad - yaw_hat + math.pi) % (2.0 * math.pi) - math.pi])
    H = np.zeros((1, len(x) - 1))
    H[0, E_TH] = heading_jacobian(x[X_Q])
    return Measurement(r, np.array([[var_rad2]]), H=H)


def baro_measurement(x, baro_height_m: float, var_m2: float, deadzone_m: float = 0.0) -> Measurement:
    """A barometric height: ``h_baro = z + b`` (``b`` from :func:`ekf_add_baro_offset`).

    ``deadzone_m`` > 0 (in the rotors' ground effect, where the barometer reads low): an
    innovation between ``-deadzone_m`` and 0 becomes 0, a lower one ``deadzone_m`` less negative
    (PX4's EKF2_GND_EFF_DZ)."""
    if len(x) != NX_BARO:
        raise ValueError("the barometer is not referenced yet (ekf_add_baro_offset)")
    if not math.isfinite(baro_height_m):
        raise ValueError(f"barometric height: expected a finite number, got {baro_height_m!r}")
    r = baro_height_m - x[X_P][2] - x[X_BARO][0]
    if deadzone_m > 0.0 and r < 0.0:
        r = min(r + deadzone_m, 0.0)
    H = np.zeros((1, NE_BARO))
    H[0, E_PZ] = 1.0
    H[0, E_BARO] = 1.0
    return Measurement(np.array([r]), np.array([[var_m2]]), H=H)


def mag_heading_jacobian(q_wxyz, mag_b_gauss) -> np.ndarray:
    """``d phi / d dtheta`` (3,) of the horizontal direction ``phi = atan2(m_y, m_x)`` of the field
    ``m = R(q) m_b`` rotated into the world, for world-frame attitude errors.

    With ``R <- (I + S(dtheta)) R``: ``dm = dtheta x m``, so ``dm_x = dth_y m_z - dth_z m_y``,
    ``dm_y = dth_z m_x - dth_x m_z`` and ``d phi = (m_x dm_y - m_y dm_x) / (m_x^2 + m_y^2)
    = dth_z - (m_x m_z dth_x + m_y m_z dth_y) / (m_x^2 + m_y^2)``: a tilt error turns the
    measured heading through the field's inclination (:func:`heading_jacobian`'s form, with the
    field in place of the body x axis).
    """
    m = quat_to_rotmat(q_wxyz) @ np.asarray(mag_b_gauss, dtype=float)
    h = m[0] ** 2 + m[1] ** 2
    return np.array([-m[0] * m[2] / h, -m[1] * m[2] / h, 1.0])


def mag_heading_measurement(x, mag_b_gauss, declination_rad: float, var_rad2: float) -> Measurement | None:
    """A magnetometer sample's heading: the measured body-frame field (FLU, any unit), rotated
    into the world with the estimated attitude (tilt compensation), must point along the earth's
    horizontal field, ``declination_rad`` east of north (in ENU at ``pi/2 - declination`` from
    east). Residual: that angle minus the rotated field's, wrapped; Jacobian
    :func:`mag_heading_jacobian`; ``None`` (nothing to measure) when the field is nearly vertical."""
    mb = _check_meas(mag_b_gauss, "magnetic field", 3)
    m = quat_to_rotmat(x[X_Q]) @ mb
    h = m[0] ** 2 + m[1] ** 2
    if not h > 1e-4 * float(mb @ mb):  # within 0.6 deg of vertical (or no field): no heading
        return None
    phi_earth = 0.5 * math.pi - declination_rad
    r = np.array([(phi_earth - math.atan2(m[1], m[0]) + math.pi) % (2.0 * math.pi) - math.pi])
    H = np.zeros((1, len(x) - 1))
    H[0, E_TH] = (-m[0] * m[2] / h, -m[1] * m[2] / h, 1.0)
    return Measurement(r, np.array([[var_rad2]]), H=H)


def ekf_update_position(x, P, pos_w_m, var_m2, gate_sigma: float = 5.0):
    """GPS position update (world frame, metres)."""
    return kalman_apply(x, P, position_measurement(x, pos_w_m, var_m2), gate_sigma)


def ekf_update_velocity(x, P, vel_w_m_s, var_m2_s2, gate_sigma: float = 5.0):
    """GPS velocity update (world frame, m/s)."""
    return kalman_apply(x, P, velocity_measurement(x, vel_w_m_s, var_m2_s2), gate_sigma)


def ekf_update_attitude(x, P, q_meas_wxyz, var_rad2, gate_sigma: float = 5.0):
    """Attitude reference update from a measured quaternion (:func:`attitude_measurement`)."""
    return kalman_apply(x, P, attitude_measurement(x, q_meas_wxyz, var_rad2), gate_sigma)


def ekf_update_heading(x, P, yaw_rad: float, var_rad2: float, gate_sigma: float = 5.0):
    """Heading (magnetometer-like) update: yaw of the body x axis about world z."""
    return kalman_apply(x, P, heading_measurement(x, yaw_rad, var_rad2), gate_sigma)


def ekf_update_baro(x, P, baro_height_m: float, var_m2: float, gate_sigma: float = 5.0,
                    deadzone_m: float = 0.0):
    """Barometric height update (:func:`baro_measurement`)."""
    return kalman_apply(x, P, baro_measurement(x, baro_height_m, var_m2, deadzone_m), gate_sigma)


def ekf_update_mag_heading(x, P, mag_b_gauss, declination_rad: float, var_rad2: float,
                           gate_sigma: float = 5.0):
    """Magnetometer heading update (:func:`mag_heading_measurement`); skipped (not accepted) when
    the field is nearly vertical."""
    return kalman_apply(x, P, mag_heading_measurement(x, mag_b_gauss, declination_rad, var_rad2), gate_sigma)


def _reset_block(x, P, xs: slice, es: slice, value, var):
    """``x[xs] = value``; the error block ``es`` of ``P`` the variance ``var``, uncorrelated."""
    x = np.array(x, dtype=float)
    P = np.array(P, dtype=float)
    x[xs] = value
    P[es, :] = 0.0
    P[:, es] = 0.0
    P[es, es] = as_covariance(var, 3)
    return x, P


def ekf_reset_position(x, P, pos_w_m, var_m2):
    """Reset the position to a fix (a discontinuity, as EKF2's ``resetHorizontalPositionTo``):
    ``p = pos``, its covariance the fix's, its correlations with the rest of the state zero."""
    return _reset_block(x, P, X_P, E_P, np.asarray(pos_w_m, dtype=float), var_m2)


def ekf_reset_velocity(x, P, vel_w_m_s, var_m2_s2):
    """Reset the velocity to a GPS velocity (as EKF2's ``resetVelocityToGnss``): ``v = vel``, its
    covariance the fix's, its correlations with the rest of the state zero. ``ValueError`` for a
    velocity that is not 3 finite numbers."""
    v = np.asarray(vel_w_m_s, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"velocity reset: expected 3 finite numbers, got {vel_w_m_s!r}")
    return _reset_block(x, P, X_V, E_V, v, var_m2_s2)


def ekf_reset_attitude(x, P, q_wxyz, var_rad2):
    """Reset the attitude to a reference (a discontinuity, as EKF2's yaw reset): ``q = q_ref``
    (normalised), its error's covariance the reference's (``var_rad2``: scalar or per world
    axis, as :func:`attitude_variance` gives it), its correlations with the rest of the state
    zero. ``ValueError`` for a quaternion that is not 4 finite numbers of nonzero norm."""
    q = np.asarray(q_wxyz, dtype=float)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
        raise ValueError(f"attitude reset: expected a quaternion of 4 finite numbers, got {q_wxyz!r}")
    return _reset_block(x, P, X_Q, E_TH, quat_normalize(q), var_rad2)


def ekf_add_baro_offset(x, P, baro_height_m: float, var_m2: float):
    """Reference the barometer: append its offset ``b = h_baro - z`` to the state (PX4's baro height
    offset, taken against the current height estimate) with the covariance of that choice: the
    offset's error is minus the height's error (plus the sample's noise ``var_m2``), so the
    barometer adds no knowledge of the absolute height."""
    if len(x) != NX:
        raise ValueError("the barometer is already referenced")
    if not math.isfinite(baro_height_m):
        raise ValueError(f"barometric height: expected a finite number, got {baro_height_m!r}")
    xa = np.concatenate((x, [baro_height_m - x[X_P][2]]))
    Pa = np.zeros((NE_BARO, NE_BARO))
    Pa[:NE, :NE] = P
    row = -P[E_PZ, :]
    Pa[E_BARO, :NE] = row
    Pa[:NE, E_BARO] = row.T
    Pa[E_BARO, E_BARO] = P[E_PZ, E_PZ] + var_m2
    return xa, Pa


def ekf_remove_baro_offset(x, P):
    """The state without the barometer's offset (it is taken again at the next sample)."""
    return np.array(x[:NX], dtype=float), np.array(P[:NE, :NE], dtype=float)


def sckf_view(x, P, gyro_b_rad_s, gps_bias_var_m2=(0.0, 0.0)):
    """What the link reports to the companion: ``(p, v, q, omega_b, P9)``.

    ``omega_b`` is the bias-corrected body rate (input of eq. 3), ``P9`` the covariance of
    ``[p~; v~; dtheta]``, its position block plus the GNSS bias the filter does not estimate
    (``EkfConfig.gps_bias_var_m2``: horizontal, vertical).
    """
    omega = np.asarray(gyro_b_rad_s, dtype=float) - x[X_BG]
    P9 = P[E_SCKF, E_SCKF].copy()
    h, v = gps_bias_var_m2
    if h or v:
        P9[E_P, E_P] += np.diag((h, h, v))
    return x[X_P].copy(), x[X_V].copy(), x[X_Q].copy(), omega, P9

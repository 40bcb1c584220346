"""The simulator link of a simulated Pixhawk (PX4's simulator MAVLink API): HIL sensor messages in, actuators out.

Harness -> flight controller, each in MAVLink units and frames (body FRD, local NED, WGS84):

* ``HIL_SENSOR``: accelerometer (specific force) and gyro, plus magnetometer;
* ``HIL_GPS``: position as latitude/longitude/altitude and NED velocity;
* ``SKELETON_AHRS_REFERENCE`` (dialect): the attitude reference measurement.

Flight controller -> harness: ``HIL_ACTUATOR_CONTROLS`` with the rotor thrusts normalised by
the thrust limit (-1..1), echoing the ``time_usec`` of the ``HIL_SENSOR`` it answers (lockstep).

Geodetic positions use a local tangent plane at a shared :class:`GeoOrigin` on a spherical
earth (centimetre-exact over the few hundred metres of a flight); every link and the harness use
the same origin so that all local positions share one frame, as the constraints require.
"""

from __future__ import annotations

import math
import numpy as np

from companion.estimation.so3 import quat_to_rotmat
from companion.mavlink.codec import MessageError, seconds, usec
from companion.mavlink.dialect import load_dialect
from companion.mavlink.frames import enu_ned, flu_frd, quat_enu_flu_to_ned_frd, quat_ned_frd_to_enu_flu

from .geo import EARTH_RADIUS_M, GeoOrigin

__all__ = [
    "SITL_GPS_EPOCH_US",
    "sitl_gps_time_us",
    "EARTH_RADIUS_M",
    "GeoOrigin",
    "MAG_FIELD_NED_GAUSS",
    "ROTORS_PER_LINK",
    "encode_hil_sensor",
    "decode_hil_sensor",
    "encode_hil_gps",
    "decode_hil_gps",
    "encode_ahrs",
    "decode_ahrs",
    "encode_actuators",
    "decode_actuators",
]

_D = load_dialect()
#: GPS time at simulation time 0 (2026-01-01T00:00:00Z) [us since the Unix epoch]: the clock of the
#: simulated GPS receivers (SYSTEM_TIME of the simulated Pixhawks, the companion's ``gps`` time base).
SITL_GPS_EPOCH_US = 1_767_225_600_000_000
#: Earth magnetic field used for the simulated magnetometer (NED, gauss; mid-latitude).
MAG_FIELD_NED_GAUSS = np.array([0.21, 0.01, 0.42])
ROTORS_PER_LINK = 8
_HIL_SENSOR_ACCEL_GYRO_MAG = 0x1FF  # fields_updated bits 0..8
_GPS_FIX_3D = 3


def sitl_gps_time_us(sim_time_us: int) -> int:
    """GPS time [us since the Unix epoch] of the simulated receivers at simulation time ``sim_time_us``."""
    return SITL_GPS_EPOCH_US + int(sim_time_us)


def _check(name: str, values) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(a)):
        raise MessageError(f"{name}: non-finite value")
    return a


_MAG_FIELD_ENU = enu_ned(MAG_FIELD_NED_GAUSS)


def encode_hil_sensor(t_s: float, accel_flu_m_s2, gyro_flu_rad_s, q_enu_flu):
    """HIL_SENSOR from body-frame specific force and rate (and the attitude, for the magnetometer)."""
    ax, ay, az = np.asarray(accel_flu_m_s2, dtype=float).tolist()
    gx, gy, gz = np.asarray(gyro_flu_rad_s, dtype=float).tolist()
    mx, my, mz = (quat_to_rotmat(q_enu_flu).T @ _MAG_FIELD_ENU).tolist()  # body FLU
    return _D.MAVLink_hil_sensor_message(
        usec(t_s), ax, -ay, -az, gx, -gy, -gz, mx, -my, -mz,  # FLU -> FRD
        1013.25, 0.0, 0.0, 20.0, _HIL_SENSOR_ACCEL_GYRO_MAG, 0,
    )


def decode_hil_sensor(msg) -> tuple[float, np.ndarray, np.ndarray]:
    """``(t_s, gyro_flu, accel_flu)``."""
    acc = _check("HIL_SENSOR.acc", (msg.xacc, msg.yacc, msg.zacc))
    gyr = _check("HIL_SENSOR.gyro", (msg.xgyro, msg.ygyro, msg.zgyro))
    return seconds(msg.time_usec), flu_frd(gyr), flu_frd(acc)


def encode_hil_gps(t_s: float, p_enu_m, v_enu_m_s, origin: GeoOrigin):
    lat, lon, alt = origin.to_geodetic(p_enu_m)
    vn, ve, vd = enu_ned(v_enu_m_s).tolist()
    speed = math.hypot(vn, ve)
    cog = (math.degrees(math.atan2(ve, vn)) % 360.0) if speed > 0.05 else 0.0
    return _D.MAVLink_hil_gps_message(
        usec(t_s), _GPS_FIX_3D, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
        30, 50, int(round(speed * 100)), int(round(vn * 100)), int(round(ve * 100)), int(round(vd * 100)),
        int(round(cog * 100)), 12,
    )


def decode_hil_gps(msg, origin: GeoOrigin) -> tuple[float, np.ndarray, np.ndarray]:
    """``(t_s, p_enu, v_enu)``; :class:`MessageError` without a 3D fix."""
    if msg.fix_type < _GPS_FIX_3D:
        raise MessageError(f"HIL_GPS.fix_type: {msg.fix_type} (no 3D fix)")
    p = origin.to_enu(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
    v = enu_ned(np.array([msg.vn, msg.ve, msg.vd], dtype=float) * 0.01)
    return seconds(msg.time_usec), p, v


def encode_ahrs(t_s: float, q_enu_flu):
    return _D.MAVLink_skeleton_ahrs_reference_message(usec(t_s), quat_enu_flu_to_ned_frd(q_enu_flu).tolist())


def decode_ahrs(msg) -> tuple[float, np.ndarray]:
    q = _check("SKELETON_AHRS_REFERENCE.q", msg.q)
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-3:
        raise MessageError(f"SKELETON_AHRS_REFERENCE.q: norm {n:.6g} is not 1")
    return seconds(msg.time_usec), quat_ned_frd_to_enu_flu(q / n)


def encode_actuators(t_s: float, thrust_n, thrust_max_n: float, armed: bool):
    controls = [0.0] * 16
    controls[:ROTORS_PER_LINK] = (np.clip(np.asarray(thrust_n, dtype=float) / thrust_max_n, -1.0, 1.0)).tolist()
    mode = _D.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
    return _D.MAVLink_hil_actuator_controls_message(usec(t_s), controls, mode, 0)


def decode_actuators(msg, thrust_max_n: float) -> tuple[int, np.ndarray]:
    """``(time_usec, thrust (8,) [N])``; non-finite controls are rejected."""
    u = msg.controls[:ROTORS_PER_LINK]
    if not all(math.isfinite(x) for x in u):
        raise MessageError("HIL_ACTUATOR_CONTROLS.controls: non-finite value")
    return int(msg.time_usec), np.array([min(max(x, -1.0), 1.0) * thrust_max_n for x in u])

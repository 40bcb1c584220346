"""The simulator link of a simulated Pixhawk (PX4's simulator MAVLink API): HIL sensor messages in, actuators out.

Harness -> flight controller, each in MAVLink units and frames (body FRD, local NED, WGS84):

* ``HIL_SENSOR``: accelerometer (specific force) and gyro at every tick; magnetometer (gauss,
  body FRD) and barometer (``abs_pressure`` [hPa] of the standard atmosphere at the barometer's
  pressure altitude, that altitude as ``pressure_alt``, and a temperature) only in the ticks that
  carry a sample of a simulated one, with their ``fields_updated`` bits set then and only then;
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
from dataclasses import dataclass

import numpy as np

from companion.mavlink.codec import MessageError, seconds, usec
from companion.mavlink.dialect import load_dialect
from companion.mavlink.frames import enu_ned, flu_frd, quat_enu_flu_to_ned_frd, quat_ned_frd_to_enu_flu

from ..geo import EARTH_RADIUS_M, MAG_FIELD_NED_GAUSS, GeoOrigin, pressure_altitude_m, pressure_hpa_at

__all__ = [
    "SITL_GPS_EPOCH_US",
    "sitl_gps_time_us",
    "EARTH_RADIUS_M",
    "GeoOrigin",
    "MAG_FIELD_NED_GAUSS",
    "ROTORS_PER_LINK",
    "encode_hil_sensor",
    "encode_hil_sensors",
    "hil_sensor_values",
    "decode_hil_sensor",
    "HilBaroMag",
    "decode_hil_baro_mag",
    "HIL_SENSOR_IMU",
    "HIL_SENSOR_MAG",
    "HIL_SENSOR_BARO",
    "encode_hil_gps",
    "decode_hil_gps",
    "encode_ahrs",
    "decode_ahrs",
    "encode_actuators",
    "decode_actuators",
    "thrusts_from_controls",
    "nonfinite_rows",
]

_D = load_dialect()
#: GPS time at simulation time 0 (2026-01-01T00:00:00Z) [us since the Unix epoch]: the clock of the
#: simulated GPS receivers (SYSTEM_TIME of the simulated Pixhawks, the companion's ``gps`` time base).
SITL_GPS_EPOCH_US = 1_767_225_600_000_000
ROTORS_PER_LINK = 8
#: HIL_SENSOR ``fields_updated`` (HIL_SENSOR_UPDATED_FLAGS): accelerometer and gyro (bits 0-5),
#: magnetometer (6-8), barometer: abs_pressure (9), pressure_alt (11), temperature (12)
HIL_SENSOR_IMU = 0x3F
HIL_SENSOR_MAG = 0x1C0
HIL_SENSOR_BARO = (1 << 9) | (1 << 11) | (1 << 12)
_HIL_ABS_PRESSURE = 1 << 9
_HIL_PRESSURE_ALT = 1 << 11
#: what a decoded sample may be: a barometer's range (MS5611: 10-1200 mbar) and a magnetometer's
#: (the earth's field is under 0.7 G; a reading beyond 4 G is a saturated or broken sensor)
BARO_RANGE_HPA = (10.0, 1200.0)
MAG_MAX_GAUSS = 4.0
#: and an IMU's, per component: beyond a high-g accelerometer's 200 g or 100 rad/s (no MEMS gyro
#: measures 4000 deg/s) the sample is corrupt, not a reading
IMU_ACCEL_MAX_M_S2 = 2000.0
IMU_GYRO_MAX_RAD_S = 100.0
#: the latest simulation time a HIL message may carry [us] (35 years): the flight controller's
#: clock in float seconds keeps the microsecond up to it
HIL_TIME_MAX_US = 2**50
_BARO_TEMPERATURE_C = 20.0
_GPS_FIX_3D = 3


def sitl_gps_time_us(sim_time_us: int) -> int:
    """GPS time [us since the Unix epoch] of the simulated receivers at simulation time ``sim_time_us``."""
    return SITL_GPS_EPOCH_US + int(sim_time_us)


def _check(name: str, values, limit: float = math.inf) -> np.ndarray:
    """``values`` (a message's numbers) as a float array; :class:`MessageError` if one is not finite
    or, in magnitude, beyond ``limit``."""
    if not all(map(math.isfinite, values)):
        raise MessageError(f"{name}: non-finite value")
    if not all(abs(x) <= limit for x in values):
        raise MessageError(f"{name}: a component beyond {limit:g}")
    return np.array(values, dtype=float)


def _time_s(name: str, time_usec: int) -> float:
    """A HIL message's ``time_usec`` in seconds; :class:`MessageError` beyond :data:`HIL_TIME_MAX_US`."""
    if time_usec > HIL_TIME_MAX_US:
        raise MessageError(f"{name}.time_usec: {time_usec} is beyond {HIL_TIME_MAX_US}")
    return seconds(time_usec)


def encode_hil_sensor(t_s: float, accel_flu_m_s2, gyro_flu_rad_s, *, mag_flu_gauss=None,
                      baro_alt_m: float | None = None):
    """HIL_SENSOR from body-frame (FLU) specific force and rate, and, when a sample is due, the
    magnetometer's field (FLU, gauss) and the barometer's pressure altitude ``baro_alt_m`` [m above
    mean sea level], sent as its standard-atmosphere pressure [hPa] and as ``pressure_alt``."""
    return encode_hil_sensors(t_s, np.reshape(accel_flu_m_s2, (1, 3)), np.reshape(gyro_flu_rad_s, (1, 3)),
                              mag_flu_gauss=None if mag_flu_gauss is None else np.reshape(mag_flu_gauss, (1, 3)),
                              baro_alt_m=None if baro_alt_m is None else (baro_alt_m,))[0]


def hil_sensor_values(accel_flu_m_s2, gyro_flu_rad_s, *, mag_flu_gauss=None, baro_alt_m=None) -> tuple[np.ndarray, int]:
    """HIL_SENSOR's floats for ``n`` links, ``(n, 13)`` in the message's wire order (specific force,
    rate and field, body FRD; absolute and differential pressure [hPa], pressure altitude [m],
    temperature [C]), and its ``fields_updated`` bits, from ``(n, 3)`` arrays of specific force and
    rate (FLU), ``mag_flu_gauss`` ``(n, 3)`` and ``baro_alt_m`` ``(n,)`` or ``None``. The frames
    are converted once for the tick, not once per link."""
    acc = flu_frd(np.asarray(accel_flu_m_s2, dtype=float))
    values = np.zeros((len(acc), 13))
    values[:, 0:3] = acc
    values[:, 3:6] = flu_frd(np.asarray(gyro_flu_rad_s, dtype=float))
    bits = HIL_SENSOR_IMU
    if mag_flu_gauss is not None:
        values[:, 6:9] = flu_frd(np.asarray(mag_flu_gauss, dtype=float))
        bits |= HIL_SENSOR_MAG
    if baro_alt_m is not None:  # (pressure [hPa], pressure altitude [m], temperature [C])
        values[:, [9, 11, 12]] = [(pressure_hpa_at(alt), alt, _BARO_TEMPERATURE_C) for alt in map(float, baro_alt_m)]
        bits |= HIL_SENSOR_BARO
    return values, bits


def encode_hil_sensors(t_s: float, accel_flu_m_s2, gyro_flu_rad_s, *, mag_flu_gauss=None, baro_alt_m=None) -> list:
    """:func:`encode_hil_sensor` for ``n`` links at once (one HIL_SENSOR each), from
    :func:`hil_sensor_values`' arguments."""
    values, bits = hil_sensor_values(accel_flu_m_s2, gyro_flu_rad_s, mag_flu_gauss=mag_flu_gauss, baro_alt_m=baro_alt_m)
    usec_t = usec(t_s)
    new = _D.MAVLink_hil_sensor_message
    return [new(usec_t, *row, bits, 0) for row in values.tolist()]


def decode_hil_sensor(msg) -> tuple[float, np.ndarray, np.ndarray]:
    """``(t_s, gyro_flu, accel_flu)``; :class:`MessageError` for a time beyond
    :data:`HIL_TIME_MAX_US` or an IMU component that is not finite or beyond ``IMU_*_MAX``."""
    t = _time_s("HIL_SENSOR", msg.time_usec)
    acc = _check("HIL_SENSOR.acc", (msg.xacc, msg.yacc, msg.zacc), IMU_ACCEL_MAX_M_S2)
    gyr = _check("HIL_SENSOR.gyro", (msg.xgyro, msg.ygyro, msg.zgyro), IMU_GYRO_MAX_RAD_S)
    return t, flu_frd(gyr), flu_frd(acc)


@dataclass(frozen=True)
class HilBaroMag:
    """The barometer and magnetometer part of a HIL_SENSOR: ``baro_alt_m`` the pressure altitude
    [m above mean sea level], ``mag_flu_gauss`` the field (body FLU); ``None`` where the message
    carries no sample; ``rejected`` names the sensors whose sample was invalid (dropped)."""

    baro_alt_m: float | None
    mag_flu_gauss: np.ndarray | None
    rejected: tuple[str, ...] = ()


#: any of these bits marks a barometer or magnetometer sample
_BARO_MAG_BITS = HIL_SENSOR_MAG | _HIL_ABS_PRESSURE | _HIL_PRESSURE_ALT
_NO_BARO_MAG = HilBaroMag(None, None)


def decode_hil_baro_mag(msg) -> HilBaroMag:
    """The barometer and magnetometer samples of a HIL_SENSOR, by its ``fields_updated`` bits.

    The barometer's altitude comes from ``abs_pressure`` through the standard atmosphere (what a
    flight controller computes from its sensor), or from ``pressure_alt`` when only that is
    marked. A non-finite or out-of-range value (pressure outside 10-1200 hPa, a field component
    beyond 4 G) drops that sensor's sample and names it in ``rejected``; never raises."""
    bits = int(msg.fields_updated)
    if not bits & _BARO_MAG_BITS:  # an IMU-only tick (most of them)
        return _NO_BARO_MAG
    rejected = []
    baro = mag = None
    if bits & _HIL_ABS_PRESSURE:
        p = float(msg.abs_pressure)
        if math.isfinite(p) and BARO_RANGE_HPA[0] <= p <= BARO_RANGE_HPA[1]:
            baro = pressure_altitude_m(p)
        else:
            rejected.append("baro")
    elif bits & _HIL_PRESSURE_ALT:
        alt = float(msg.pressure_alt)
        if math.isfinite(alt) and pressure_altitude_m(BARO_RANGE_HPA[1]) <= alt <= pressure_altitude_m(BARO_RANGE_HPA[0]):
            baro = alt
        else:
            rejected.append("baro")
    if bits & HIL_SENSOR_MAG == HIL_SENSOR_MAG:
        m = np.array([msg.xmag, msg.ymag, msg.zmag], dtype=float)
        if np.isfinite(m).all() and np.all(np.abs(m) <= MAG_MAX_GAUSS):
            mag = flu_frd(m)
        else:
            rejected.append("mag")
    return HilBaroMag(baro, mag, tuple(rejected))


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
    return _time_s("HIL_GPS", msg.time_usec), p, v


def encode_ahrs(t_s: float, q_enu_flu):
    return _D.MAVLink_skeleton_ahrs_reference_message(usec(t_s), quat_enu_flu_to_ned_frd(q_enu_flu).tolist())


#: the largest departure from 1 of an attitude reference's norm :func:`decode_ahrs` takes
AHRS_NORM_TOLERANCE = 1e-3


def decode_ahrs(msg) -> tuple[float, np.ndarray]:
    """``(time [s], q body FLU to ENU)``; the quaternion normalised, its norm summed in order
    (``w, x, y, z``: the vehicle's record tick, :func:`~link_firmware_sim.kernels.tick.hil_tick_kernel`,
    gives the same numbers)."""
    q = _check("SKELETON_AHRS_REFERENCE.q", msg.q)
    w, x, y, z = q.tolist()
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if abs(n - 1.0) > AHRS_NORM_TOLERANCE:
        raise MessageError(f"SKELETON_AHRS_REFERENCE.q: norm {n:.6g} is not 1")
    return _time_s("SKELETON_AHRS_REFERENCE", msg.time_usec), quat_ned_frd_to_enu_flu(q / n)


def encode_actuators(t_s: float, thrust_n, thrust_max_n: float, armed: bool, time_usec: int | None = None):
    """HIL_ACTUATOR_CONTROLS of rotor thrusts [N] at ``t_s`` (``time_usec``: the time to echo as it
    came, for an answer to a sample whose time is refused)."""
    controls = [0.0] * 16
    # clipped to -1..1 (NaN stays NaN, as np.clip): plain floats, numpy's per-call cost at 500 Hz is not
    u = (np.asarray(thrust_n, dtype=float) / thrust_max_n).tolist()
    controls[:ROTORS_PER_LINK] = [min(max(x, -1.0), 1.0) for x in u]
    mode = _D.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
    return _D.MAVLink_hil_actuator_controls_message(usec(t_s) if time_usec is None else time_usec, controls, mode, 0)


def decode_actuators(msg, thrust_max_n: float) -> tuple[int, np.ndarray]:
    """``(time_usec, thrust (8,) [N])``; non-finite controls are rejected."""
    return int(msg.time_usec), thrusts_from_controls(np.array(msg.controls[:ROTORS_PER_LINK], dtype=float),
                                                     thrust_max_n)


def thrusts_from_controls(controls, thrust_max_n: float) -> np.ndarray:
    """Rotor thrusts [N] of HIL_ACTUATOR_CONTROLS ``controls`` (the first 8 of a message, or one row
    of them per link: ``(n, 8)``), each clipped to -1..1 and scaled by the thrust limit;
    :class:`MessageError` naming the rows (0-based) with a non-finite value. The harness decodes
    a whole tick's answers in one call."""
    controls = np.asarray(controls, dtype=float)
    if not np.isfinite(controls).all():
        raise MessageError(f"HIL_ACTUATOR_CONTROLS.controls: non-finite value (row(s) {nonfinite_rows(controls)})")
    return np.minimum(np.maximum(controls, -1.0), 1.0) * thrust_max_n


def nonfinite_rows(controls) -> list[int]:
    """The rows (0-based) of ``controls`` (8, or (n, 8)) holding a NaN or an infinity."""
    finite = np.isfinite(np.asarray(controls, dtype=float)).reshape(-1, ROTORS_PER_LINK)
    return np.flatnonzero(~finite.all(axis=1)).tolist()

"""The same-host simulator link's records as the compiled ticks read and write them.

A record is a 1-byte kind, then the MAVLink message's payload in wire order, little-endian
(:mod:`link_firmware_sim.vehicle.simlink`); :mod:`link_firmware_sim.vehicle.simlink` checks these offsets against
the dialect's layouts when it is imported.
"""

from __future__ import annotations

import math

import numpy as np

from companion.kernels.jit import jit
from companion.kernels.so3 import quat_mul

__all__ = ["HIL_SENSOR_RECORD", "HIL_ACTUATOR_RECORD", "HIL_AHRS_RECORD", "AHRS_NORM_TOLERANCE", "HIL_BARO_MAG_BITS",
           "IMU_ACCEL_MAX_M_S2", "IMU_GYRO_MAX_RAD_S",
           "sensor_record_at", "ahrs_record", "record_time_us", "sensor_records"]

#: the records as :func:`.tick.hil_tick_kernel` reads and writes them. They are literals in this
#: file, not derived from the dialect, on purpose: numba freezes a global into the machine code it
#: caches on disk, and its cache follows this file's changes only.
#: HIL_SENSOR: kind 0, ``time_usec`` (uint64), ``xacc..zacc`` then ``xgyro..zgyro`` (floats, body
#: FRD), then its other floats (``floats`` in all, from ``acc``), ``fields_updated`` (uint32), ``id`` (uint8)
HIL_SENSOR_RECORD = {"kind": 0, "size": 66, "time_usec": 1, "acc": 9, "gyro": 21, "fields_updated": 61, "id": 65,
                     "floats": 13}
#: HIL_ACTUATOR_CONTROLS: kind 3, ``time_usec`` and ``flags`` (uint64), ``controls`` (16 floats), ``mode`` (uint8)
HIL_ACTUATOR_RECORD = {"kind": 3, "size": 82, "time_usec": 1, "flags": 9, "controls": 17, "mode": 81}
# the same numbers as the kernel's compile-time constants
_SENSOR_KIND, _SENSOR_SIZE, _SENSOR_T, _SENSOR_ACC, _SENSOR_GYRO, _SENSOR_BITS, _SENSOR_ID, _SENSOR_FLOATS = (
    HIL_SENSOR_RECORD.values())
_ACT_KIND, _ACT_SIZE, _ACT_T, _ACT_FLAGS, _ACT_CONTROLS, _ACT_MODE = HIL_ACTUATOR_RECORD.values()
#: SKELETON_AHRS_REFERENCE: kind 2, ``time_usec`` (uint64), ``q`` (4 floats, body FRD to local NED)
HIL_AHRS_RECORD = {"kind": 2, "size": 25, "time_usec": 1, "q": 9}
_AHRS_KIND, _AHRS_SIZE, _AHRS_T, _AHRS_Q = HIL_AHRS_RECORD.values()
#: ``hil.decode_ahrs``'s tolerance on the reference quaternion's norm (a literal: ``tests/unit/test_fast_paths.py``
#: checks it is hil's)
AHRS_NORM_TOLERANCE = 1e-3
#: the HIL_SENSOR ``fields_updated`` bits of a magnetometer or barometer sample (``hil``:
#: HIL_SENSOR_MAG, abs_pressure, pressure_alt; a literal for the same reason, and
#: ``tests/unit/test_fast_paths.py`` checks it is hil's): such a tick takes the decoding path
HIL_BARO_MAG_BITS = 0x1C0 | (1 << 9) | (1 << 11)
#: ``hil.decode_hil_sensor``'s bounds on each component of an IMU sample, accelerometer [m/s^2] and
#: gyro [rad/s] (literals for the same reason; ``tests/unit/test_fast_paths.py`` checks they are hil's)
IMU_ACCEL_MAX_M_S2 = 2000.0
IMU_GYRO_MAX_RAD_S = 100.0


@jit
def sensor_record_at(rec, n):
    """Where the HIL_SENSOR record of a packet of ``n`` bytes the record tick takes starts: 0 for
    [HIL_SENSOR], :data:`HIL_AHRS_RECORD`'s size for [SKELETON_AHRS_REFERENCE, HIL_SENSOR] (the
    attitude reference's ticks); -1 for any other packet."""
    if n == _SENSOR_SIZE and rec[0] == _SENSOR_KIND:
        return 0
    if n == _AHRS_SIZE + _SENSOR_SIZE and rec[0] == _AHRS_KIND and rec[_AHRS_SIZE] == _SENSOR_KIND:
        return _AHRS_SIZE
    return -1


@jit
def ahrs_record(rec, frame):
    """``hil.decode_ahrs`` of the SKELETON_AHRS_REFERENCE record at the start of ``rec``, with the
    same numbers: its quaternion (body FRD to local NED) finite and of norm 1 within
    :data:`AHRS_NORM_TOLERANCE`, normalised and turned into body FLU to ENU
    (``frames.quat_ned_frd_to_enu_flu``: ``frame[:4] (x) q (x) frame[4:]``). Returns ``(ok, q)``:
    ``ok`` false (``q`` undefined) for a quaternion the decoder rejects."""
    qf = np.empty(4, np.float32)
    qf.view(np.uint8)[:] = rec[_AHRS_Q:_AHRS_Q + 16]
    m = np.empty(4)
    for i in range(4):
        if not math.isfinite(qf[i]):
            return False, (0.0, 0.0, 0.0, 0.0)
        m[i] = np.float64(qf[i])
    n = math.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3])
    if abs(n - 1.0) > AHRS_NORM_TOLERANCE:
        return False, (0.0, 0.0, 0.0, 0.0)
    for i in range(4):
        m[i] = m[i] / n
    e = quat_mul(frame[0], frame[1], frame[2], frame[3], m[0], m[1], m[2], m[3])
    return True, quat_mul(e[0], e[1], e[2], e[3], frame[4], frame[5], frame[6], frame[7])


@jit
def record_time_us(rec, at):
    """The ``time_usec`` (uint64) of the record at ``rec[at:]`` (HIL_SENSOR, SKELETON_AHRS_REFERENCE
    and HIL_ACTUATOR_CONTROLS have it at the same offset), copied byte-wise (it is not aligned)."""
    tb = np.empty(1, np.uint64)
    tb.view(np.uint8)[:] = rec[at + _SENSOR_T:at + _SENSOR_T + 8]
    return tb[0]


@jit
def sensor_records(t_us, values, bits, out):
    """The HIL_SENSOR records of ``n`` links into ``out`` (uint8, ``(n, size)``): time ``t_us``,
    ``values[i]`` (``(n, floats)``, the message's floats in wire order: ``hil.hil_sensor_values``)
    as float32, ``fields_updated`` ``bits``, ``id`` 0; the bytes ``simlink.encode_packet`` packs
    for the same message. Returns False (``out`` unfinished) when a finite value is too large for a
    float32, which pymavlink's packing refuses: the caller's path raises its error."""
    f = np.empty(_SENSOR_FLOATS, np.float32)
    head = np.empty(1, np.uint64)
    head[0] = t_us
    tail = np.empty(1, np.uint32)
    tail[0] = bits
    for i in range(values.shape[0]):
        for k in range(_SENSOR_FLOATS):
            f[k] = np.float32(values[i, k])
            if math.isfinite(values[i, k]) and not math.isfinite(f[k]):
                return False
        row = out[i]
        row[0] = _SENSOR_KIND
        row[_SENSOR_T:_SENSOR_T + 8] = head.view(np.uint8)
        row[_SENSOR_ACC:_SENSOR_ACC + 4 * _SENSOR_FLOATS] = f.view(np.uint8)
        row[_SENSOR_BITS:_SENSOR_BITS + 4] = tail.view(np.uint8)
        row[_SENSOR_ID] = 0
    return True

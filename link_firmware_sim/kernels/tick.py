"""The firmware's fast-loop tick in one kernel call: the EKF's propagation (and a queued attitude
reference), the control estimate, eq. 1 and the allocation; and the vehicle's common tick from the
simulator link's record to its answer's.

A call's dispatch and the Python between the steps cost more than their arithmetic at 500 Hz per
link, so the firmware runs its common case (armed, eq. 1, a fresh target) as one call, with the
operations of the kernels it fuses in their order; ``tests/unit/test_fast_paths.py`` checks it against
the step-by-step path, and the record tick byte for byte against the decoders'.

The state is grouped (:mod:`.layouts`): ``ekf_par`` the EKF's parameters (``EKF_*``), ``cmd`` the
firmware's inputs (``IN_*``: the correction's weight, the correction, the target), ``ctl`` eq. 1's
controller (``CTL_*``, its integrals updated), ``alloc`` the allocator's ``(B_pinv,
reduced_by_side, state)`` (``ALLOC_*``, ``xi''_pre`` updated), ``out`` the tick's results
(``OUT_*``) and, for the record tick, ``io`` the vehicle's side (``IO_*``).
"""

from __future__ import annotations

import math

import numpy as np

from companion.kernels.jit import jit
from companion.kernels.so3 import retract, rotmat_unit

from .allocation import ALLOC_META, allocate_kernel
from .ekf import attitude_update_kernel, ekf_predict_kernel
from .hil_records import (HIL_ACTUATOR_RECORD, HIL_BARO_MAG_BITS, HIL_SENSOR_RECORD, IMU_ACCEL_MAX_M_S2,
                          IMU_GYRO_MAX_RAD_S, ahrs_record, record_time_us, sensor_record_at)
from .impedance import impedance_kernel
from .layouts import (CTL_GRAVITY, CTL_MASS, IN_CORRECTION, IN_TARGET, IN_WEIGHT, IO_AHRS_ACCEPTED, IO_AHRS_Q,
                      IO_AHRS_REJECTED, IO_AHRS_T_US, IO_ACCEL, IO_FRAME, IO_GYRO, IO_MODE, IO_THRUST_MAX, OUT_COMMAND,
                      OUT_FINITE, OUT_FORCE_NORM, OUT_P_CTRL, OUT_SATURATED, OUT_SCALE, OUT_SIZE, OUT_U, TGT_SIZE)

__all__ = ["tick_kernel", "attitude_tick_kernel", "hil_tick_kernel"]

_SENSOR_T, _SENSOR_ACC, _SENSOR_BITS = HIL_SENSOR_RECORD["time_usec"], HIL_SENSOR_RECORD["acc"], HIL_SENSOR_RECORD[
    "fields_updated"]
_ACT_KIND, _ACT_SIZE, _ACT_T, _ACT_FLAGS, _ACT_CONTROLS, _ACT_MODE = HIL_ACTUATOR_RECORD.values()


@jit
def tick_kernel(x, P, predict, imu, dt_s, ekf_par, cmd, ctl, alloc, out):
    """One tick of the fast loop, ``imu = (gyro, accel)`` the body rate and specific force (3,
    each): if ``predict``, :func:`.ekf.ekf_predict_kernel` (paper eq. 2's propagation; else ``x, P``
    are already propagated and updated), the control estimate (the EKF's output plus the correction
    ``cmd[IN_CORRECTION]`` = ``[dp; dv; dtheta]`` at weight ``cmd[IN_WEIGHT]``, the attitude by
    ``so3.retract``: ``LinkFirmware.control_estimate``), the body rate ``gyro - b_g``,
    :func:`.impedance.impedance_kernel` (paper eq. 1) towards ``cmd[IN_TARGET]`` and, when ``U`` is
    finite, :func:`.allocation.allocate_kernel` (thesis Prop. 1, (2.15), (2.17)) with the link's
    weight kept whole at the limit. Returns the propagated ``(x, P)``; ``out`` (``OUT_*``) gets the
    rest."""
    gyro, accel = imu
    if predict:
        xn, Pn = ekf_predict_kernel(x, P, gyro, accel, dt_s, ekf_par)
    else:
        xn, Pn = x, P
    p = np.empty(3)
    v = np.empty(3)
    q = np.empty(4)
    for i in range(4):
        q[i] = xn[6 + i]
    wgt = cmd[IN_WEIGHT]
    if wgt > 0.0:
        for i in range(3):
            p[i] = xn[i] + wgt * cmd[IN_CORRECTION + i]
            v[i] = xn[3 + i] + wgt * cmd[IN_CORRECTION + 3 + i]
        q[0], q[1], q[2], q[3] = retract(q[0], q[1], q[2], q[3], 0.5 * (wgt * cmd[IN_CORRECTION + 6]),
                                         0.5 * (wgt * cmd[IN_CORRECTION + 7]), 0.5 * (wgt * cmd[IN_CORRECTION + 8]))
    else:
        for i in range(3):
            p[i] = xn[i]
            v[i] = xn[3 + i]
    w = np.empty(3)
    for i in range(3):
        w[i] = gyro[i] - xn[13 + i]
    U = np.empty(6)
    impedance_kernel(p, v, q, w, cmd[IN_TARGET:IN_TARGET + TGT_SIZE], ctl, dt_s, U)
    finite = True
    for i in range(6):
        out[OUT_U + i] = U[i]
        if not math.isfinite(U[i]):
            finite = False
    out[OUT_FORCE_NORM] = math.sqrt(U[0] * U[0] + U[1] * U[1] + U[2] * U[2])
    for i in range(3):
        out[OUT_P_CTRL + i] = p[i]
    out[OUT_FINITE] = 1.0 if finite else 0.0
    if finite:
        result = np.empty((5, 8))
        meta = np.empty(ALLOC_META)
        # the link's weight at the control estimate's attitude, kept whole at the limit:
        # controllers.common.weight_wrench, R^T m g e3 = m g (the third row of R(q))
        mg = ctl[CTL_MASS] * ctl[CTL_GRAVITY]
        R = rotmat_unit(q[0], q[1], q[2], q[3])
        keep = np.zeros(6)
        keep[0] = R[6] * mg
        keep[1] = R[7] * mg
        keep[2] = R[8] * mg
        allocate_kernel(U, keep, alloc, result, meta)
        for i in range(8):
            out[OUT_COMMAND + i] = result[0, i]
        out[OUT_SCALE] = meta[5]
        out[OUT_SATURATED] = meta[4]
    return xn, Pn


@jit
def attitude_tick_kernel(x, P, q_meas, imu, dt_s, ekf_par, cmd, ctl, alloc, out):
    """:func:`tick_kernel` for a tick with an attitude reference ``q_meas`` queued, as the firmware
    runs it step by step: :func:`.ekf.ekf_predict_kernel`, :func:`.ekf.attitude_update_kernel`,
    then the tick without the propagation. Returns ``(x, P, status)``, the update's status: 1
    accepted, 0 rejected by the gate, -1 an invalid quaternion (non-finite or zero), when nothing
    was changed or written and the caller takes the step-by-step path (which raises the
    specification's error)."""
    gyro, accel = imu
    xp, Pp = ekf_predict_kernel(x, P, gyro, accel, dt_s, ekf_par)
    xu, Pu, status, _, _ = attitude_update_kernel(xp, Pp, q_meas, ekf_par)
    if status < 0:
        return x, P, status
    xn, Pn = tick_kernel(xu, Pu, False, imu, dt_s, ekf_par, cmd, ctl, alloc, out)
    return xn, Pn, status


@jit
def hil_tick_kernel(rec, answer, x, P, dt_s, ekf_par, cmd, ctl, alloc, io):
    """The vehicle's common lockstep tick from bytes to bytes: a same-host simulator-link packet
    ``rec`` (uint8) holding one HIL_SENSOR record with an IMU sample only (no barometer or
    magnetometer bits) and finite accelerations and rates within the decoder's bounds
    (``IMU_*_MAX``), after a SKELETON_AHRS_REFERENCE record on the attitude reference's ticks, to
    its HIL_ACTUATOR_CONTROLS record in ``answer`` (uint8, ``HIL_ACTUATOR_RECORD``'s size).

    The steps of the decoding path, with the same numbers: ``hil.decode_hil_sensor`` (body FRD to
    FLU), :func:`tick_kernel` with the propagation, ``hil.encode_actuators`` (each command over
    ``io[IO_THRUST_MAX]``, clipped to -1..1, as a float; ``io[IO_MODE]``; the sample's
    ``time_usec`` echoed). With an attitude reference (:func:`.hil_records.ahrs_record`, with the
    frame change ``io[IO_FRAME]``) the propagation, then :func:`.ekf.attitude_update_kernel`, then
    the tick without the propagation, as the firmware runs a queued measurement; ``io`` counts it
    (``IO_AHRS_ACCEPTED`` / ``IO_AHRS_REJECTED``, added to) and holds its time and quaternion.
    ``io[IO_GYRO]`` gets the body rate (FLU), ``io[IO_ACCEL]`` the specific force (FLU),
    ``io[:OUT_SIZE]`` the tick's results. Returns ``(x,
    P, taken)``: with ``taken`` false (another kind or size, baro/mag bits, a non-finite or
    out-of-range value, a reference the decoder rejects, an answer buffer of another size) nothing
    was changed or written and the caller decodes the packet the general way. The fields sit at odd
    offsets: they are copied byte-wise into aligned arrays, never read or written through a
    misaligned view."""
    s0 = sensor_record_at(rec, rec.shape[0])
    if s0 < 0 or answer.shape[0] != _ACT_SIZE:
        return x, P, False  # (the answer's size checked too: numba does not check the writes' bounds)
    bits = np.empty(1, np.uint32)
    bits.view(np.uint8)[:] = rec[s0 + _SENSOR_BITS:s0 + _SENSOR_BITS + 4]
    if bits[0] & HIL_BARO_MAG_BITS:
        return x, P, False
    imu = np.empty(6, np.float32)  # xacc, yacc, zacc, xgyro, ygyro, zgyro: adjacent in the record
    imu.view(np.uint8)[:] = rec[s0 + _SENSOR_ACC:s0 + _SENSOR_ACC + 24]
    for i in range(6):  # (NaN fails the comparison)
        if not abs(np.float64(imu[i])) <= (IMU_ACCEL_MAX_M_S2 if i < 3 else IMU_GYRO_MAX_RAD_S):
            return x, P, False
    accel = np.empty(3)
    g = np.empty(3)
    for i in range(3):
        sign = 1.0 if i == 0 else -1.0  # frames.flu_frd: (x, -y, -z)
        accel[i] = sign * np.float64(imu[i])
        g[i] = sign * np.float64(imu[3 + i])
    out = io[:OUT_SIZE]
    if s0 == 0:
        xn, Pn = tick_kernel(x, P, True, (g, accel), dt_s, ekf_par, cmd, ctl, alloc, out)
    else:
        if not dt_s > 0.0:
            return x, P, False  # (the decoding path raises for a step that is not positive)
        ok, qa = ahrs_record(rec, io[IO_FRAME:IO_FRAME + 8])
        if not ok:
            return x, P, False
        qm = np.empty(4)
        qm[0], qm[1], qm[2], qm[3] = qa
        xn, Pn, status = attitude_tick_kernel(x, P, qm, (g, accel), dt_s, ekf_par, cmd, ctl, alloc, out)
        io[IO_AHRS_ACCEPTED if status == 1 else IO_AHRS_REJECTED] += 1.0  # (status -1 cannot pass ahrs_record)
        io[IO_AHRS_T_US] = record_time_us(rec, 0)
        for i in range(4):
            io[IO_AHRS_Q + i] = qm[i]
    for i in range(3):
        io[IO_GYRO + i] = g[i]
        io[IO_ACCEL + i] = accel[i]
    controls = np.zeros(16, np.float32)
    thrust_max_n = io[IO_THRUST_MAX]
    for i in range(8):
        u = out[OUT_COMMAND + i] / thrust_max_n
        if u > 1.0:
            u = 1.0
        elif u < -1.0:
            u = -1.0
        controls[i] = np.float32(u)
    answer[0] = _ACT_KIND
    answer[_ACT_T:_ACT_T + 8] = rec[s0 + _SENSOR_T:s0 + _SENSOR_T + 8]
    answer[_ACT_FLAGS:_ACT_FLAGS + 8] = 0
    answer[_ACT_CONTROLS:_ACT_CONTROLS + 64] = controls.view(np.uint8)
    answer[_ACT_MODE] = np.uint8(io[IO_MODE])
    return xn, Pn, True

"""The firmware's common tick as one kernel call, and the vehicle's record tick and lockstep loop.

:class:`FusedTicks` is the part of :class:`~link_firmware_sim.firmware.LinkFirmware` that runs its
common case (armed, eq. 1's controller, a fresh target) through the kernels of
:mod:`link_firmware_sim.kernels.tick` and :mod:`link_firmware_sim.kernels.lockstep`, with the same
state changes as the step-by-step path (``tests/unit/test_fast_paths.py``, ``tests/integration/test_lockstep.py``): a
call's dispatch and the Python between the steps cost more than their arithmetic at 500 Hz per link.

The kernels read the firmware's state as it is grouped (:mod:`link_firmware_sim.kernels.layouts`):
the EKF's ``x``, ``P`` and parameters (:attr:`LinkEkf.par <.estimators.link_ekf.LinkEkf.par>`), eq. 1's
controller (:attr:`ImpedanceController.state <.controllers.impedance.ImpedanceController.state>`),
the allocator's (:attr:`Allocator.tick_state <.allocation.allocator.Allocator.tick_state>`), the tick's
inputs kept here (the correction's weight, the correction, the target: packed when they change, not
at 500 Hz) and, for the vehicle, its buffers (:class:`HilBuffers`).
"""

from __future__ import annotations

import math

import numpy as np

from companion.kernels.jit import ENABLED
from companion.mavlink.frames import FRAME_CHANGE_QUATS
from companion.messages import Correction

from .controllers.impedance import pack_target
from .kernels.hil_records import HIL_ACTUATOR_RECORD
from .kernels.layouts import (IN_CORRECTION, IN_SIZE, IN_TARGET, IN_WEIGHT, IO_ACCEL, IO_AHRS_ACCEPTED, IO_AHRS_Q,
                              IO_AHRS_REJECTED, IO_AHRS_T_US, IO_ARM_HEIGHT, IO_CORR_HOLD, IO_CORR_STALE,
                              IO_CORR_TIME, IO_DT, IO_DT_DEFAULT, IO_DUE_US, IO_FRAME, IO_GPS_FIX, IO_GPS_TIMEOUT,
                              IO_GYRO, IO_MAX_TICKS, IO_MODE, IO_N_FDS, IO_PACKET, IO_SENT, IO_SIZE, IO_STATUS,
                              IO_T_PREV, IO_T_US, IO_TAKEN_BYTES, IO_TAKEOFF, IO_TARGET_STALE, IO_TARGET_TIME,
                              IO_THRUST_MAX, IO_TICKS, IO_TIMEOUT_MS, OUT_COMMAND, OUT_FINITE, OUT_FORCE_NORM,
                              OUT_P_CTRL, OUT_SATURATED, OUT_SCALE, OUT_SIZE)
from .kernels.lockstep import hil_loop_kernel
from .kernels.mavlink_frames import FRAME_BYTES, FRAMING_SIZE
from .kernels.tick import attitude_tick_kernel, hil_tick_kernel, tick_kernel

__all__ = ["TAKEOFF_HEIGHT_M", "pack_correction", "HilBuffers", "FusedTicks"]

TAKEOFF_HEIGHT_M = 0.15  # above the arming height: the land detector's take-off
_COMMAND = slice(OUT_COMMAND, OUT_COMMAND + 8)
_GYRO = slice(IO_GYRO, IO_GYRO + 3)
_ACCEL = slice(IO_ACCEL, IO_ACCEL + 3)
_AHRS = slice(IO_AHRS_ACCEPTED, IO_AHRS_Q + 4)


def pack_correction(correction: Correction) -> np.ndarray:
    """A :class:`~companion.messages.Correction` as the tick reads it (9,): ``dp``, ``dv``, ``dtheta``."""
    return np.concatenate((correction.dp_w_m, correction.dv_w_m_s, correction.dtheta_w_rad)).astype(float)


class HilBuffers:
    """What the vehicle's compiled record tick and lockstep loop write into and read from, owned by
    the vehicle and preallocated once: the answer record (HIL_ACTUATOR_CONTROLS, :attr:`answer`),
    the receive buffer and, over PX4's TCP link, the records read from frames and the answer's
    frame (:attr:`bufs`), the ``poll`` descriptors (:attr:`fds`), the MAVLink 2 framing state
    (:attr:`framing`, ``FRAMING`` of :mod:`link_firmware_sim.kernels.mavlink_frames`) and the
    vehicle's side of the kernels (:attr:`io`, ``IO_*`` of :mod:`link_firmware_sim.kernels.layouts`:
    the tick's results, the attitude references it fused, the loop's report). ``thrust_max_n`` and
    ``mode``: what the answers carry (the controls over the thrust limit, the MAVLink mode flags)."""

    def __init__(self, thrust_max_n: float, mode: int, recv_bytes: int, max_ports: int = 2):
        self.answer = np.zeros(HIL_ACTUATOR_RECORD["size"], dtype=np.uint8)
        buf = np.zeros(recv_bytes, dtype=np.uint8)
        #: ``(receive buffer, records read from frames, the answer's frame, the answer record)``
        self.bufs = (buf, np.zeros(recv_bytes, dtype=np.uint8), np.zeros(FRAME_BYTES, dtype=np.uint8), self.answer)
        #: ``poll``'s pairs ``(fd, events | revents << 16)``: the simulator's socket, then the MAVLink ports
        self.fds = np.zeros(2 * (1 + max_ports), dtype=np.int32)
        self.framing = np.zeros(FRAMING_SIZE, dtype=np.int64)
        self.io = np.zeros(IO_SIZE)
        self.io[IO_THRUST_MAX] = thrust_max_n
        self.io[IO_MODE] = mode
        self.io[IO_FRAME:IO_FRAME + 8] = FRAME_CHANGE_QUATS

    @property
    def buf(self) -> np.ndarray:
        """The receive buffer (a packet the loop left to the caller is at its start)."""
        return self.bufs[0]

    @property
    def frame(self) -> np.ndarray:
        """The newest answer's MAVLink 2 frame (PX4's TCP link)."""
        return self.bufs[2]

    def ahrs(self) -> tuple[int, int, int, np.ndarray]:
        """The attitude references the last call fused: ``(accepted, rejected, newest time_usec,
        newest quaternion (body FLU to ENU))``."""
        io = self.io
        return (int(io[IO_AHRS_ACCEPTED]), int(io[IO_AHRS_REJECTED]), int(io[IO_AHRS_T_US]),
                io[IO_AHRS_Q:IO_AHRS_Q + 4])


class FusedTicks:
    """:class:`~link_firmware_sim.firmware.LinkFirmware`'s fused ticks (a part of that class: it
    reads and keeps the firmware's state as the step-by-step path does)."""

    #: run :meth:`on_imu`'s common case as one kernel call (:meth:`_tick_fused`); ``False`` on an
    #: instance: every tick through the step-by-step path (the two agree: ``tests/unit/test_fast_paths.py``)
    fused_tick: bool = ENABLED
    #: let the vehicle run its quiet lockstep ticks in one kernel call (:meth:`on_hil_loop`); ``False``
    #: on an instance: every tick through :meth:`on_hil_record` (the two agree: ``tests/integration/test_lockstep.py``)
    hil_loop: bool = ENABLED

    def _init_fused(self) -> None:
        self._tick_in = np.zeros(IN_SIZE)  # the kernels' inputs (IN_*), packed as they change
        self._packed = (None, None)  # the correction and the target packed in it

    def _tick_inputs(self, t_s: float) -> np.ndarray:
        """The fused tick's inputs at ``t_s``: the correction's weight, the correction, the target."""
        cmd = self._tick_in
        cmd[IN_WEIGHT] = self.correction_weight(t_s)
        correction, target = self.correction, self.target
        packed_correction, packed_target = self._packed
        if correction is not packed_correction or target is not packed_target:  # (both are frozen)
            if correction is not packed_correction:
                cmd[IN_CORRECTION:IN_TARGET] = 0.0 if correction is None else pack_correction(correction)
            if target is not packed_target:
                cmd[IN_TARGET:] = pack_target(target)
            self._packed = (correction, target)
        return cmd

    def _tick_fused(self, t_s: float, dt: float, gyro_b_rad_s, accel_b_m_s2) -> np.ndarray | None:
        """:meth:`on_imu`'s common case (armed, eq. 1's controller, a fresh target) by
        :func:`~link_firmware_sim.kernels.tick.tick_kernel`: the EKF's propagation, the control
        estimate, eq. 1 and the allocation in one call (with measurements queued: the propagation
        and the updates first, as the step-by-step path runs them), with the same state changes as
        the step-by-step path. ``None`` (nothing changed) in any other case, or without the
        compiled kernels. A tick with an attitude reference alone queued (the attitude reference's
        ticks between GPS fixes) runs the propagation, the update and the tick as one call too
        (:func:`~link_firmware_sim.kernels.tick.attitude_tick_kernel`)."""
        if not self._fused_applies(t_s):
            return None
        ekf, ctl, alloc = self.ekf, self._controller.tick_state, self.allocator.tick_state
        gyro = np.array(gyro_b_rad_s, dtype=float)
        imu = (gyro, np.asarray(accel_b_m_s2, dtype=float))
        out = np.empty(OUT_SIZE)
        predict = not self._pending
        if not predict:
            pending = self._pending
            if len(pending) == 1 and pending[0][0] == "att" and dt > 0.0:  # an attitude reference alone
                q = np.asarray(pending[0][1][0], dtype=float)
                if q.shape == (4,):
                    x, P, status = attitude_tick_kernel(ekf.x, ekf.P, q, imu, dt, ekf.par, self._tick_inputs(t_s),
                                                        ctl, alloc, out)
                    if status >= 0:  # (else the steps below raise the specification's error)
                        ekf.x, ekf.P = x, P
                        ekf.count_attitude(int(status == 1), int(status == 0))
                        pending.clear()
                        return self._fused_done(t_s, dt, gyro, imu[1], out)
            ekf.predict(*imu, dt)
            self.time_s = t_s
            self._apply_pending()
        ekf.x, ekf.P = tick_kernel(ekf.x, ekf.P, predict, imu, dt, ekf.par, self._tick_inputs(t_s), ctl, alloc, out)
        return self._fused_done(t_s, dt, gyro, imu[1], out)

    def _fused_applies(self, t_s: float) -> bool:
        """The fused tick's case: armed, eq. 1's controller (compiled), a fresh target, no attitude
        reset due (the next attitude reference takes the step-by-step path, which resets) and the
        gyro and the accelerometer not stale (the step-by-step path flies without them)."""
        target = self.target
        return (self.fused_tick and self.armed and self._controller.tick_state is not None and target is not None
                and t_s - self._target_time_s <= self.config.target_stale_s
                and not (self.ekf is not None and self.ekf.attitude_reset_due) and not self.imu_health.stale)

    def _fused_done(self, t_s: float, dt: float, gyro: np.ndarray, accel: np.ndarray, out: np.ndarray) -> np.ndarray:
        """The state the fused tick leaves outside the kernels' arrays (from its results ``out``,
        ``OUT_*``); returns the thrust commands (with a wrench that is not finite: the held ones,
        :mod:`.wrench_guard`; the compiled paths then sent no answer)."""
        self.ekf.last_gyro_b_rad_s = gyro
        self.time_s = t_s
        self.events.extend(self.gps_health.on_tick(t_s))
        self.imu_health.sample(gyro, accel)
        if not out[OUT_FINITE]:
            return self._refuse_wrench(t_s)
        self.wrench_guard.passed(out[_COMMAND])
        self._thrust_total_n = float(out[OUT_FORCE_NORM])
        if not self._airborne and out[OUT_P_CTRL + 2] - self._arm_height_m > TAKEOFF_HEIGHT_M:
            self._airborne = True
        alloc = self.allocator
        alloc.scale, alloc.saturated = float(out[OUT_SCALE]), bool(out[OUT_SATURATED])
        self.events.extend(self.thrust_limit.on_tick(t_s, dt, alloc.saturated, alloc.scale))
        return out[_COMMAND]

    def on_hil_record(self, t_s: float, record: np.ndarray, hil: HilBuffers, answered=None) -> np.ndarray | None:
        """:meth:`on_imu`'s fused case (armed, eq. 1, a fresh target) with no measurement queued,
        straight from a same-host simulator-link record to its answer record, by
        :func:`~link_firmware_sim.kernels.tick.hil_tick_kernel`: ``record`` (uint8) one HIL_SENSOR
        of sample time ``t_s`` (after a SKELETON_AHRS_REFERENCE on the attitude reference's ticks:
        :meth:`on_attitude`'s update, counted by the EKF and in ``hil``, :meth:`HilBuffers.ahrs`);
        ``hil.answer`` gets the HIL_ACTUATOR_CONTROLS, and ``answered(answer)``, when given, is
        called as soon as it is written and its wrench found finite, before the tick's bookkeeping
        (integrals, health and thrust-limit monitors): the simulator is not kept waiting for what
        does not change the answer. Returns the thrust commands; ``None`` (nothing changed or
        written) in any other case, for a record the kernel leaves to the decoding path, or without
        the compiled kernels. The record layouts are ``HIL_SENSOR_RECORD`` / ``HIL_ACTUATOR_RECORD``
        of :mod:`link_firmware_sim.kernels.hil_records`, which :mod:`.vehicle.simlink` checks against the
        dialect."""
        if self.ekf is None or self._pending or not self._fused_applies(t_s):
            return None
        dt = self._tick_dt(t_s)
        ekf, io = self.ekf, hil.io
        io[_AHRS] = 0.0
        x, P, taken = hil_tick_kernel(record, hil.answer, ekf.x, ekf.P, dt, ekf.par, self._tick_inputs(t_s),
                                      self._controller.tick_state, self.allocator.tick_state, io)
        if not taken:
            return None
        ekf.x, ekf.P = x, P
        ekf.count_attitude(int(io[IO_AHRS_ACCEPTED]), int(io[IO_AHRS_REJECTED]))
        if answered is not None and io[OUT_FINITE]:
            answered(hil.answer)
        return self._fused_done(t_s, dt, io[_GYRO].copy(), io[_ACCEL].copy(), io[:OUT_SIZE]).copy()

    def on_hil_loop(self, hil: HilBuffers, n_fds: int, timeout_ms: int, max_ticks: int, due_us: int, answered,
                    frames: bool = False) -> tuple | None:
        """The vehicle's lockstep over quiet ticks (:func:`~link_firmware_sim.kernels.lockstep.hil_loop_kernel`,
        the waits and the socket calls in it): each is :meth:`on_hil_record`'s tick, answered
        through the simulator's socket (``hil.fds``' first descriptor; ``n_fds`` descriptors in
        all) from ``hil.answer``, with the bookkeeping left out that such a tick does not change.
        Each wait lasts at most ``timeout_ms``, the call at most ``max_ticks`` ticks; ``due_us``:
        the vehicle's next stream or log row (a tick at or after it is the last). The newest tick's
        bookkeeping is done here (``answered(answer)`` first if the kernel did not send it), as
        :meth:`on_hil_record` does it, and stands for the ticks before it. ``frames``: the
        simulator's link is PX4's TCP link, MAVLink 2 frames on a stream, with ``hil.framing`` set
        (else the same-host link's records). Returns ``(status, ticks, sent, t_us, packet,
        taken_bytes)`` (the ``IO_STATUS`` ... ``IO_TAKEN_BYTES`` of the loop's report: why it
        returned, ``LOOP_*`` of :mod:`link_firmware_sim.kernels.lockstep`); ``None`` (nothing
        waited for or changed) unless the case holds: armed, eq. 1, a target, no measurement or
        event queued, the GPS and thrust-limit monitors quiet."""
        if not (self.hil_loop and self._quiet_case()):
            return None
        ekf, io = self.ekf, hil.io
        cmd = self._quiet_io(io)  # (the kernel weighs the correction itself, tick by tick)
        io[IO_TIMEOUT_MS], io[IO_MAX_TICKS], io[IO_N_FDS], io[IO_DUE_US] = timeout_ms, max_ticks, n_fds, due_us
        if not frames:
            hil.framing[:] = 0  # (the records: the frame buffers are not touched)
        x, P = hil_loop_kernel(hil.fds, hil.bufs, hil.framing, ekf.x, ekf.P, ekf.par, cmd,
                               self._controller.tick_state, self.allocator.tick_state, io)
        status, ticks, sent, t_us, packet, taken_bytes = (int(io[k]) for k in (IO_STATUS, IO_TICKS, IO_SENT, IO_T_US,
                                                                                IO_PACKET, IO_TAKEN_BYTES))
        if ticks:
            ekf.x, ekf.P = x, P
            ekf.count_attitude(int(io[IO_AHRS_ACCEPTED]), int(io[IO_AHRS_REJECTED]))
            if sent < ticks and io[OUT_FINITE]:
                answered(hil.answer)
            self._fused_done(t_us * 1e-6, float(io[IO_DT]), io[_GYRO].copy(), io[_ACCEL].copy(), io[:OUT_SIZE])
        return status, ticks, sent, t_us, packet, taken_bytes

    def _quiet_case(self) -> bool:
        """Quiet ticks may run in a kernel without this firmware's bookkeeping (:mod:`.kernels.quiet`):
        armed, eq. 1, a fresh target (:meth:`_fused_applies`), no measurement or event queued, the
        GPS and thrust-limit monitors quiet."""
        return (self.ekf is not None and not self._pending and not self.events and not self.gps_health.fault
                and self.thrust_limit.quiet and self._fused_applies(self.time_s))

    def _quiet_io(self, io: np.ndarray) -> np.ndarray:
        """The inputs of :mod:`.kernels.quiet` written to ``io`` (``IO_*``: the previous tick's time,
        the nominal step, the target's, the correction's and the GPS fix's times and limits, the
        arming and take-off heights); returns the fused tick's inputs (``IN_*``)."""
        cfg = self.config
        io[IO_T_PREV], io[IO_DT_DEFAULT] = self.time_s, 1.0 / cfg.rate_hz
        io[IO_TARGET_TIME], io[IO_TARGET_STALE] = self._target_time_s, cfg.target_stale_s
        io[IO_CORR_TIME] = math.nan if self.correction is None else self._correction_time_s
        io[IO_CORR_HOLD], io[IO_CORR_STALE] = cfg.correction_hold_s, cfg.correction_stale_s
        io[IO_GPS_FIX], io[IO_GPS_TIMEOUT] = self.gps_health.last_fix_s, self.gps_health.config.timeout_s
        io[IO_ARM_HEIGHT], io[IO_TAKEOFF] = math.inf if self._airborne else self._arm_height_m, TAKEOFF_HEIGHT_M
        io[_AHRS] = 0.0
        return self._tick_inputs(self.time_s)

    def _quiet_done(self, io: np.ndarray, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The bookkeeping after quiet ticks run elsewhere (:class:`~link_firmware_sim.batch.LinkBatch`):
        the EKF's new ``x``, ``P`` (the caller's to give: not reused) and the newest tick's, from
        ``io`` (``IO_*``: its time, step, samples and results); returns its thrust commands (a
        non-finite wrench: the held ones)."""
        ekf = self.ekf
        ekf.x, ekf.P = x, P
        return self._fused_done(float(io[IO_T_PREV]), float(io[IO_DT]), io[_GYRO].copy(), io[_ACCEL].copy(),
                                io[:OUT_SIZE])

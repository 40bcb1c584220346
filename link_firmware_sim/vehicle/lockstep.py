"""The vehicle's side of the simulator link, in lockstep: every HIL_SENSOR gets exactly one
HIL_ACTUATOR_CONTROLS answer, echoing its ``time_usec``; HIL_GPS and SKELETON_AHRS_REFERENCE
start the EKF, then feed it. The simulator's ticks are the flight controller's clock. Injected
failures (:mod:`.failures`) apply to the GPS fixes, IMU samples and rotor commands here; while an
IMU or motor failure is in effect every tick takes the decoders' path.

Three paths, with the same numbers (``tests/integration/test_lockstep.py``):

* the decoders (:mod:`.hil`) and the firmware's step-by-step calls, for every packet;
* the record tick (:meth:`Lockstep.tick_record`): a same-host link's packet that is the common
  tick (one IMU-only HIL_SENSOR record, after a SKELETON_AHRS_REFERENCE on the attitude
  reference's ticks; armed, eq. 1's controller, a fresh target, no measurement queued), from the
  packet's bytes to the answer's in one compiled call;
* the lockstep loop (:meth:`Lockstep.run_loop`): a run of such quiet ticks, with the waits and the
  socket calls between them, in one compiled call, over the same-host link or PX4's TCP link
  (reading and writing the ticks' MAVLink 2 frames).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from companion.mavlink.codec import MessageError, seconds
from companion.mavlink.dialect import load_dialect

from ..fused import HilBuffers
from ..kernels.hil_records import HIL_SENSOR_RECORD, sensor_record_at
from ..kernels.lockstep import LOOP_PACKET
from ..kernels.mavlink_frames import FRAMES_TO_VEHICLE, FRAMING
from .hil import decode_ahrs, decode_hil_baro_mag, decode_hil_gps, decode_hil_sensor, encode_actuators
from .links import HIL_ACCEPT
from .simlink import RECV_BYTES, SimLinkPort, open_sim_port

__all__ = ["Lockstep"]

log = logging.getLogger(__name__)
D = load_dialect()

# the same-host link's records the compiled tick reads and writes (checked against the dialect by .simlink)
_SENSOR_TIME = HIL_SENSOR_RECORD["time_usec"]
_FRAMING_SEQ_IN, _FRAMING_SEQ_OUT = FRAMING["seq_in"], FRAMING["seq_out"]
_FRAMING_SENT, _FRAMING_LENGTH = FRAMING["sent"], FRAMING["length"]
#: the most quiet ticks one call of the lockstep loop runs (streams and log rows end it sooner)
_LOOP_MAX_TICKS = 64
_NEVER_US = 2**62


class Lockstep:
    """The simulator link of vehicle ``vehicle`` (``url``: PX4's TCP link or the same-host link,
    never signed: it is the physics) and the ticks it brings: the vehicle's firmware, its
    flight-controller time (set here), its error counters, its origin; after each tick the
    vehicle's bookkeeping (``vehicle.after_tick``: events, streams, the flight log)."""

    def __init__(self, vehicle, url: str, thrust_max_n: float):
        self.vehicle = vehicle
        self.thrust_max_n = thrust_max_n
        self.sim = open_sim_port(url, vehicle.system_id, accept=HIL_ACCEPT)
        self.records = isinstance(self.sim, SimLinkPort)
        #: the compiled record tick's and lockstep loop's buffers: the answer, the receive buffer,
        #: the poll descriptors, over PX4's TCP link the MAVLink 2 framing (sequence numbers), and
        #: what the kernels report
        self.buffers = HilBuffers(thrust_max_n, D.MAV_MODE_FLAG_SAFETY_ARMED, RECV_BYTES)
        self.last_gps: tuple | None = None  # (t, p, v) until the EKF starts
        self.last_ahrs: tuple | None = None  # (t, q)

    # -- what poll reads ---------------------------------------------------------------------
    def on_readable(self) -> None:
        """The simulator link is readable (or not connected: a listener accepts on readable too)."""
        if self.records:
            data = self.sim.recv()
            if data is not None:
                self.on_packet(data)
        else:
            for msg in self.sim.read():
                self.on_hil(msg)

    def on_packet(self, data: bytes) -> None:
        """A same-host link's packet: the record tick (:meth:`tick_record`), else its messages
        through the decoders."""
        if not self.tick_record(data):
            for msg in self.sim.decode(data):
                self.on_hil(msg)

    # -- the decoders' path ------------------------------------------------------------------
    def on_hil(self, msg) -> None:
        v = self.vehicle
        fw = v.fw
        kind = msg.get_type()
        try:
            if kind == "HIL_SENSOR":
                self._on_hil_sensor(msg)
            elif kind == "HIL_GPS":
                t, p, vel = decode_hil_gps(msg, v.origin)
                fix = v.failures.gps(p, vel)
                if fix is None:  # an injected GPS failure: no fix reaches the firmware
                    return
                p, vel = fix
                self.last_gps = (t, p, vel)
                if fw.initialized:
                    fw.on_gps(t, p, vel)
                elif self.last_ahrs is not None:
                    fw.initialize(t, p, vel, self.last_ahrs[1])
            elif kind == "SKELETON_AHRS_REFERENCE":
                t, q = decode_ahrs(msg)
                self.last_ahrs = (t, q)
                if fw.initialized:
                    fw.on_attitude(t, q)
                elif self.last_gps is not None:
                    _, p, vel = self.last_gps
                    fw.initialize(t, p, vel, q)
        except MessageError as exc:
            v.errors["hil"] += 1
            log.warning("link %d: rejected %s: %s", v.system_id, kind, exc)

    def _on_hil_sensor(self, msg) -> None:
        """One lockstep tick: every HIL_SENSOR gets exactly one HIL_ACTUATOR_CONTROLS answer. A
        sample the decoder refuses is answered with zero thrust at its own ``time_usec`` (the
        lockstep goes on) and moves nothing: not the clock, not the estimate."""
        v = self.vehicle
        try:
            t, gyro, accel = decode_hil_sensor(msg)
        except MessageError:
            # keep the lockstep going; the caller logs the rejection
            self.sim.send(encode_actuators(0.0, np.zeros(8), self.thrust_max_n, v.fw.armed,
                                                 time_usec=int(msg.time_usec)))
            raise
        v.fc_time_us = int(msg.time_usec)
        v.fc_time_s = t
        self._on_baro_mag(t, msg)
        if not v.fw.initialized:
            # The EKF starts at the first GPS fix with an attitude reference; until then the
            # rotors stay off, but the simulator still gets its answer.
            self._answer(np.zeros(8))
            return
        failures = v.failures
        if self.step_by_step:
            gyro, accel = failures.imu(gyro, accel)
            command = v.fw.on_imu(t, gyro, accel)
            thrust = failures.thrust(command)  # (what the motors apply: the ESCs' telemetry)
            v.fw.on_esc_telemetry(t, command, thrust)
            self._answer(thrust)
        else:
            self._answer(v.fw.on_imu(t, gyro, accel))
        v.after_tick()

    def _on_baro_mag(self, t: float, msg) -> None:
        """The HIL_SENSOR's barometer and magnetometer samples (when its bits mark them) to the
        firmware, queued before this tick's IMU sample; an invalid one is dropped and counted
        (``errors["hil_baro"]`` / ``["hil_mag"]``), the tick goes on."""
        v = self.vehicle
        sample = decode_hil_baro_mag(msg)
        for name in sample.rejected:
            count = v.errors[f"hil_{name}"] = v.errors[f"hil_{name}"] + 1
            if math.log10(count).is_integer():  # the 1st, 10th, 100th, ...: no flood at 50 Hz
                log.warning("link %d: dropped an invalid HIL_SENSOR %s sample (%d so far)", v.system_id, name,
                            count)
        if sample.baro_alt_m is not None:
            v.fw.on_baro(t, sample.baro_alt_m - v.origin.alt_m)  # height above the origin
        if sample.mag_flu_gauss is not None:
            v.fw.on_mag(t, sample.mag_flu_gauss)

    @property
    def step_by_step(self) -> bool:
        """Whether the ticks must take the decoding path, not the compiled ones: an injected IMU or
        motor failure is applied there, and a rotor left out has its ESCs' telemetry judged there."""
        v = self.vehicle
        return v.failures.imu_or_motor or v.fw.rotor_out

    def _answer(self, thrust: np.ndarray) -> None:
        v = self.vehicle
        self.sim.send(encode_actuators(v.fc_time_s, thrust, self.thrust_max_n, v.fw.armed))

    # -- the compiled paths ------------------------------------------------------------------
    def tick_record(self, data: bytes) -> bool:
        """The same-host link's common tick from the packet's bytes to the answer's, in one
        compiled call (:meth:`LinkFirmware.on_hil_record`): the decoding path's numbers without a
        message object on the way. ``False`` (nothing changed) for any other packet: the caller
        decodes it."""
        v = self.vehicle
        if self.step_by_step:
            return False
        rec = np.frombuffer(data, dtype=np.uint8)
        at = sensor_record_at(rec, len(rec))
        if at < 0:
            return False
        t_us = int.from_bytes(data[at + _SENSOR_TIME:at + _SENSOR_TIME + 8], "little")
        t_s = seconds(t_us)
        # (a record it takes is answered through send_packet before the tick's bookkeeping)
        command = v.fw.on_hil_record(t_s, rec, self.buffers, answered=self.sim.send_packet)
        if command is None:
            return False
        v.fc_time_us, v.fc_time_s = t_us, t_s
        if v.fw.wrench_guard.holding:  # (a refused wrench: the kernel sent nothing)
            self._answer(command)
        self.sim.count("HIL_SENSOR")
        self._ahrs_fused()
        v.after_tick()
        return True

    def _ahrs_fused(self) -> None:
        """The attitude references a compiled tick fused (:meth:`HilBuffers.ahrs`): counted on the
        link, the newest kept, as :meth:`on_hil` does with one it decodes."""
        accepted, rejected, t_us, q = self.buffers.ahrs()
        if accepted + rejected:
            self.sim.count("SKELETON_AHRS_REFERENCE", accepted + rejected)
            self.last_ahrs = (seconds(t_us), q.copy())

    def run_loop(self, timeout_s: float) -> bool:
        """The simulator link's quiet ticks in one compiled call (:meth:`LinkFirmware.on_hil_loop`:
        the waits, the packets, the ticks and their answers, with the numbers of :meth:`tick_record`
        and of the decoders), until a tick needs the vehicle's bookkeeping (a stream or log row
        due, an event), a packet is of another kind, a MAVLink port is readable, or ``timeout_s``.
        Over PX4's TCP link the loop reads and writes the MAVLink 2 frames while the port may hand
        its stream over (:meth:`MavlinkPort.handover`) and gives the sequence numbers back.
        ``False`` (nothing waited for) when the case does not hold; the caller then waits as
        usual."""
        v = self.vehicle
        if self.step_by_step:
            return False
        hil = self.buffers
        framing = hil.framing
        if self.records:
            conn = self.sim.conn
            if conn is None:
                return False
            sim_fd, answered = conn.fileno(), self.sim.send_packet
        else:
            handover = self.sim.handover()
            if handover is None:
                return False
            sim_fd, sender, last_seq = handover
            framing[:7] = (FRAMES_TO_VEHICLE, *sender, last_seq, v.system_id, self.sim.mav.srcComponent,
                           self.sim.mav.seq)
            answered = self.answer_rest
        fds = hil.fds
        fds[0] = sim_fd
        for k, ep in enumerate(v.endpoints, 1):
            fds[2 * k] = ep.port.fileno()
        n_fds = 1 + len(v.endpoints)
        if fds[:2 * n_fds:2].min() < 0:
            return False  # (a serial port waiting to reopen)
        due = min(v.streams.due_us, v.recorder.due_us)
        due = int(min(due, _NEVER_US))  # (no stream at all: inf; the kernel takes an integer)
        frames = not self.records
        res = v.fw.on_hil_loop(hil, n_fds=n_fds, timeout_ms=max(int(timeout_s * 1e3), 0),
                               max_ticks=_LOOP_MAX_TICKS, due_us=due, answered=answered, frames=frames)
        if res is None:
            return False
        status, ticks, sent, t_us, packet, taken_bytes = res
        if frames and ticks:  # (before a packet handed over is parsed: its numbers follow these)
            self.sim.resume(sender, int(framing[_FRAMING_SEQ_IN]), int(framing[_FRAMING_SEQ_OUT]))
        if ticks:
            self.sim.received(taken_bytes)
            self.sim.count("HIL_SENSOR", ticks)
            self._ahrs_fused()
            self.sim.sent(sent)
            v.fc_time_us, v.fc_time_s = t_us, seconds(t_us)
            if v.fw.wrench_guard.holding:  # (the last tick's wrench refused: the kernel sent nothing)
                self._answer(v.fw.wrench_guard.command)
            v.after_tick()
        if status == LOOP_PACKET:  # received, not taken: as poll takes a packet
            data = hil.buf[:packet].tobytes()
            if self.records:
                self.sim.received(packet)
                self.on_packet(data)
            else:  # (the parser counts the bytes)
                for msg in self.sim.parse(data):
                    self.on_hil(msg)
        return True

    def answer_rest(self, _answer) -> None:
        """The lockstep loop's answer frame over TCP, the part its send did not take (all of it
        after EAGAIN or an error): the port writes it as it writes a frame it packed."""
        framing = self.buffers.framing
        start = max(int(framing[_FRAMING_SENT]), 0)
        self.sim.send_frame(self.buffers.frame[start:int(framing[_FRAMING_LENGTH])].tobytes())

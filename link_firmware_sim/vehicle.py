"""A simulated Pixhawk as a MAVLink 2 vehicle: one OS process per link.

Ports (PX4 SITL habits; all configurable):

* simulator: ``tcpin://127.0.0.1:4560+i`` (PX4's simulator MAVLink API, lockstep): HIL_SENSOR,
  HIL_GPS and SKELETON_AHRS_REFERENCE in, HIL_ACTUATOR_CONTROLS out, one answer per HIL_SENSOR;
  or the same messages over the same-host link ``unixin:///PATH`` (:mod:`.simlink`). Either way
  the quiet ticks run in one compiled loop (:meth:`Vehicle._poll_loop`), the waits and the
  socket calls in it;
* onboard (companion): ``udpout://127.0.0.1:14540+i`` from local port 14580+i;
* GCS: ``udpout://127.0.0.1:14550`` from local port 18570+i.

MAVLink services implemented here with pymavlink (see the README for why not MAVSDK's server
components): HEARTBEAT and SYS_STATUS (1 Hz), the parameter protocol (PARAM_REQUEST_LIST /
READ, PARAM_SET with PARAM_VALUE replies; persisted), COMMAND_LONG / COMMAND_INT with COMMAND_ACK
(arm/disarm, SET_MESSAGE_INTERVAL, REQUEST_MESSAGE incl. AUTOPILOT_VERSION, REQUEST_AUTOPILOT_
CAPABILITIES, the dialect's MAV_CMD_SKELETON_SET_CONTACT for the hybrid controller; anything else:
UNSUPPORTED), telemetry streams on flight-controller time
(ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT, ODOMETRY with covariance,
SKELETON_LINK_STATE; SKELETON_EXTERNAL_WRENCH with the hybrid controller, ``SKL_WRENCH_HZ``;
DEBUG_VECT ``PSPM`` with PSPM's reservoirs under teleoperation, ``SKL_PSPM_EN``), and inputs:
SKELETON_CORRECTION, ODOMETRY as external-vision correction (standard-messages mode),
SET_POSITION_TARGET_LOCAL_NED and SET_ATTITUDE_TARGET (operator set poses under PSPM). Only those
message types are acted on; everything else is counted (see :class:`MavlinkPort`).

Failsafes are the firmware's: a correction older than ``SKL_CORR_STALE`` fades to the raw EKF, a
target older than ``COM_OF_LOSS_T`` becomes a position hold.
"""

from __future__ import annotations

import json
import logging
import math
import signal
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion.logstream import LogStream
from companion.mavlink.codec import (
    MessageError,
    decode_contact_command,
    decode_correction,
    decode_target_feedforward,
    encode_external_wrench,
    encode_link_state,
    seconds,
    usec,
)
from companion.mavlink.dialect import load_dialect
from companion.mavlink.frames import enu_ned, flu_frd, quat_enu_flu_to_ned_frd
from companion.mavlink.standard import (
    decode_attitude_target,
    decode_external_pose,
    decode_position_target,
    encode_odometry,
    euler_zyx,
)
from companion.mavlink.port import MavlinkPort
from companion.mavlink.tlog import TlogWriter
from companion.mavlink.transport import wait_readable
from companion.mavlink.signing import KEY_LEN, UNSIGNED_ALLOWED, SigningConfig, write_key_file
from companion.messages import Correction, PoseTarget

from .firmware import CorrectionRejected, LinkFirmware
from .fused import HilBuffers
from .geo import GeoOrigin
from .hil import (
    decode_ahrs,
    decode_hil_baro_mag,
    decode_hil_gps,
    decode_hil_sensor,
    encode_actuators,
    sitl_gps_time_us,
)
from .kernels.hil_records import HIL_SENSOR_RECORD, sensor_record_at
from .kernels.lockstep import LOOP_PACKET
from .kernels.mavlink_frames import FRAMES_TO_VEHICLE, FRAMING
from .params import ParamTable
from .simlink import RECV_BYTES, SimLinkPort, open_sim_port

__all__ = ["VehiclePorts", "Vehicle", "FORCE_DISARM"]

log = logging.getLogger(__name__)
D = load_dialect()

HIL_ACCEPT = frozenset({"HIL_SENSOR", "HIL_GPS", "SKELETON_AHRS_REFERENCE"})
MAVLINK_ACCEPT = frozenset({
    "HEARTBEAT", "PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET", "COMMAND_LONG", "COMMAND_INT",
    "SET_POSITION_TARGET_LOCAL_NED", "SET_ATTITUDE_TARGET", "SKELETON_TARGET_FEEDFORWARD", "SKELETON_CORRECTION",
    "ODOMETRY", "VISION_POSITION_ESTIMATE", "SET_GPS_GLOBAL_ORIGIN", "SETUP_SIGNING", "FILE_TRANSFER_PROTOCOL",
})
#: DEBUG_VECT name of PSPM's reservoirs (x: E_t, y: E_r [J]; z: the set position's lag [m])
PSPM_DEBUG_NAME = b"PSPM"
_PX4_OFFBOARD = 6 << 16  # PX4 custom_mode: main mode OFFBOARD
#: MAV_CMD_COMPONENT_ARM_DISARM param2 that disarms a vehicle in flight (PX4, ArduPilot)
FORCE_DISARM = 21196
#: How long a SKELETON_TARGET_FEEDFORWARD goes on applying to later position targets when theirs
#: has not come (lost, or still on its way) [ms of time_boot_ms]: five 50 Hz target periods.
FEEDFORWARD_HOLD_MS = 100
_LINK_NAMES = ("onboard", "gcs")
# the same-host link's records the compiled tick reads and writes (checked against the dialect by .simlink)
_SENSOR_TIME = HIL_SENSOR_RECORD["time_usec"]
_FRAMING_SEQ_IN, _FRAMING_SEQ_OUT = FRAMING["seq_in"], FRAMING["seq_out"]
_FRAMING_SENT, _FRAMING_LENGTH = FRAMING["sent"], FRAMING["length"]
#: the most quiet ticks one call of the lockstep loop runs (streams and log rows end it sooner)
_LOOP_MAX_TICKS = 64
_NEVER_US = 2**62
# MAVLink FTP (mavlink.io "File Transfer Protocol"): opcodes and errors this vehicle answers
_FTP_TERMINATE, _FTP_RESET, _FTP_ACK, _FTP_NAK = 1, 2, 128, 129
_FTP_ERR_UNKNOWN_COMMAND, _FTP_ERR_FILE_NOT_FOUND = 9, 10
_FTP_OPEN_FILE_RO, _FTP_LIST_DIRECTORY = 4, 3
_FLIGHT_SW_VERSION = (0 << 24) | (1 << 16) | (0 << 8) | 255  # 0.1.0 (release)
_CAPABILITIES = (
    D.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | D.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | D.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | D.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | D.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
)


@dataclass(frozen=True)
class VehiclePorts:
    sim: str
    onboard: str
    gcs: str | None

    @classmethod
    def px4_sitl(cls, instance: int, host: str = "127.0.0.1") -> VehiclePorts:
        return cls(
            sim=f"tcpin://{host}:{4560 + instance}",
            onboard=f"udpout://{host}:{14540 + instance}?bind={14580 + instance}",
            gcs=f"udpout://{host}:14550?bind={18570 + instance}",
        )


@dataclass
class _Stream:
    """A periodic message on flight-controller time, in integer microseconds (no drift off the
    simulator's tick grid)."""

    interval_us: int
    next_us: int = 0

    @classmethod
    def at_rate(cls, hz: float, now_us: int = 0) -> _Stream:
        return cls.every(int(round(1e6 / hz)), now_us)

    @classmethod
    def every(cls, interval_us: int, now_us: int = 0) -> _Stream:
        """First message at the next multiple of the interval: every link's stream of one rate has
        the same phase whenever it was requested, so the companion gets coherent snapshots."""
        interval_us = max(int(interval_us), 1)
        return cls(interval_us, -(-now_us // interval_us) * interval_us)


@dataclass
class _Endpoint:
    port: MavlinkPort
    name: str = "onboard"  # "onboard" or "gcs"
    trusted: bool = False  # SETUP_SIGNING accepted here
    streams: dict[int, _Stream] = field(default_factory=dict)


class Vehicle:
    """One link's firmware behind its MAVLink ports."""

    def __init__(self, instance: int, firmware: LinkFirmware, params: ParamTable, ports: VehiclePorts,
                 out_dir: Path | None = None, log_rate_hz: float = 50.0, thrust_max_n: float = 8.0,
                 signing: SigningConfig | None = None, key: bytes | None = None, key_path: Path | None = None):
        self.instance = instance
        self.system_id = instance + 1
        self.fw = firmware
        self.params = params
        self.origin = params.origin()
        self.out_dir = out_dir
        self.thrust_max_n = thrust_max_n
        self.signing = signing or SigningConfig()
        self.key_path = key_path
        self.fw.reconfigure(params.firmware_config())
        # The simulator link is the physics (PX4's simulator API): never signed.
        self.sim = open_sim_port(ports.sim, self.system_id, accept=HIL_ACCEPT)
        self._records = isinstance(self.sim, SimLinkPort)
        # the compiled record tick's (_tick_record) and lockstep loop's (_poll_loop) buffers: the answer,
        # the receive buffer, the poll descriptors, over PX4's TCP link the MAVLink 2 framing (sequence
        # numbers), and what the kernels report
        self._hil = HilBuffers(thrust_max_n, D.MAV_MODE_FLAG_SAFETY_ARMED, RECV_BYTES)
        self.endpoints = []
        for link_id, (name, url) in enumerate(zip(_LINK_NAMES, (ports.onboard, ports.gcs))):
            if not url:
                continue
            trusted = name in self.signing.trusted
            # one tlog per link (each has its own sequence numbers): link<i>.tlog, link<i>_gcs.tlog
            suffix = "" if name == "onboard" else f"_{name}"
            tlog = TlogWriter(out_dir / f"link{instance + 1}{suffix}.tlog") if out_dir is not None else None
            allowed = UNSIGNED_ALLOWED | ({"SETUP_SIGNING"} if trusted else set())
            try:
                port = MavlinkPort(url, self.system_id, accept=MAVLINK_ACCEPT, tlog=tlog,
                                   signing=self.signing.link_mode(name), key=key, link_id=link_id,
                                   unsigned_allowed=allowed)
            except Exception:
                self.sim.close()
                for ep in self.endpoints:
                    ep.port.close()
                raise
            self.endpoints.append(_Endpoint(port, name, trusted))
        self._set_default_streams()
        self.fc_time_s = 0.0
        self.fc_time_us = 0
        self.boot_wall_s = time.monotonic()
        self._next_heartbeat_wall = 0.0
        # Like PX4's SITL, the firmware is silent on MAVLink until the simulator has connected: a
        # process started ahead of its "power on" (a scripted reboot) is not seen before it.
        self._sim_seen = False
        self._pos_target: tuple | None = None  # (p, v, a) ENU
        self._pos_target_ms = -1  # its time_boot_ms
        self._ff_target: tuple | None = None  # (time_boot_ms, omega_dot FLU, force ENU, torque FLU)
        self._ff_applied: tuple | None = None  # the newest one that met its position target
        self._att_target: tuple | None = None  # (q ENU/FLU, omega FLU)
        self._target_due = False  # a target message came: _update_target after the link's read
        self._log = _Stream.at_rate(log_rate_hz)
        # pspm: PSPM's reservoirs E_t, E_r [J] and the set position's lag [m] (pspm_report; NaN while PSPM is off)
        self._rows: dict[str, list] = {k: [] for k in ("t", "p_ekf", "q_ekf", "p_ctrl", "q_ctrl", "p_target", "q_target",
                                                       "pspm")}
        self.errors = {"hil": 0, "mavlink": 0, "correction_rejected": 0, "disarm_refused": 0, "setup_signing_refused": 0,
                       "hil_baro": 0, "hil_mag": 0}
        self._next_status_wall: dict[str, float] = {}
        self._cache_tick_us = -1  # no tick yet: _tick_values computes on first use
        self._cached = None
        self._last_gps: tuple | None = None  # (t, p, v) until the EKF starts
        self._last_ahrs: tuple | None = None  # (t, q)
        self._stop = False
        self._closed = False
        # The flight log streamed to disk every second (a killed vehicle keeps what it flew)
        self._log_stream = LogStream(out_dir / f"link{instance + 1}_firmware.stream") if out_dir is not None else None

    # -- streams -------------------------------------------------------------------------
    def _default_rates(self, endpoint: int) -> dict[int, float]:
        """Message id -> default rate [Hz] of endpoint 0 (onboard) or 1 (GCS)."""
        rates = self.params.rates()
        onboard = {
            D.MAVLINK_MSG_ID_SKELETON_LINK_STATE: rates.state_hz,
            D.MAVLINK_MSG_ID_ODOMETRY: rates.odometry_hz,
            D.MAVLINK_MSG_ID_ATTITUDE: 10.0,
            D.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 10.0,
            D.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
            D.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
            D.MAVLINK_MSG_ID_SKELETON_EXTERNAL_WRENCH: rates.wrench_hz,
        }
        gcs = {
            D.MAVLINK_MSG_ID_ATTITUDE: 10.0,
            D.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 5.0,
            D.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
            D.MAVLINK_MSG_ID_DEBUG_VECT: 5.0,  # PSPM's reservoirs (nothing is sent while PSPM is off)
            # the link's state and covariance, for a ground station with the dialect (SET_MESSAGE_INTERVAL: faster)
            D.MAVLINK_MSG_ID_SKELETON_LINK_STATE: 1.0,
        }
        return onboard if endpoint == 0 else gcs

    def _set_default_streams(self) -> None:
        for k, ep in enumerate(self.endpoints):
            ep.streams = {mid: _Stream.at_rate(hz) for mid, hz in self._default_rates(k).items() if hz > 0}
        self._streams_due_us = 0  # (streams changed: the next tick looks at every one)

    def _builders(self):
        return {
            D.MAVLINK_MSG_ID_SKELETON_LINK_STATE: self._msg_link_state,
            D.MAVLINK_MSG_ID_ODOMETRY: self._msg_odometry,
            D.MAVLINK_MSG_ID_ATTITUDE: self._msg_attitude,
            D.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._msg_local_position,
            D.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._msg_global_position,
            D.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._msg_autopilot_version,
            D.MAVLINK_MSG_ID_SYS_STATUS: self._msg_sys_status,
            D.MAVLINK_MSG_ID_HEARTBEAT: self._msg_heartbeat,
            D.MAVLINK_MSG_ID_SYSTEM_TIME: self._msg_system_time,
            D.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: self._msg_gps_global_origin,
            D.MAVLINK_MSG_ID_SKELETON_EXTERNAL_WRENCH: self._msg_external_wrench,
            D.MAVLINK_MSG_ID_DEBUG_VECT: self._msg_pspm,
        }

    # -- messages out --------------------------------------------------------------------------
    @property
    def time_boot_ms(self) -> int:
        return (self.fc_time_us // 1000) & 0xFFFFFFFF

    def _msg_system_time(self):
        """GPS time (0 until the EKF has its first fix) against boot time, as PX4 sends it; in SITL
        the simulated GPS's clock is :func:`~link_firmware_sim.hil.sitl_gps_time_us` of simulation time."""
        unix_us = sitl_gps_time_us(self.fc_time_us) if self.fw.initialized else 0
        return D.MAVLink_system_time_message(unix_us, self.time_boot_ms)

    def _msg_heartbeat(self):
        base = D.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (D.MAV_MODE_FLAG_SAFETY_ARMED if self.fw.armed else 0)
        status = D.MAV_STATE_ACTIVE if self.fw.armed else D.MAV_STATE_STANDBY
        # A PX4-style autopilot (PX4's parameter encoding, names, ports, failsafes and signing): the
        # stock tools pick the parameter encoding from this field (MAVProxy and QGroundControl decode
        # bytewise only for MAV_AUTOPILOT_PX4, MAVSDK casts only for ArduPilot). Custom mode: PX4's
        # OFFBOARD (main mode 6), what the link flies in: the companion's targets.
        return D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_PX4, base, _PX4_OFFBOARD, status, 3)

    def _msg_sys_status(self):
        sensors = (D.MAV_SYS_STATUS_SENSOR_3D_GYRO | D.MAV_SYS_STATUS_SENSOR_3D_ACCEL | D.MAV_SYS_STATUS_SENSOR_3D_MAG
                   | D.MAV_SYS_STATUS_SENSOR_GPS | D.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
                   | D.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION | D.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
                   | D.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL | D.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS)
        gps_ok = self.fw.initialized and not self.fw.gps_health.fault
        health = sensors if gps_ok else sensors & ~D.MAV_SYS_STATUS_SENSOR_GPS
        health |= D.MAV_SYS_STATUS_GEOFENCE  # no fence, so none breached (a ground station reads 0 as a breach)
        dropped = sum(ep.port.stats.dropped for ep in self.endpoints)
        return D.MAVLink_sys_status_message(sensors, sensors, health, 0, 16200, -1, 100, 0, min(dropped, 65535),
                                            0, 0, 0, 0)

    def _msg_autopilot_version(self):
        return D.MAVLink_autopilot_version_message(
            _CAPABILITIES, _FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0x1209, 0x5A4B, self.system_id,
        )

    def _tick_values(self):
        """(control estimate, state report) of the current tick, computed once for all streams."""
        if self._cache_tick_us != self.fc_time_us:
            self._cache_tick_us = self.fc_time_us
            self._cached = (self.fw.control_estimate(self.fc_time_s), self.fw.state_report())
        return self._cached

    def _estimate(self):
        return self._tick_values()[0]

    def _report(self):
        return self._tick_values()[1]

    def _msg_attitude(self):
        _, _, q = self._estimate()
        roll, pitch, yaw = euler_zyx(quat_enu_flu_to_ned_frd(q))
        w = flu_frd(self._report().omega_b_rad_s)
        return D.MAVLink_attitude_message(self.time_boot_ms, roll, pitch, yaw, *w.tolist())

    def _msg_local_position(self):
        p, v, _ = self._estimate()
        return D.MAVLink_local_position_ned_message(self.time_boot_ms, *enu_ned(p).tolist(), *enu_ned(v).tolist())

    def _msg_global_position(self):
        p, v, q = self._estimate()
        lat, lon, alt = self.origin.to_geodetic(p)
        vn, ve, vd = enu_ned(v).tolist()
        hdg = int(round((math.degrees(euler_zyx(quat_enu_flu_to_ned_frd(q))[2]) % 360.0) * 100))
        return D.MAVLink_global_position_int_message(
            self.time_boot_ms, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            int(round(p[2] * 1000)), int(round(vn * 100)), int(round(ve * 100)), int(round(vd * 100)), hdg,
        )

    def _msg_link_state(self):
        fw = self.fw
        return encode_link_state(self._report(), fw.flags(self.fc_time_s), fw.ekf.resets, fw.correction_seq,
                                 fw.correction_latency_us)

    def _msg_odometry(self):
        """Raw EKF output with covariance (standard messages: what a stock PX4 publishes)."""
        st = self._report()
        return encode_odometry(st, usec(st.time_s), estimator_type=D.MAV_ESTIMATOR_TYPE_NAIVE)

    def _msg_external_wrench(self):
        """The momentum observer's estimate (``None`` without one: the stream sends nothing)."""
        report = self.fw.external_wrench_report()
        return None if report is None else encode_external_wrench(report)

    def _msg_pspm(self):
        """DEBUG_VECT ``PSPM``: x, y the reservoirs E_t, E_r [J], z how far the modulated set position
        lags the operator's [m] (``None`` while PSPM is off: the stream sends nothing)."""
        report = self.fw.pspm_report()
        return None if report is None else D.MAVLink_debug_vect_message(PSPM_DEBUG_NAME, self.fc_time_us, *report)

    def _send_due_streams(self) -> None:
        """Every stream whose time has come; ticks before the earliest one due return at once."""
        t = self.fc_time_us
        if t < self._streams_due_us:
            return
        builders = None
        due = math.inf
        for ep in self.endpoints:
            msgs = []  # one link's messages due on this tick leave together (one UDP datagram)
            for mid, stream in ep.streams.items():
                if t >= stream.next_us:
                    if builders is None:
                        builders = self._builders()
                    msg = builders[mid]()
                    if msg is not None:
                        msgs.append(msg)
                    stream.next_us = max(stream.next_us + stream.interval_us, t)
                due = min(due, stream.next_us)
            if msgs:
                ep.port.send_many(msgs)
        self._streams_due_us = due

    def _heartbeats(self) -> None:
        self._sim_seen = self._sim_seen or self.sim.connected
        now = time.monotonic()
        if now < self._next_heartbeat_wall or not self._sim_seen:
            return
        self._next_heartbeat_wall = now + 1.0
        for ep in self.endpoints:
            ep.port.send_many((self._msg_heartbeat(), self._msg_sys_status()))
        if self._log_stream is not None:
            self._log_stream.flush(self._log_lists())

    # -- simulator link ----------------------------------------------------------------------------
    def _on_hil(self, msg) -> None:
        kind = msg.get_type()
        try:
            if kind == "HIL_SENSOR":
                self._on_hil_sensor(msg)
            elif kind == "HIL_GPS":
                t, p, v = decode_hil_gps(msg, self.origin)
                self._last_gps = (t, p, v)
                if self.fw.initialized:
                    self.fw.on_gps(t, p, v)
                elif self._last_ahrs is not None:
                    self.fw.initialize(t, p, v, self._last_ahrs[1])
            elif kind == "SKELETON_AHRS_REFERENCE":
                t, q = decode_ahrs(msg)
                self._last_ahrs = (t, q)
                if self.fw.initialized:
                    self.fw.on_attitude(t, q)
                elif self._last_gps is not None:
                    _, p, v = self._last_gps
                    self.fw.initialize(t, p, v, q)
        except MessageError as exc:
            self.errors["hil"] += 1
            log.warning("link %d: rejected %s: %s", self.system_id, kind, exc)

    def _on_hil_sensor(self, msg) -> None:
        """One lockstep tick: every HIL_SENSOR gets exactly one HIL_ACTUATOR_CONTROLS answer."""
        self.fc_time_us = int(msg.time_usec)
        self.fc_time_s = self.fc_time_us * 1e-6
        try:
            t, gyro, accel = decode_hil_sensor(msg)
        except MessageError:
            self._answer(np.zeros(8))  # keep the lockstep going; the caller logs the rejection
            raise
        self._on_baro_mag(t, msg)
        if not self.fw.initialized:
            # The EKF starts at the first GPS fix with an attitude reference; until then the
            # rotors stay off, but the simulator still gets its answer.
            self._answer(np.zeros(8))
            return
        self._answer(self.fw.on_imu(t, gyro, accel))
        self._after_tick()

    def _tick_record(self, data: bytes) -> bool:
        """The same-host link's common tick (one HIL_SENSOR record with an IMU sample only, after
        a SKELETON_AHRS_REFERENCE on the attitude reference's ticks; armed, eq. 1's controller, a
        fresh target, no measurement queued) from the packet's bytes to the answer's, in one
        compiled call (:meth:`LinkFirmware.on_hil_record`): the decoding path's numbers
        (``tests/test_fast_paths.py``) without a message object on the way. ``False`` (nothing
        changed) for any other packet: the caller decodes it."""
        rec = np.frombuffer(data, dtype=np.uint8)
        at = sensor_record_at(rec, len(rec))
        if at < 0:
            return False
        t_us = int.from_bytes(data[at + _SENSOR_TIME:at + _SENSOR_TIME + 8], "little")
        t_s = seconds(t_us)
        # (a record it takes is answered through send_packet before the tick's bookkeeping)
        if self.fw.on_hil_record(t_s, rec, self._hil, answered=self.sim.send_packet) is None:
            return False
        self.fc_time_us, self.fc_time_s = t_us, t_s
        self.sim.count("HIL_SENSOR")
        self._ahrs_fused()
        self._after_tick()
        return True

    def _ahrs_fused(self) -> None:
        """The attitude references a compiled tick fused (:meth:`HilBuffers.ahrs`): counted on the
        link, the newest kept, as :meth:`_on_hil` does with one it decodes."""
        accepted, rejected, t_us, q = self._hil.ahrs()
        if accepted + rejected:
            self.sim.count("SKELETON_AHRS_REFERENCE", accepted + rejected)
            self._last_ahrs = (seconds(t_us), q.copy())

    def _poll_loop(self, timeout_s: float) -> bool:
        """The simulator link's quiet ticks in one compiled call (:meth:`LinkFirmware.on_hil_loop`:
        the waits, the packets, the ticks and their answers, with the numbers of :meth:`_tick_record`
        and of the decoders, ``tests/test_simlink.py``), until a tick needs the vehicle's bookkeeping
        (a stream or log row due, an event), a packet is of another kind, a MAVLink port is
        readable, or ``timeout_s``. Over PX4's TCP link the loop reads and writes the MAVLink 2
        frames while the port may hand its stream over (:meth:`MavlinkPort.handover`) and gives
        the sequence numbers back. ``False`` (nothing waited for) when the case does not hold;
        :meth:`poll` then waits as usual."""
        framing = self._hil.framing
        if self._records:
            conn = self.sim.conn
            if conn is None:
                return False
            sim_fd, answered = conn.fileno(), self.sim.send_packet
        else:
            handover = self.sim.handover()
            if handover is None:
                return False
            sim_fd, sender, last_seq = handover
            framing[:7] = (FRAMES_TO_VEHICLE, *sender, last_seq, self.system_id, self.sim.mav.srcComponent,
                           self.sim.mav.seq)
            answered = self._answer_rest
        fds = self._hil.fds
        fds[0] = sim_fd
        for k, ep in enumerate(self.endpoints, 1):
            fds[2 * k] = ep.port.fileno()
        n_fds = 1 + len(self.endpoints)
        if fds[:2 * n_fds:2].min() < 0:
            return False  # (a serial port waiting to reopen)
        due = self._streams_due_us if self.out_dir is None else min(self._streams_due_us, self._log.next_us)
        due = int(min(due, _NEVER_US))  # (no stream at all: inf; the kernel takes an integer)
        frames = not self._records
        res = self.fw.on_hil_loop(self._hil, n_fds=n_fds, timeout_ms=max(int(timeout_s * 1e3), 0),
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
            self.fc_time_us, self.fc_time_s = t_us, seconds(t_us)
            self._after_tick()
        if status == LOOP_PACKET:  # received, not taken: as poll takes a packet
            data = self._hil.buf[:packet].tobytes()
            if self._records:
                self.sim.received(packet)
                self._on_sim_packet(data)
            else:  # (the parser counts the bytes)
                for msg in self.sim.parse(data):
                    self._on_hil(msg)
        return True

    def _answer_rest(self, _answer) -> None:
        """The lockstep loop's answer frame over TCP, the part its send did not take (all of it
        after EAGAIN or an error): the port writes it as it writes a frame it packed."""
        framing = self._hil.framing
        start = max(int(framing[_FRAMING_SENT]), 0)
        self.sim.send_frame(self._hil.frame[start:int(framing[_FRAMING_LENGTH])].tobytes())

    def _on_sim_packet(self, data: bytes) -> None:
        """A same-host link's packet: the record tick (:meth:`_tick_record`), else its messages
        through the decoders."""
        if not self._tick_record(data):
            for msg in self.sim.decode(data):
                self._on_hil(msg)

    def _on_baro_mag(self, t: float, msg) -> None:
        """The HIL_SENSOR's barometer and magnetometer samples (when its bits mark them) to the
        firmware, queued before this tick's IMU sample; an invalid one is dropped and counted
        (``errors["hil_baro"]`` / ``["hil_mag"]``), the tick goes on."""
        sample = decode_hil_baro_mag(msg)
        for name in sample.rejected:
            count = self.errors[f"hil_{name}"] = self.errors[f"hil_{name}"] + 1
            if math.log10(count).is_integer():  # the 1st, 10th, 100th, ...: no flood at 50 Hz
                log.warning("link %d: dropped an invalid HIL_SENSOR %s sample (%d so far)", self.system_id, name,
                            count)
        if sample.baro_alt_m is not None:
            self.fw.on_baro(t, sample.baro_alt_m - self.origin.alt_m)  # height above the origin
        if sample.mag_flu_gauss is not None:
            self.fw.on_mag(t, sample.mag_flu_gauss)

    def _answer(self, thrust: np.ndarray) -> None:
        self.sim.send(encode_actuators(self.fc_time_s, thrust, self.thrust_max_n, self.fw.armed))

    def _after_tick(self) -> None:
        if self.fw.events:
            self._report_events()
        self._send_due_streams()
        if self.out_dir is not None and self.fc_time_us >= self._log.next_us:
            interval = self._log.interval_us  # the next grid point (a vehicle started in flight skips ahead)
            self._log.next_us = (self.fc_time_us // interval + 1) * interval
            self._log_row()

    def _report_events(self) -> None:
        """The firmware's GPS health and thrust-limit transitions, as STATUSTEXT to every link and in
        the log."""
        severity = {"fault": D.MAV_SEVERITY_WARNING, "reset": D.MAV_SEVERITY_CRITICAL, "recovered": D.MAV_SEVERITY_INFO}
        for ev in self.fw.events:
            log.warning("link %d at %.2f s: %s", self.system_id, self.fc_time_s, ev.text)
            for ep in self.endpoints:
                self._status(ep, severity[ev.kind], ev.text)
        self.fw.events.clear()

    def _log_row(self) -> None:
        fw = self.fw
        estimate = fw.control_estimate(self.fc_time_s)
        p, _, q = estimate
        target = fw.active_target(self.fc_time_s, estimate)
        r = self._rows
        r["t"].append(self.fc_time_s)
        r["p_ekf"].append(fw.ekf.p_w_m)
        r["q_ekf"].append(fw.ekf.q_wxyz)
        r["p_ctrl"].append(p)
        r["q_ctrl"].append(q)
        r["p_target"].append(target.p_w_m)
        r["q_target"].append(target.q_wxyz)
        r["pspm"].append(fw.pspm_report() or (math.nan,) * 3)

    # -- MAVLink in ------------------------------------------------------------------------------
    def _for_us(self, msg) -> bool:
        target = getattr(msg, "target_system", 0)
        return target in (0, self.system_id)

    def _on_mavlink(self, ep: _Endpoint, msg) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            return
        if not self._for_us(msg):
            ep.port.stats.ignored += 1
            return
        try:
            if kind == "SKELETON_CORRECTION":
                self._on_correction(decode_correction(msg, self.instance))
            elif kind in ("ODOMETRY", "VISION_POSITION_ESTIMATE"):
                pose = decode_external_pose(msg)  # standard-messages mode: the companion's corrected pose
                self.fw.on_external_pose(self.fc_time_s, pose.p_w_m, pose.v_w_m_s, pose.q_wxyz)
            elif kind == "SET_POSITION_TARGET_LOCAL_NED":
                self._on_position_target(msg)
            elif kind == "SET_ATTITUDE_TARGET":
                self._on_attitude_target(msg)
            elif kind == "SKELETON_TARGET_FEEDFORWARD":
                self._ff_target = (msg.time_boot_ms, *decode_target_feedforward(msg))
                if msg.time_boot_ms == self._pos_target_ms:  # after its position target: applies now
                    self._target_due = True
            elif kind in ("COMMAND_LONG", "COMMAND_INT"):
                self._on_command(ep, msg)
            elif kind.startswith("PARAM_"):
                self._on_param(ep, msg)
            elif kind == "SET_GPS_GLOBAL_ORIGIN":
                self._on_set_origin(ep, msg)
            elif kind == "SETUP_SIGNING":
                self._on_setup_signing(ep, msg)
            elif kind == "FILE_TRANSFER_PROTOCOL":
                self._on_ftp(ep, msg)
        except MessageError as exc:
            self.errors["mavlink"] += 1
            log.warning("link %d: rejected %s: %s", self.system_id, kind, exc)

    def _on_correction(self, corr: Correction | None) -> None:
        try:
            self.fw.on_correction(self.fc_time_s, corr)
        except CorrectionRejected as exc:
            self.errors["correction_rejected"] += 1
            log.warning("link %d: %s (SKL_CORR_MAX*; rejected so far: %d)", self.system_id, exc,
                        self.errors["correction_rejected"])
            self._status_all(D.MAV_SEVERITY_WARNING, "Correction rejected: out of bounds", every_s=5.0)

    # -- operator messages -------------------------------------------------------------------
    def _status(self, ep: _Endpoint, severity: int, text: str) -> None:
        """A STATUSTEXT to one link (at most 50 characters, as PX4 sends them)."""
        ep.port.send(D.MAVLink_statustext_message(severity, text[:50].encode()))

    def _status_all(self, severity: int, text: str, every_s: float = 0.0) -> None:
        """A STATUSTEXT to every link, at most once per ``every_s`` for the same text."""
        now = time.monotonic()
        if now < self._next_status_wall.get(text, 0.0):
            return
        self._next_status_wall[text] = now + every_s
        for ep in self.endpoints:
            self._status(ep, severity, text)

    def _on_set_origin(self, ep: _Endpoint, msg) -> None:
        """SET_GPS_GLOBAL_ORIGIN: the shared local origin (refused while armed: the frame would jump)."""
        if msg.target_system not in (0, self.system_id):
            return
        if self.fw.armed:
            self._status(ep, D.MAV_SEVERITY_WARNING, "Origin not changed: armed")
        else:
            try:
                origin = GeoOrigin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            except ValueError as exc:
                self._status(ep, D.MAV_SEVERITY_WARNING, f"Origin refused: {exc}")
            else:
                self.params.set_origin(origin)
                self.origin = origin
                log.info("link %d: origin set to %.7f, %.7f, %.2f m", self.system_id, origin.lat_deg,
                         origin.lon_deg, origin.alt_m)
        ep.port.send(self._msg_gps_global_origin())

    def _msg_gps_global_origin(self):
        o = self.origin
        return D.MAVLink_gps_global_origin_message(int(round(o.lat_deg * 1e7)), int(round(o.lon_deg * 1e7)),
                                                   int(round(o.alt_m * 1e3)), self.fc_time_us)

    def _on_setup_signing(self, ep: _Endpoint, msg) -> None:
        """SETUP_SIGNING: a new key for every link, accepted only on a trusted link (PX4: USB only).

        An all-zero key with timestamp 0 turns signing off (MAVLink semantics). The key is
        written to the configured key file (hex), so it survives a restart."""
        if msg.target_system not in (0, self.system_id):
            return
        if not ep.trusted:
            self.errors["setup_signing_refused"] += 1
            log.warning("link %d: SETUP_SIGNING on the untrusted %s link refused", self.system_id, ep.name)
            self._status(ep, D.MAV_SEVERITY_WARNING, "Signing setup refused: untrusted link")
            return
        key = bytes(msg.secret_key)
        if len(key) != KEY_LEN:
            raise MessageError(f"SETUP_SIGNING key of {len(key)} bytes")
        disable = not any(key) and msg.initial_timestamp == 0
        for other in self.endpoints:
            mode = "off" if disable else (self.signing.link_mode(other.name) if self.signing.active else "required")
            other.port.set_signing(mode, None if disable else key)
            if not disable:
                other.port.mav.signing.timestamp = max(other.port.mav.signing.timestamp, int(msg.initial_timestamp))
        if self.key_path is not None and not disable:
            write_key_file(self.key_path, key.hex(), overwrite=True)
        log.warning("link %d: signing %s over the %s link", self.system_id, "disabled" if disable else "key replaced",
                    ep.name)
        self._status_all(D.MAV_SEVERITY_NOTICE, "Signing disabled" if disable else "Signing key updated")

    def _on_ftp(self, ep: _Endpoint, msg) -> None:
        """MAVLink FTP: no file system here. Session resets are acknowledged, everything else is
        answered at once with a NAK (opening a file: FileNotFound, so a ground station that tries
        ``@PARAM/param.pck`` first falls back to PARAM_REQUEST_LIST without waiting)."""
        if msg.target_system not in (0, self.system_id):
            return
        payload = bytes(msg.payload)
        if len(payload) < 12:
            raise MessageError("FILE_TRANSFER_PROTOCOL payload shorter than its header")
        seq, session, opcode = struct.unpack_from("<HBB", payload)
        if opcode in (_FTP_ACK, _FTP_NAK):
            return
        if opcode in (_FTP_TERMINATE, _FTP_RESET):
            reply, data = _FTP_ACK, b""
        elif opcode in (_FTP_OPEN_FILE_RO, _FTP_LIST_DIRECTORY):
            reply, data = _FTP_NAK, bytes([_FTP_ERR_FILE_NOT_FOUND])
        else:
            reply, data = _FTP_NAK, bytes([_FTP_ERR_UNKNOWN_COMMAND])
        header = struct.pack("<HBBBBBBI", (seq + 1) & 0xFFFF, session, reply, len(data), opcode, 0, 0, 0)
        body = (header + data).ljust(251, b"\0")
        ep.port.send(D.MAVLink_file_transfer_protocol_message(0, msg.get_srcSystem(), msg.get_srcComponent(),
                                                              list(body)))

    def _on_position_target(self, msg) -> None:
        self._pos_target = decode_position_target(msg)
        self._pos_target_ms = msg.time_boot_ms
        self._target_due = True

    def _on_attitude_target(self, msg) -> None:
        self._att_target = decode_attitude_target(msg)
        self._target_due = True

    def _apply_target(self) -> None:
        """:meth:`_update_target` after a read; a target the firmware refuses is counted as a bad
        message (``errors["mavlink"]``), as it was when each message applied its own."""
        try:
            self._update_target()
        except MessageError as exc:
            self.errors["mavlink"] += 1
            log.warning("link %d: rejected a target: %s", self.system_id, exc)

    def _update_target(self) -> None:
        """The firmware's target from the newest position, attitude and feed-forward messages: once
        per read of a link (:meth:`poll`), after all its messages, so that one target sent as its
        three messages in one datagram is one target (under PSPM, one set pose), not three partial
        ones at the same flight-controller time."""
        self._target_due = False
        if self._pos_target is None and self._att_target is None:
            return
        if self.fw.initialized:
            p_now, _, q_now = self.fw.control_estimate(self.fc_time_s)
        else:
            p_now, q_now = np.zeros(3), np.array([1.0, 0, 0, 0])
        p, v, a = self._pos_target if self._pos_target is not None else (p_now, np.zeros(3), np.zeros(3))
        q, w = self._att_target if self._att_target is not None else (q_now, np.zeros(3))
        # The rest of the target (angular acceleration, whole-chain feed-forward) comes in its own
        # message stamped with its position target's time_boot_ms: it applies to that position
        # target and, while the next one's is still to come or was lost on the wire, to the
        # position targets of the next FEEDFORWARD_HOLD_MS (dropping it for a lost message would
        # drop, for one target period, the weight a link carries for a neighbour without rotors).
        # One that comes before its position target waits for it (the companion sends it first).
        ff = self._ff_target
        if ff is not None and ff[0] == self._pos_target_ms:
            self._ff_applied = ff
        ff = self._ff_applied
        held = ff is not None and (self._pos_target_ms - ff[0]) & 0xFFFFFFFF <= FEEDFORWARD_HOLD_MS
        wd, f_ff, tau_ff = ff[1:] if held else (np.zeros(3), np.zeros(3), np.zeros(3))
        # The target rate is in the desired body frame (eq. 1): FLU rates of the target attitude.
        self.fw.set_target(self.fc_time_s, PoseTarget(p, q, v, a, w, wd, f_ff, tau_ff))

    def _ack(self, ep: _Endpoint, msg, result: int) -> None:
        ep.port.send(D.MAVLink_command_ack_message(msg.command, result, 255, 0, msg.get_srcSystem(),
                                                   msg.get_srcComponent()))

    def _on_command(self, ep: _Endpoint, msg) -> None:
        cmd = msg.command
        if cmd == D.MAV_CMD_COMPONENT_ARM_DISARM:
            if msg.param1 >= 0.5:
                result = D.MAV_RESULT_ACCEPTED if self.fw.arm(self.fc_time_s) else D.MAV_RESULT_TEMPORARILY_REJECTED
            elif self.fw.armed and not self.fw.landed(self.fc_time_s) and int(round(msg.param2)) != FORCE_DISARM:
                # PX4: disarming in flight needs the force value (the link would fall)
                self.errors["disarm_refused"] += 1
                log.warning("link %d: disarm refused in flight (param2 %g, force is %d)", self.system_id,
                            msg.param2, FORCE_DISARM)
                self._status(ep, D.MAV_SEVERITY_CRITICAL, f"Disarm refused: in flight (force {FORCE_DISARM})")
                result = D.MAV_RESULT_DENIED
            else:
                self.fw.disarm()
                result = D.MAV_RESULT_ACCEPTED
            self._ack(ep, msg, result)
        elif cmd == D.MAV_CMD_SET_MESSAGE_INTERVAL:
            mid, interval_us = int(msg.param1), msg.param2
            builders = self._builders()
            if mid not in builders or mid in (D.MAVLINK_MSG_ID_HEARTBEAT, D.MAVLINK_MSG_ID_AUTOPILOT_VERSION):
                self._ack(ep, msg, D.MAV_RESULT_UNSUPPORTED)
                return
            if interval_us == 0:  # the default rate (MAVLink semantics)
                hz = self._default_rates(self.endpoints.index(ep)).get(mid, 0.0)
                interval_us = 1e6 / hz if hz > 0 else -1
            if interval_us < 0:
                ep.streams.pop(mid, None)
            else:
                ep.streams[mid] = _Stream.every(int(round(interval_us)), self.fc_time_us)
            self._streams_due_us = 0
            self._ack(ep, msg, D.MAV_RESULT_ACCEPTED)
        elif cmd in (D.MAV_CMD_REQUEST_MESSAGE, D.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            mid = int(msg.param1) if cmd == D.MAV_CMD_REQUEST_MESSAGE else D.MAVLINK_MSG_ID_AUTOPILOT_VERSION
            builder = self._builders().get(mid)
            if builder is None or (mid != D.MAVLINK_MSG_ID_AUTOPILOT_VERSION and not self.fw.initialized):
                self._ack(ep, msg, D.MAV_RESULT_UNSUPPORTED if builder is None else D.MAV_RESULT_TEMPORARILY_REJECTED)
                return
            out = builder()
            self._ack(ep, msg, D.MAV_RESULT_ACCEPTED if out is not None else D.MAV_RESULT_DENIED)
            if out is not None:
                ep.port.send(out)
        elif cmd == D.MAV_CMD_SKELETON_SET_CONTACT:
            self._on_contact_command(ep, msg)
        else:
            self._ack(ep, msg, D.MAV_RESULT_UNSUPPORTED)

    def _on_contact_command(self, ep: _Endpoint, msg) -> None:
        """MAV_CMD_SKELETON_SET_CONTACT: the hybrid controller's contact (or its release), validated;
        refused with MAV_RESULT_DENIED and a STATUSTEXT saying why."""
        if msg.get_type() != "COMMAND_LONG":
            reason = "Contact refused: send it as COMMAND_LONG"
        elif self.fw.config.controller != "hybrid":
            reason = f"Contact refused: controller {self.fw.config.controller} (SKL_CTRL 2)"
        else:
            try:
                contact = decode_contact_command(msg)
                self.fw.set_contact(self.fc_time_s, contact)
            except ValueError as exc:  # MessageError too
                reason = f"Contact refused: {exc}"
            else:
                log.info("link %d: contact %s", self.system_id, "released" if contact is None else
                         f"{contact.force_n:g} N along {np.round(contact.normal_w, 3).tolist()} (world)")
                self._ack(ep, msg, D.MAV_RESULT_ACCEPTED)
                return
        log.warning("link %d: %s", self.system_id, reason)
        self._status(ep, D.MAV_SEVERITY_WARNING, reason)
        self._ack(ep, msg, D.MAV_RESULT_DENIED)

    def _param_value(self, name: str):
        """PARAM_VALUE, PX4's bytewise encoding: an integer's 32 bits in the float field."""
        spec = self.params.spec(name)
        value = self.params.values[name]
        if spec.kind == "int":
            raw, ptype = _int_as_float_bits(int(value)), D.MAV_PARAM_TYPE_INT32
        else:
            raw, ptype = float(value), D.MAV_PARAM_TYPE_REAL32
        return D.MAVLink_param_value_message(name.encode(), raw, ptype, len(self.params.names),
                                             self.params.names.index(name))

    def _on_param(self, ep: _Endpoint, msg) -> None:
        kind = msg.get_type()
        names = self.params.names
        if kind == "PARAM_REQUEST_LIST":
            for name in names:
                ep.port.send(self._param_value(name))
            return
        if kind == "PARAM_REQUEST_READ":
            if msg.param_index >= 0:
                if msg.param_index < len(names):
                    ep.port.send(self._param_value(names[msg.param_index]))
                return
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\x00")
            if name in self.params.values:
                ep.port.send(self._param_value(name))
            return
        if kind == "PARAM_SET":
            if msg.target_system not in (0, self.system_id):
                return
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\x00")
            spec = self.params.spec(name)
            if spec is None:
                log.warning("link %d: PARAM_SET of unknown parameter %r", self.system_id, name)
                self._status(ep, D.MAV_SEVERITY_ERROR, f"Param {name[:16]} unknown")
                return
            value = msg.param_value
            if spec.kind == "int":
                value = _decode_int_param(value, spec)
            try:
                self.params.set(name, value)
            except ValueError as exc:
                log.warning("link %d: PARAM_SET refused: %s", self.system_id, exc)
                self._status(ep, D.MAV_SEVERITY_ERROR, _refusal_text(name, spec, value, str(exc)))
            else:
                self._apply_params(name)
            ep.port.send(self._param_value(name))  # the current value either way (PX4 behaviour)

    def _apply_params(self, name: str) -> None:
        self.fw.reconfigure(self.params.firmware_config())
        if name in ("SKL_STATE_HZ", "SKL_ODOM_HZ", "SKL_WRENCH_HZ"):
            defaults = self._default_rates(0)
            streams = self.endpoints[0].streams
            for mid in (D.MAVLINK_MSG_ID_SKELETON_LINK_STATE, D.MAVLINK_MSG_ID_ODOMETRY,
                        D.MAVLINK_MSG_ID_SKELETON_EXTERNAL_WRENCH):
                hz = defaults[mid]
                if hz > 0:
                    streams[mid] = _Stream.at_rate(hz, self.fc_time_us)
                else:
                    streams.pop(mid, None)
            self._streams_due_us = 0

    # -- main loop -----------------------------------------------------------------------------
    def stop(self, *_args) -> None:
        self._stop = True

    def poll(self, timeout_s: float) -> None:
        """Wait for input at most ``timeout_s`` and handle everything that arrived."""
        if self._poll_loop(timeout_s):
            timeout_s = 0.0  # the loop waited: what it left (a MAVLink port, a packet) is handled below
        ready = wait_readable([self.sim] + [ep.port for ep in self.endpoints], timeout_s)
        if self.sim in ready or not self.sim.connected:  # (a listener accepts on readable too)
            if self._records:
                data = self.sim.recv()
                if data is not None:
                    self._on_sim_packet(data)
            else:
                for msg in self.sim.read():
                    self._on_hil(msg)
        for ep in self.endpoints:
            if ep.port in ready:
                for msg in ep.port.read():
                    self._on_mavlink(ep, msg)
                if self._target_due:
                    self._apply_target()
        self._heartbeats()

    def run(self) -> None:
        signal.signal(signal.SIGTERM, self.stop)
        signal.signal(signal.SIGINT, self.stop)
        log.info("link %d up (sysid %d): sim %s, onboard %s", self.instance + 1, self.system_id, self.sim.url,
                 self.endpoints[0].port.url)
        try:
            while not self._stop:
                self.poll(0.2)
        finally:
            self.close()

    def _log_lists(self) -> dict[str, list]:
        return {**self._rows, "correction_latency": self.fw.latency_log}

    def flight_log(self) -> dict[str, np.ndarray]:
        out = {k: np.asarray(v) for k, v in self._rows.items()}
        out["correction_latency"] = np.asarray(self.fw.latency_log).reshape(-1, 2)
        return out

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self._log_stream.flush(self._log_lists())
            self._log_stream.close()
            np.savez_compressed(self.out_dir / f"link{self.instance + 1}_firmware.npz", **self.flight_log())
            stats = {ep.port.url: vars(ep.port.stats) for ep in self.endpoints}
            stats[self.sim.url] = vars(self.sim.stats)
            stats["errors"] = self.errors
            stats["gps"] = self.fw.gps_health.report(self.fc_time_s)
            stats["thrust_limit"] = self.fw.thrust_limit.report()
            if self.fw.ekf is not None:  # measurements fused / gated per kind (barometer, magnetometer too)
                stats["ekf"] = {"accepted": self.fw.ekf.accepted, "rejected": self.fw.ekf.rejected}
            (self.out_dir / f"link{self.instance + 1}_ports.json").write_text(json.dumps(stats, indent=1, default=str))
        self.sim.close()
        for ep in self.endpoints:
            ep.port.close()



def _refusal_text(name: str, spec, value: float, reason: str) -> str:
    """The STATUSTEXT of a refused PARAM_SET (50 characters, as PX4 words them)."""
    if spec.read_only:
        return f"Param {name} is read-only"
    if not (spec.minimum <= value <= spec.maximum):
        return f"Param {name}: {value:g} out of [{spec.minimum:g}, {spec.maximum:g}]"
    return f"Param {name} refused: {reason.split(': ', 1)[-1]}"[:50]


def _int_as_float_bits(value: int) -> float:
    return struct.unpack("<f", struct.pack("<i", value))[0]


def _decode_int_param(raw: float, spec) -> float:
    """An integer PARAM_SET value: PX4's bytewise encoding (what this vehicle declares), or, when
    that is out of the parameter's range and the float is a whole number in it, a C-cast value (a
    client that did not know the parameter's type, e.g. MAVProxy before its first download). The
    two never both fit: integer ranges here stay within 2**24, where bytewise values are denormal."""
    bits = struct.unpack("<i", struct.pack("<f", raw))[0]
    if spec.minimum <= bits <= spec.maximum:
        return bits
    if math.isfinite(raw) and abs(raw) >= 1.1754944e-38:
        return raw  # a normal float: sent C-cast (the range and integer checks report what is wrong)
    return bits

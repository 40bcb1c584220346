"""A simulated Pixhawk as a MAVLink 2 vehicle: one OS process per link (``python -m
link_firmware_sim``).

:class:`Vehicle` puts one link's :class:`~link_firmware_sim.firmware.LinkFirmware` behind its
ports (:mod:`.links`: the simulator link, the onboard and the GCS links) and runs its main loop:
it waits on every port, hands the simulator's ticks to :mod:`.lockstep` (which sets the
flight-controller time) and each MAVLink message to the service that owns it:

* :mod:`.targets`: SET_POSITION_TARGET_LOCAL_NED, SET_ATTITUDE_TARGET, SKELETON_TARGET_FEEDFORWARD;
* here: SKELETON_CORRECTION, and ODOMETRY / VISION_POSITION_ESTIMATE as the external-vision
  correction (standard-messages mode);
* :mod:`.commands`: COMMAND_LONG / COMMAND_INT; :mod:`.param_protocol`: PARAM_*;
  :mod:`.origin`: SET_GPS_GLOBAL_ORIGIN; :mod:`.signing_setup`: SETUP_SIGNING; :mod:`.ftp`:
  FILE_TRANSFER_PROTOCOL; :mod:`.home`: the home position (MAV_CMD_DO_SET_HOME, arming).

After each tick it reports the firmware's events as STATUSTEXT, sends the telemetry streams that
are due (:mod:`.streams`) and records the flight log (:mod:`.recorder`); HEARTBEAT and
SYS_STATUS go out once a second of wall time. MAVLink services are implemented with pymavlink
(see the README for why not MAVSDK's server components).

Failsafes are the firmware's: a correction older than ``SKL_CORR_STALE`` fades to the raw EKF, a
target older than ``COM_OF_LOSS_T`` becomes a position hold.
"""

from __future__ import annotations

import json
import logging
import signal
import time
from pathlib import Path

import numpy as np

from companion.mavlink.codec import MessageError, decode_correction
from companion.mavlink.dialect import load_dialect
from companion.mavlink.signing import SigningConfig
from companion.mavlink.standard import ExternalPose, decode_external_pose
from companion.mavlink.transport import wait_readable
from companion.messages import Correction

from ..config import VehicleSetup
from ..events import SEVERITY
from ..firmware import CorrectionRejected, LinkFirmware
from .commands import on_command
from .failures import FailureInjector, SeveredTransport
from .ftp import on_ftp
from .home import Home
from .links import Endpoint, VehiclePorts, open_endpoints, statustext
from .lockstep import Lockstep
from .origin import on_set_origin
from .param_protocol import apply_param, on_param
from .params import ParamTable
from .recorder import FlightRecorder
from .signing_setup import on_setup_signing
from .streams.schedule import Streams
from .streams.system import heartbeat, sys_status
from .targets import TargetMessages

__all__ = ["Vehicle"]

log = logging.getLogger(__name__)
D = load_dialect()

#: STATUSTEXT severity of each kind of firmware event

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
        self.fc_time_s = 0.0
        self.fc_time_us = 0
        self.errors = {"hil": 0, "mavlink": 0, "correction_rejected": 0, "disarm_refused": 0, "setup_signing_refused": 0,
                       "hil_baro": 0, "hil_mag": 0}
        #: failures injected by MAV_CMD_INJECT_FAILURE, applied to the samples the lockstep takes in
        self.failures = FailureInjector(seed=instance)
        self.lockstep = Lockstep(self, ports.sim, thrust_max_n)
        self.sim = self.lockstep.sim
        try:
            self.endpoints: list[Endpoint] = open_endpoints(ports, self.system_id, self.signing, key, out_dir)
        except Exception:
            self.sim.close()
            raise
        self.streams = Streams(self)
        self.streams.set_defaults()
        self.home = Home()
        self.targets = TargetMessages(self)
        self.recorder = FlightRecorder(firmware, self.system_id, out_dir, log_rate_hz)
        self._next_heartbeat_wall = 0.0
        # Like PX4's SITL, the firmware is silent on MAVLink until the simulator has connected: a
        # process started ahead of its "power on" (a scripted reboot) is not seen before it.
        self._sim_seen = False
        self._next_status_wall: dict[str, float] = {}
        self._stop = False
        self._closed = False

    @classmethod
    def from_setup(cls, setup: VehicleSetup, instance: int, ports: VehiclePorts, out_dir: Path | None = None,
                   params_path: Path | None = None, log_rate_hz: float = 50.0, key: bytes | None = None) -> Vehicle:
        """Link ``instance`` of a vehicle config: its firmware, its parameter table (persisted in
        ``params_path``, by default ``out_dir/link<i+1>_params.json``), the signing of its links with
        ``key`` (replaced by SETUP_SIGNING in the config's key file)."""
        if params_path is None and out_dir is not None:
            params_path = out_dir / f"link{instance + 1}_params.json"
        firmware = setup.firmware_for(instance)
        params = ParamTable(instance + 1, setup.firmware, setup.origin, setup.stream_rates(), params_path)
        key_path = Path(setup.signing.key_file) if setup.signing.key_file else None
        return cls(instance, firmware, params, ports, out_dir, log_rate_hz, setup.rotors.thrust_max_n,
                   signing=setup.signing, key=key, key_path=key_path)

    @property
    def time_boot_ms(self) -> int:
        return (self.fc_time_us // 1000) & 0xFFFFFFFF

    def set_param(self, name: str, value) -> None:
        """Parameter ``name`` set as PARAM_SET sets it: validated (``ValueError``, nothing changed),
        persisted and applied at once."""
        self.params.set(name, value)
        apply_param(self, name)

    # -- main loop -----------------------------------------------------------------------------
    def stop(self, *_args) -> None:
        self._stop = True

    def poll(self, timeout_s: float) -> None:
        """Wait for input at most ``timeout_s`` and handle everything that arrived."""
        looped = self.lockstep.run_loop(timeout_s)
        # the loop waited and handled the simulator link: the MAVLink ports are handled below, the
        # simulator's next packet by the next call's loop (compiled) rather than the decoders
        ports = [ep.port for ep in self.endpoints]
        ready = wait_readable(ports if looped else [self.sim] + ports, 0.0 if looped else timeout_s)
        if not looped and (self.sim in ready or not self.sim.connected):  # (a listener accepts on readable too)
            self.lockstep.on_readable()
        for ep in self.endpoints:
            if ep.port in ready:
                for msg in ep.port.read():
                    self._on_mavlink(ep, msg)
                if self.targets.due:
                    self.targets.apply()
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

    def apply_link_failure(self) -> None:
        """The onboard link severed while the MAVLink signal failure is on
        (:class:`~.failures.SeveredTransport` under its port), whole again once it is cleared."""
        ep = next((e for e in self.endpoints if e.name == "onboard"), None)
        if ep is None:
            return
        severed = isinstance(ep.port.transport, SeveredTransport)
        if self.failures.link_off and not severed:
            ep.port.transport = SeveredTransport(ep.port.transport, self.failures.changed)
        elif not self.failures.link_off and severed:
            ep.port.transport = ep.port.transport.inner

    def after_tick(self) -> None:
        """A tick's bookkeeping: on a stream or log row, the IMU watched; the firmware's events,
        the streams due, the flight log's row."""
        if self.fc_time_us >= min(self.streams.due_us, self.recorder.due_us):
            self.fw.watch_imu(self.fc_time_s)
            self.home.on_tick(self)
        if self.fw.events:
            self._report_events()
        self.streams.send_due()
        self.recorder.after_tick(self.fc_time_us, self.fc_time_s)

    def _heartbeats(self) -> None:
        self._sim_seen = self._sim_seen or self.sim.connected
        now = time.monotonic()
        if now < self._next_heartbeat_wall or not self._sim_seen:
            return
        self._next_heartbeat_wall = now + 1.0
        for ep in self.endpoints:
            ep.port.send_many((heartbeat(self), sys_status(self)))
        self.recorder.flush()

    # -- operator messages -----------------------------------------------------------------------
    def _report_events(self) -> None:
        """The firmware's GPS health and thrust-limit transitions, as STATUSTEXT to every link and in
        the log."""
        for ev in self.fw.events:
            log.warning("link %d at %.2f s: %s", self.system_id, self.fc_time_s, ev.text)
            self.recorder.statustext(self.fc_time_s, SEVERITY[ev.kind], ev.text)
            for ep in self.endpoints:
                statustext(ep, SEVERITY[ev.kind], ev.text)
        self.fw.events.clear()

    def status_all(self, severity: int, text: str, every_s: float = 0.0) -> None:
        """A STATUSTEXT to every link, at most once per ``every_s`` for the same text."""
        now = time.monotonic()
        if now < self._next_status_wall.get(text, 0.0):
            return
        self._next_status_wall[text] = now + every_s
        for ep in self.endpoints:
            statustext(ep, severity, text)

    # -- MAVLink in ------------------------------------------------------------------------------
    def _on_mavlink(self, ep: Endpoint, msg) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            return
        if getattr(msg, "target_system", 0) not in (0, self.system_id):
            ep.port.stats.ignored += 1
            return
        try:
            if kind == "SKELETON_CORRECTION":
                self._on_correction(decode_correction(msg, self.instance))
            elif kind in ("ODOMETRY", "VISION_POSITION_ESTIMATE"):
                pose = decode_external_pose(msg)  # standard-messages mode: the companion's corrected pose
                self._on_external_pose(pose)
            elif kind == "SET_POSITION_TARGET_LOCAL_NED":
                self.targets.on_position_target(msg)
            elif kind == "SET_ATTITUDE_TARGET":
                self.targets.on_attitude_target(msg)
            elif kind == "SKELETON_TARGET_FEEDFORWARD":
                self.targets.on_feedforward(msg)
            elif kind in ("COMMAND_LONG", "COMMAND_INT"):
                on_command(self, ep, msg)
            elif kind.startswith("PARAM_"):
                on_param(self, ep, msg)
            elif kind == "SET_GPS_GLOBAL_ORIGIN":
                on_set_origin(self, ep, msg)
            elif kind == "SETUP_SIGNING":
                on_setup_signing(self, ep, msg)
            elif kind == "FILE_TRANSFER_PROTOCOL":
                on_ftp(self, ep, msg)
        except MessageError as exc:
            self.errors["mavlink"] += 1
            log.warning("link %d: rejected %s: %s", self.system_id, kind, exc)

    def _on_correction(self, corr: Correction | None) -> None:
        try:
            self.fw.on_correction(self.fc_time_s, corr)
        except CorrectionRejected as exc:
            self._correction_rejected(exc)

    def _on_external_pose(self, pose: ExternalPose) -> None:
        """An external-vision pose as the correction (the firmware's bounds apply as to a
        SKELETON_CORRECTION: one out of them is rejected, counted and reported)."""
        try:
            self.fw.on_external_pose(self.fc_time_s, pose.p_w_m, pose.v_w_m_s, pose.q_wxyz)
        except CorrectionRejected as exc:
            self._correction_rejected(exc)

    def _correction_rejected(self, exc: CorrectionRejected) -> None:
        self.errors["correction_rejected"] += 1
        log.warning("link %d: %s (SKL_CORR_MAX*; rejected so far: %d)", self.system_id, exc,
                    self.errors["correction_rejected"])
        self.status_all(D.MAV_SEVERITY_WARNING, "Correction rejected: out of bounds", every_s=5.0)

    # -- the end ---------------------------------------------------------------------------------
    def flight_log(self) -> dict[str, np.ndarray]:
        return self.recorder.arrays()

    def close(self) -> None:
        """The flight log saved and the link's counters written (``link<i>_ports.json``: every
        port's, the errors, the GPS health, the thrust limit, the gyro and the accelerometer, the
        wrenches refused, the injected failures, the EKF's fused and gated measurements), then
        every port closed."""
        if self._closed:
            return
        self._closed = True
        if self.out_dir is not None:
            self.recorder.save()
            stats = {ep.port.url: vars(ep.port.stats) for ep in self.endpoints}
            stats[self.sim.url] = vars(self.sim.stats)
            stats["errors"] = self.errors
            stats["gps"] = self.fw.gps_report(self.fc_time_s)
            stats["thrust_limit"] = self.fw.thrust_limit.report()
            stats.update(self.fw.imu_health.report(self.fc_time_s))  # "gyro", "accel"
            stats["wrench"] = self.fw.wrench_guard.report()
            stats["failures"] = self.failures.report()
            if self.fw.ekf is not None:  # measurements fused / gated per kind (barometer, magnetometer too)
                stats["ekf"] = {"accepted": self.fw.ekf.accepted, "rejected": self.fw.ekf.rejected}
            (self.out_dir / f"link{self.system_id}_ports.json").write_text(json.dumps(stats, indent=1, default=str))
        self.sim.close()
        for ep in self.endpoints:
            ep.port.close()

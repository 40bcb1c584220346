"""The fleet's harness: the plant in lockstep with vehicles behind simulator links.

At every firmware tick the harness sends HIL_GPS / SKELETON_AHRS_REFERENCE (when due) and
HIL_SENSOR to every vehicle, waits until every vehicle has answered with HIL_ACTUATOR_CONTROLS for
that time, then advances the physics; ``speed`` paces it at that many times real time (0: as fast
as the lockstep goes).

The truth is logged at the log rate. With a ``truth_stream`` file the rows go to it every
simulated second (:mod:`companion.logstream`) and only the newest :data:`TRUTH_KEEP_S` stay in
memory (what the live view shows), so a long flight's memory stays flat; :meth:`FleetHarness.truth_log`
reads the whole log back.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from companion.estimation.so3 import quat_to_rotmat
from companion.logstream import LogStream
from companion.mavlink.codec import MessageError, usec
from companion.mavlink.transport import wait_readable
from companion.skeleton.kinematics import tension
from link_firmware_sim.allocation import Allocator
from link_firmware_sim.controllers import weight_wrench
from link_firmware_sim.vehicle.hil import (ROTORS_PER_LINK, encode_ahrs, encode_hil_gps, encode_hil_sensors, nonfinite_rows,
                                   thrusts_from_controls)
from link_firmware_sim.vehicle.simlink import hil_sensor_records, open_sim_port
from sitl.plant.plant import Plant
from sitl.plant.schedule import Schedule
from sitl.scenario import Scenario
from sitl.watch import announce

from .layout import LOCKSTEP_ENDED, LOCKSTEP_STARTED, FleetError
from .processes import STARTUP_TIMEOUT_S

__all__ = ["FleetHarness", "ANSWER_TIMEOUT_S", "TRUTH_KEEP_S", "complete_rows"]

log = logging.getLogger(__name__)

ANSWER_TIMEOUT_S = 10.0
#: while waiting for the vehicles' answers, :attr:`FleetHarness.on_wait` runs at least this often [wall s]
WAIT_CHECK_S = 0.1
#: simulated seconds of truth rows kept in memory when they are streamed to a file
TRUTH_KEEP_S = 20.0
#: the harness's log lines where the lockstep starts and ends (``bench sitl`` times the loop by them)


def _sim_port(url: str):
    """The simulator's end of link ``url``'s simulator link (PX4's simulator API: system 255,
    component 190; TCP or the same-host link, :mod:`link_firmware_sim.vehicle.simlink`), waiting for the
    vehicle as long as a process may take to start (it loads its compiled kernels first)."""
    return open_sim_port(url, system_id=255, component_id=190, accept=frozenset({"HIL_ACTUATOR_CONTROLS"}),
                         connect_timeout_s=STARTUP_TIMEOUT_S, simulator=True)


def complete_rows(rows: dict) -> dict[str, np.ndarray]:
    """Each series of ``rows`` (lists or arrays by key) cut to the rows every series has: a row an
    interruption (Ctrl-C) cut short between its appends is left out."""
    n = min(len(v) for v in rows.values())
    return {k: np.asarray(v[:n]) for k, v in rows.items()}


class FleetHarness:
    """The physics of a scenario in lockstep with vehicles behind simulator links."""

    def __init__(self, sc: Scenario, sim_urls: list[str], plant: Plant | None = None,
                 truth_stream: Path | None = None):
        self.scenario = sc
        self.plant = plant if plant is not None else Plant(sc)
        self.schedule = Schedule.of(sc)
        self.n = self.plant.n
        self.ports = [_sim_port(url) for url in sim_urls]
        if not sc.start.on_ground:
            self._prime_hover()
        self.gps_fault = sc.faults.gps
        self.down: set[int] = set()  # links whose vehicle process is gone (rotors stopped)
        #: the truth at the log rate (the newest ``TRUTH_KEEP_S`` with a ``truth_stream``)
        self.rows: dict[str, list] = {k: [] for k in ("t", "p_true", "v_true", "q_true", "thrust", "joint_force_true",
                                                      "tension_true")}
        self._stream = LogStream(truth_stream) if truth_stream is not None else None
        log_dt = self.plant.dt * self.schedule.log
        self._keep_rows = int(round(TRUTH_KEEP_S / log_dt))
        self._flush_every = max(1, int(round(1.0 / log_dt)))  # log ticks: a simulated second
        self.wall_s = 0.0
        self.sim_s = 0.0
        # Called as hook(k, t) at every physics tick after the kinematics (the cameras, sitl.cameras.stream).
        self.tick_hooks: list = []
        #: called while the vehicles' answers are awaited, every WAIT_CHECK_S (the launcher: its
        #: processes checked, so a vehicle that died is reported as such, not as a silent link)
        self.on_wait = lambda: None
        announce(self)

    def _prime_hover(self) -> None:
        """In-air start: the rotors spin at the thrusts that carry each link, as in batch mode."""
        sc, plant = self.scenario, self.plant
        allocator = Allocator(plant.geometry, sc.firmware.allocation)
        thrust = []
        for q in plant.model.truth().q_wxyz:
            thrust.append(allocator.allocate(weight_wrench(plant.inertia, q)).command_n)
            allocator.reset()
        plant.rotors.prime(np.concatenate(thrust))

    def detach(self, i: int) -> None:
        """0-based link ``i``'s vehicle is gone: its rotors stop, the lockstep goes on without it."""
        self.ports[i].close()
        self.down.add(i)

    def attach(self, i: int, url: str) -> None:
        """A (restarted) vehicle for link ``i`` re-joins the lockstep at the next tick."""
        self.ports[i] = _sim_port(url)
        self.down.discard(i)

    def _exchange(self, t: float, k: int, truth) -> np.ndarray:
        """Send this tick's sensor messages to every vehicle; collect every answer."""
        sch, sensors = self.schedule, self.plant.sensors
        outgoing: list[list] = [[] for _ in range(self.n)]
        if k % sch.gps == 0:
            pos, vel = sensors.gps(t, truth.p_w_m, truth.v_w_m_s)
            pos, has_fix = self.gps_fault.apply(t, pos)
            for i in range(self.n):
                if has_fix[i]:
                    outgoing[i].append(encode_hil_gps(t, pos[i], vel[i], self.scenario.origin))
        if k % sch.att == 0:
            att = sensors.attitude(t, truth.q_wxyz)
            for i in range(self.n):
                outgoing[i].append(encode_ahrs(t, att[i]))
        baro, mag = self.plant.baro_mag(k, sch, truth)
        if baro is not None:
            baro = baro + self.scenario.origin.alt_m  # pressure altitude above mean sea level
        gyro, accel = sensors.imu(truth.specific_force_b_m_s2, truth.omega_b_rad_s, sch.fw * self.plant.dt)
        records = hil_sensor_records(t, accel, gyro, mag_flu_gauss=mag, baro_alt_m=baro)  # (one compiled call)
        imu = None
        for i, port in enumerate(self.ports):
            if i in self.down:
                continue
            if not port.send_records(outgoing[i], records[i]):  # one write per vehicle and tick
                if imu is None:  # (this link's messages, packed by pymavlink: a signed link, a tlog)
                    imu = encode_hil_sensors(t, accel, gyro, mag_flu_gauss=mag, baro_alt_m=baro)
                port.send_many(outgoing[i] + [imu[i]])
        want = usec(t)
        controls = np.zeros((self.n, ROTORS_PER_LINK))  # a link that is down: its rotors stopped
        pending = set(range(self.n)) - self.down
        deadline = time.monotonic() + ANSWER_TIMEOUT_S
        while pending:
            ready = wait_readable([self.ports[i] for i in pending], min(deadline - time.monotonic(), WAIT_CHECK_S))
            if not ready:
                if time.monotonic() >= deadline:
                    raise FleetError(f"link(s) {sorted(i + 1 for i in pending)} stopped answering the simulator "
                                     f"at t = {t:.3f} s")
                self.on_wait()
                continue
            for i in list(pending):
                port = self.ports[i]
                if port not in ready:
                    continue
                if not port.connected:
                    raise FleetError(f"link {i + 1} closed its simulator connection at t = {t:.3f} s")
                for msg in port.read():
                    if int(msg.time_usec) == want:
                        controls[i] = msg.controls[:ROTORS_PER_LINK]
                        pending.discard(i)
        try:  # the tick's answers decoded together
            return thrusts_from_controls(controls, self.scenario.rotors.thrust_max_n)
        except MessageError:
            bad = [i + 1 for i in nonfinite_rows(controls)]
            raise FleetError(f"link(s) {bad} answered the simulator with a non-finite control at t = {t:.3f} s") from None

    def run(self, duration_s: float, speed: float = 0.0, progress=None, stop=lambda: False) -> None:
        plant, sch = self.plant, self.schedule
        dt = plant.dt
        n_ticks = int(round(duration_s / dt))
        tick0 = int(round(plant.time_s / dt))
        log.info("%s %d vehicle(s) from t = %.3f s", LOCKSTEP_STARTED, self.n - len(self.down), plant.time_s)
        wall0 = time.perf_counter()
        try:
            for k in range(tick0, tick0 + n_ticks):
                t = k * dt
                fw_due, log_due = k % sch.fw == 0, k % sch.log == 0
                truth = plant.begin_tick(truth=fw_due or log_due)  # (the other ticks: nobody reads it)
                if fw_due:
                    plant.rotors.set_command(self._exchange(t, k, truth).reshape(-1))
                    if speed > 0:
                        lag = (t / speed) - (time.perf_counter() - wall0)
                        if lag > 0:
                            time.sleep(lag)
                    if stop():
                        break
                if log_due:
                    r = self.rows
                    r["t"].append(t)
                    r["p_true"].append(truth.p_w_m.copy())
                    r["v_true"].append(truth.v_w_m_s.copy())
                    r["q_true"].append(truth.q_wxyz.copy())
                    r["thrust"].append(plant.rotors.thrust_n.reshape(self.n, -1).copy())
                    r["joint_force_true"].append(truth.joint_force_w_n)
                    r["tension_true"].append(tension(truth.joint_force_w_n, quat_to_rotmat(truth.q_wxyz)))
                    plant.check_crash(t, truth, None)
                    if self._stream is not None and len(r["t"]) % self._flush_every == 0:
                        self._stream.flush(r, keep=self._keep_rows)
                for hook in self.tick_hooks:
                    hook(k, t)
                plant.end_tick()
                self.sim_s += dt
                if progress is not None and (k - tick0) % 100 == 99:
                    progress(100 * dt)
        finally:
            self.wall_s += time.perf_counter() - wall0
            log.info("%s at t = %.3f s", LOCKSTEP_ENDED, plant.time_s)

    def truth_log(self) -> dict[str, np.ndarray]:
        """The log-rate truth, one row per log tick (read back from the stream file, which first
        gets the newest rows); a row an interruption (Ctrl-C) cut short is left out, so that every
        series has the same rows."""
        if self._stream is None:
            return complete_rows(self.rows)
        got = self._stream.read_back(self.rows, keep=self._keep_rows)
        if any(k not in got for k in self.rows):
            return {k: np.zeros(0) for k in self.rows}
        return complete_rows(got)

    def close(self) -> None:
        if self._stream is not None and not self._stream.closed:
            self._stream.flush(self.rows, keep=self._keep_rows)
            self._stream.close()
        for port in self.ports:
            port.close()

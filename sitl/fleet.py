"""Fleet mode: the MuJoCo harness in lockstep with one firmware process per link, plus the companion.

``python -m sitl launch --config FILE`` starts, for an n-link scenario:

* n vehicle processes (``python -m link_firmware_sim``): link ``i`` is MAVLink system ``i + 1``,
  simulator TCP 4560+i, onboard UDP 14540+i (from 14580+i), GCS UDP 14550 (from 18570+i; another
  port with ``--gcs-port``);
* the companion daemon (``python -m companion``), listening on UDP 14540+i; with
  ``companion.distributed`` one per group (``--group G``, run folder ``companion-gG``), joined
  over Zenoh on loopback (``tcp/127.0.0.1:7460+G-1``, clear of a local zenohd on 7447); ``[faults]`` can SIGKILL one of them
  mid-flight and start a new one later (folder ``companion-gG-restart``);
* with ``--sim-link unix`` the vehicles' simulator links are the same-host link
  (:mod:`link_firmware_sim.simlink`: the same HIL messages as binary records over UNIX sockets in
  a private temporary folder) instead of PX4's TCP 4560+i, which stays the default;
* with ``--instance-offset K`` every one of these ports moves by K (link ``i`` is PX4 SITL
  instance K+i; the system ids stay), so that two fleets can fly side by side;
* the harness (this process): the same :class:`~sitl.runner.Plant` as batch mode, talking to each
  vehicle over its simulator link. Lockstep: at every firmware tick the harness sends HIL_GPS /
  SKELETON_AHRS_REFERENCE (when due) and HIL_SENSOR to every vehicle, waits until every vehicle
  has answered with HIL_ACTUATOR_CONTROLS for that time, then advances the physics. ``--speed F``
  paces the simulation at F times real time (0: as fast as possible).

At the end (or on Ctrl-C) every process is stopped (SIGTERM, then SIGKILL after a grace period;
children also die with the launcher through PR_SET_PDEATHSIG), their logs are merged and the run
folder gets the same ``metrics.json``, ``log.npz`` and plots as batch mode, plus a .tlog per link.

A scenario with ``[[cameras]]`` adds the vision consumer (``python -m companion.vision``, folder
``vision``): the harness renders the cameras on the simulation clock and publishes their frames
on ``<prefix>/camera/<vehicle>/image`` from its own Zenoh session on a free loopback port
(:mod:`sitl.camera_stream`); the consumer runs the marker pipeline on them, and
``metrics.json["vision"]`` scores its poses against the truth (``vision.npz``).
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.config import SITL_STATE_PORT, LinkEndpoint
from companion.configfile import dump_toml
from companion.fleetnet.config import new_users_file
from companion.logstream import read_log_stream
from companion.mavlink.signing import key_passphrase, new_key_file
from companion.mavlink.codec import MessageError, usec
from companion.estimation.so3 import quat_to_rotmat
from companion.mavlink.transport import PortError, wait_readable
from companion.skeleton.kinematics import tension
from link_firmware_sim import _fast
from link_firmware_sim.allocation import Allocator
from link_firmware_sim.control import weight_wrench
from companion.motion.inverse import InverseModel
from link_firmware_sim.simlink import is_simlink_url, open_sim_port
from link_firmware_sim.hil import (ROTORS_PER_LINK, SITL_GPS_EPOCH_US, encode_ahrs, encode_hil_gps, encode_hil_sensors,
                                   nonfinite_rows, thrusts_from_controls)

from .metrics import PAPER_THREE_LINK, carrying_metrics, compute_metrics, reboot_timeline, vehicle_down_windows
from .runner import Plant, Schedule
from .scenario import Scenario
from .steplog import attach_truth, merge_step_logs

__all__ = ["FleetError", "FleetHarness", "GCS_PORT", "check_fleet_scenario", "check_instance_offset", "endpoint_table",
           "launch", "signing_instructions"]

log = logging.getLogger(__name__)

#: UDP ports of the impaired wire (``[faults.mavlink]``): vehicle i sends to WIRE_VEHICLE_SIDE + i,
#: the companion sees it from WIRE_COMPANION_SIDE + i
WIRE_VEHICLE_SIDE = 15540
WIRE_COMPANION_SIDE = 15580
ANSWER_TIMEOUT_S = 10.0
#: the vehicles' simulator links: PX4's simulator API on TCP (the default), or the same-host link
SIM_LINKS = ("tcp", "unix")
#: the harness's log lines where the lockstep starts and ends (``bench sitl`` times the loop by them)
LOCKSTEP_STARTED = "lockstep started:"
LOCKSTEP_ENDED = "lockstep ended"
STOP_GRACE_S = 10.0
STARTUP_TIMEOUT_S = 30.0
#: where every vehicle sends its ground-station traffic (PX4 SITL's: QGroundControl listens there)
GCS_PORT = 14550


class FleetError(RuntimeError):
    """The fleet could not run (a process died, a link stopped answering the simulator)."""


def signing_instructions(sc: Scenario, gcs_port: int = GCS_PORT) -> str:
    """How a ground station joins a signed fleet, as typed: MAVProxy's ``signing key`` takes the
    passphrase itself (its prompt does no shell expansion)."""
    modes = f"MAVLink 2 signing: onboard {sc.signing.link_mode('onboard')}, GCS {sc.signing.link_mode('gcs')}; key file " \
            f"{sc.signing.key_file}"
    try:
        passphrase = key_passphrase(sc.signing.key_file)
    except ValueError as exc:
        return f"{modes} ({exc})"
    if passphrase is None:
        return (f"{modes}: a raw key; MAVProxy and QGroundControl derive theirs from a passphrase "
                "(python -m companion keys new FILE makes one)")
    return (f"{modes}\nMAVProxy: mavproxy.py --master=udpin:127.0.0.1:{gcs_port}, then type at its prompt:\n"
            f"    signing key {passphrase}")


def endpoint_table(sc: Scenario, host: str = "127.0.0.1", instance_offset: int = 0,
                   sim_dir: Path | None = None, gcs_port: int = GCS_PORT) -> str:
    """The fleet's addresses; ``sim_dir``: the same-host simulator link's socket folder (else TCP)."""
    k = instance_offset
    rows = [f"{'link':>4} | {'sysid':>5} | {'simulator (TCP)' if sim_dir is None else 'simulator (UNIX)':>18} | "
            f"{'onboard / companion (UDP)':>28} | {'GCS (UDP)':>24}", "-" * 93]
    for i in range(sc.skeleton.n_links):
        sim = f"{host}:{4560 + k + i}" if sim_dir is None else f"link{i + 1}.sock"
        onboard = f"{host}:{14540 + k + i} <- :{14580 + k + i}"
        gcs = f"{host}:{gcs_port} <- :{18570 + k + i}"
        rows.append(f"{i + 1:>4} | {i + 1:>5} | {sim:>18} | {onboard:>28} | {gcs:>24}")
    if sim_dir is not None:
        rows.append(f"simulator links: UNIX sockets in {sim_dir} (this run only)")
    if sc.companion.distributed:
        for g, links in enumerate(sc.companion.group_layout(sc.skeleton.n_links)):
            rows.append(f"companion of group {g + 1} (links {links[0] + 1}-{links[-1] + 1}): Zenoh "
                        f"{sc.zenoh.group_endpoint(g)}, keys {sc.zenoh_prefix}/...")
    rows.append(f"QGroundControl / MAVProxy: listen on UDP {gcs_port}. MAVSDK: udpin://127.0.0.1:{14540 + k}+i (launch with "
                "--no-companion).")
    if sc.signing.active:
        rows.append(signing_instructions(sc, gcs_port))
    return "\n".join(rows)


def _sim_port(url: str):
    """The simulator's end of link ``url``'s simulator link (PX4's simulator API: system 255,
    component 190; TCP or the same-host link, :mod:`link_firmware_sim.simlink`), waiting for the
    vehicle as long as a process may take to start (it loads its compiled kernels first)."""
    return open_sim_port(url, system_id=255, component_id=190, accept=frozenset({"HIL_ACTUATOR_CONTROLS"}),
                         connect_timeout_s=STARTUP_TIMEOUT_S, simulator=True)


class FleetHarness:
    """The physics of a scenario in lockstep with vehicles behind simulator links."""

    def __init__(self, sc: Scenario, sim_urls: list[str], plant: Plant | None = None):
        self.scenario = sc
        self.plant = plant if plant is not None else Plant(sc)
        self.schedule = Schedule.of(sc)
        self.n = self.plant.n
        self.ports = [_sim_port(url) for url in sim_urls]
        if not sc.start.on_ground:
            self._prime_hover()
        self.gps_fault = sc.faults.gps
        self.down: set[int] = set()  # links whose vehicle process is gone (rotors stopped)
        self.rows: dict[str, list] = {k: [] for k in ("t", "p_true", "v_true", "q_true", "thrust", "joint_force_true",
                                                      "tension_true")}
        self.wall_s = 0.0
        self.sim_s = 0.0
        # Called as hook(k, t) at every physics tick after the kinematics (the cameras, sitl.camera_stream).
        self.tick_hooks: list = []

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
        imu = encode_hil_sensors(t, accel, gyro, mag_flu_gauss=mag, baro_alt_m=baro)
        for i, port in enumerate(self.ports):
            if i in self.down:
                continue
            outgoing[i].append(imu[i])
            port.send_many(outgoing[i])  # one write per vehicle and tick
        want = usec(t)
        controls = np.zeros((self.n, ROTORS_PER_LINK))  # a link that is down: its rotors stopped
        pending = set(range(self.n)) - self.down
        deadline = time.monotonic() + ANSWER_TIMEOUT_S
        while pending:
            ready = wait_readable([self.ports[i] for i in pending], deadline - time.monotonic())
            if not ready and time.monotonic() >= deadline:
                raise FleetError(f"link(s) {sorted(i + 1 for i in pending)} stopped answering the simulator at t = {t:.3f} s")
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
                truth = plant.begin_tick()
                if k % sch.fw == 0:
                    plant.rotors.set_command(self._exchange(t, k, truth).reshape(-1))
                    if speed > 0:
                        lag = (t / speed) - (time.perf_counter() - wall0)
                        if lag > 0:
                            time.sleep(lag)
                    if stop():
                        break
                if k % sch.log == 0:
                    r = self.rows
                    r["t"].append(t)
                    r["p_true"].append(truth.p_w_m.copy())
                    r["v_true"].append(truth.v_w_m_s.copy())
                    r["q_true"].append(truth.q_wxyz.copy())
                    r["thrust"].append(plant.rotors.thrust_n.reshape(self.n, -1).copy())
                    r["joint_force_true"].append(truth.joint_force_w_n)
                    r["tension_true"].append(tension(truth.joint_force_w_n, quat_to_rotmat(truth.q_wxyz)))
                    plant.check_crash(t, truth, None)
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
        """The log-rate truth, one row per log tick; a row an interruption (Ctrl-C) cut short is
        left out, so that every series has the same rows."""
        n = min(len(v) for v in self.rows.values())
        return {k: np.asarray(v[:n]) for k, v in self.rows.items()}

    def close(self) -> None:
        for port in self.ports:
            port.close()


def _die_with_parent() -> None:  # runs in the child before exec (Linux)
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def _enter_batch_scheduling() -> int | None:
    """Put the calling thread under Linux's SCHED_BATCH, and so every process it starts from now
    (the policy is inherited across fork and exec); returns the policy to restore
    (:func:`_restore_scheduling`), or ``None`` where SCHED_BATCH is missing (not Linux) or refused.

    An unpaced fleet is a throughput job: each tick the harness wakes seven vehicles, they wake
    it and their companions, and under the default policy every woken process preempts the one
    that woke it. SCHED_BATCH keeps the same CPU shares (nice values) but a woken process waits
    for the running one to block or use up its slice instead of preempting it (sched(7)), which
    spares the context switches and the caches they cost. Measured on the 2-core VM (seven_link,
    same-host link, interleaved pairs of 20 s flights): 1.36x mean real-time factor without it and
    1.48x with it over 6 pairs, every pair faster; 1.26x and 1.32x over 4 more in a slower phase of
    the VM (two pairs level); three_link the same either way (3.09x, 3.08x)."""
    policy = getattr(os, "SCHED_BATCH", None)
    if policy is None:
        return None
    try:
        before = os.sched_getscheduler(0)
        os.sched_setscheduler(0, policy, os.sched_param(0))
    except OSError as exc:
        log.info("SCHED_BATCH refused (%s): the default scheduling policy stays", exc)
        return None
    return before


def _restore_scheduling(before: int | None) -> None:
    if before is not None:
        try:
            os.sched_setscheduler(0, before, os.sched_param(0))
        except OSError as exc:  # (back to SCHED_OTHER is allowed unprivileged)
            log.warning("could not restore the scheduling policy: %s", exc)


class _Processes:
    def __init__(self):
        self.procs: list[tuple[str, subprocess.Popen]] = []
        self.killed: set[str] = set()
        self._next_check_s = -float("inf")

    def start(self, name: str, argv: list[str], log_path: Path, stdin_pipe: bool = False,
              env: dict | None = None) -> None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(log_path, "wb")
        # Own session: a Ctrl-C in the terminal reaches the launcher only, which stops the fleet in order.
        proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, preexec_fn=_die_with_parent,
                                start_new_session=True, stdin=subprocess.PIPE if stdin_pipe else subprocess.DEVNULL,
                                env=env)
        fh.close()
        self.procs.append((name, proc))

    def release(self, name: str) -> None:
        """Start a process waiting in ``--standby`` (one line on its stdin)."""
        for pname, proc in self.procs:
            if pname == name and proc.stdin is not None:
                proc.stdin.write(b"start\n")
                proc.stdin.flush()

    def kill(self, name: str) -> None:
        """SIGKILL a process on purpose (a scripted fault): it is no longer checked."""
        for pname, proc in self.procs:
            if pname == name and proc.poll() is None:
                proc.kill()
                proc.wait()
        self.killed.add(name)

    def check(self, every_s: float = 0.0) -> None:
        """:class:`FleetError` if a process exited (not one killed on purpose); with ``every_s``, at
        most once per that much wall time (the lockstep calls it every tick: ten waitpid calls)."""
        if every_s > 0.0:
            now = time.monotonic()
            if now < self._next_check_s:
                return
            self._next_check_s = now + every_s
        for name, proc in self.procs:
            if name not in self.killed and proc.poll() is not None:
                raise FleetError(f"{name} exited with code {proc.returncode} (see its console log)")

    def stop(self) -> None:
        for _, proc in self.procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        for name, proc in self.procs:
            try:
                proc.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s: killing it", name, STOP_GRACE_S)
                proc.kill()
                proc.wait()


def _companion_name(group: int | None) -> str:
    return "companion" if group is None else f"companion of group {group + 1}"


def _distributed_metrics(sc: Scenario, merged: dict, summaries: dict[str, dict], faults: dict) -> dict:
    """Global-step figures of a distributed fleet run: per companion its counts, leaders and
    round trips; the leader failover after a scripted kill, measured by the surviving groups."""
    out: dict = {"companions": {}}
    rts = []
    for name, summ in summaries.items():
        out["companions"][name] = {k: summ.get(k) for k in ("global_step", "round_trip_ms_as_leader", "failovers",
                                                             "malformed_payloads", "cpg_targets")}
        if summ.get("round_trip_ms_as_leader"):
            rts.append(summ["round_trip_ms_as_leader"])
    for part in ("network", "end_to_end"):
        values = [r[part]["p99"] for r in rts if r.get(part)]
        if values:
            out[f"round_trip_{part}_ms_p99"] = max(values)
    win = merged.get("t_sckf", np.zeros(0)) >= sc.flight_start_s
    if "global_applied" in merged and np.any(win):
        out["cycles_with_global_step_fraction"] = float(np.mean(np.all(merged["global_applied"][win], axis=1)))
    if faults:
        out["fault"] = {k: v for k, v in faults.items() if not k.endswith("_monotonic")}
        takeovers = []
        for name, summ in summaries.items():
            for fo in summ.get("failovers") or []:
                if fo.get("from") == faults["group"] and "gone_at" in fo:
                    takeovers.append({"observed_by": name, "to_group": fo.get("to"),
                                      "leader_gone_after_kill_s": round(fo["gone_at"] - faults["killed_at_monotonic"], 4),
                                      "global_step_back_after_kill_s": round(
                                          fo["gone_at"] + fo["first_global_after_s"] - faults["killed_at_monotonic"], 4),
                                      "cycles_without_global_step": fo["cycles_without_global"]})
        out["fault"]["failover"] = takeovers
        if takeovers:
            out["fault"]["failover_s_max"] = max(t["global_step_back_after_kill_s"] for t in takeovers)
    return out


def _bound_ports(kind: str) -> set[int]:
    """Local ports with a bound UDP socket (``kind = "udp"``) or a listening TCP one (``"tcp"``),
    from Linux's /proc/net tables (IPv4 and IPv6)."""
    ports = set()
    for table in (f"/proc/net/{kind}", f"/proc/net/{kind}6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            cols = line.split()  # local address "0100007F:38B4", state at [3] ("0A": LISTEN)
            if kind == "udp" or cols[3] == "0A":
                ports.add(int(cols[1].rsplit(":", 1)[1], 16))
    return ports


def _listening_unix_paths() -> set[str]:
    """Paths of listening UNIX sockets, from Linux's /proc/net/unix (flag 0x10000: accepting)."""
    paths = set()
    try:
        lines = Path("/proc/net/unix").read_text().splitlines()[1:]
    except OSError:
        return paths
    for line in lines:
        cols = line.split(None, 7)  # Num RefCount Protocol Flags Type St Inode [Path (may hold spaces)]
        if len(cols) >= 8 and int(cols[3], 16) & 0x10000:
            paths.add(cols[7])
    return paths


def _wait_udp_listening(ports: list[int], procs: _Processes, who: str = "the companion") -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while not set(ports) <= _bound_ports("udp"):
        procs.check()
        if time.monotonic() > deadline:
            raise FleetError(f"{who} did not open UDP {ports} within {STARTUP_TIMEOUT_S:.0f} s")
        time.sleep(0.05)


def load_run_log(folder: Path, stem: str) -> dict[str, np.ndarray] | None:
    """A process's log in a fleet run folder: ``<stem>.npz`` (written at a clean exit), else what
    its ``<stem>.stream`` holds (a killed process: up to its last flush), else ``None``."""
    npz, stream = folder / f"{stem}.npz", folder / f"{stem}.stream"
    if npz.exists():
        return dict(np.load(npz))
    if stream.exists():
        return read_log_stream(stream) or None
    return None


def _merge_logs(sc: Scenario, truth: dict[str, np.ndarray],
                out_dir: Path) -> tuple[dict[str, np.ndarray], np.ndarray, list[int]]:
    """Align the vehicles', the companion's and the harness's logs on flight-controller time;
    returns the merged log, the correction latencies and the links (1-based) without a flight log."""
    n = sc.skeleton.n_links
    t_us = np.round(truth["t"] * 1e6).astype(np.int64)
    index = {int(x): i for i, x in enumerate(t_us)}
    fw = [_vehicle_log(out_dir, i) for i in range(n)]
    missing = [i + 1 for i, f in enumerate(fw) if f is None]
    if len(missing) == n:
        raise FleetError("no vehicle wrote its flight log")
    if missing:
        log.warning("no flight log from link(s) %s (killed): their estimates are NaN in the metrics", missing)
    # Every simulator row that some vehicle logged: a link that was not flying its firmware then
    # (not started yet, killed, rebooting) has NaN estimates in that row.
    logged: set[int] = set()
    for f in fw:
        if f is not None:
            logged |= set(np.round(f["t"] * 1e6).astype(np.int64).tolist())
    times = np.array(sorted(set(t_us.tolist()) & logged), dtype=np.int64)
    if times.size == 0:
        raise FleetError("the vehicles' flight logs and the simulator log share no time stamps")
    rows = [index[int(x)] for x in times]
    merged = {
        "t": times * 1e-6,
        "p_true": truth["p_true"][rows],
        "v_true": truth["v_true"][rows],
        "q_true": truth["q_true"][rows],
        "thrust": truth["thrust"][rows],
        "joint_force_true": truth["joint_force_true"][rows],
        "tension_true": truth["tension_true"][rows],
    }
    fw_rows = []  # per link: the row of its log at each merged time (-1: none)
    for f in fw:
        if f is None:
            fw_rows.append(None)
            continue
        ft = {int(x): i for i, x in enumerate(np.round(f["t"] * 1e6).astype(np.int64))}
        fw_rows.append(np.array([ft.get(int(x), -1) for x in times], dtype=np.int64))
    present = next(f for f in fw if f is not None)
    for key in ("p_ekf", "q_ekf", "p_ctrl", "q_ctrl", "p_target", "q_target"):
        columns = []
        for f, r in zip(fw, fw_rows):
            col = np.full((times.size,) + present[key].shape[1:], np.nan)
            if f is not None:
                col[r >= 0] = f[key][r[r >= 0]]
            columns.append(col)
        merged[key] = np.stack(columns, axis=1)
    comp = _companion_log(sc, out_dir)
    if comp is not None:
        if sc.companion.time_base == "gps":  # a companion on GPS time: the simulated GPS clock
            comp["t_sckf"] = (np.round(comp["t_sckf"] * 1e6).astype(np.int64) - SITL_GPS_EPOCH_US) * 1e-6
        merged.update(attach_truth(comp, truth["t"], truth["p_true"], truth["v_true"], truth["q_true"]))
    logs = [f["correction_latency"] for f in fw if f is not None]
    latency = np.concatenate(logs) if logs else np.zeros((0, 2))
    return merged, latency, missing


def _vehicle_log(out_dir: Path, i: int) -> dict[str, np.ndarray] | None:
    """0-based link ``i``'s flight log: its first process's and, after a scripted reboot, its
    restarted process's (folder ``link<i+1>-restart``), one after the other."""
    parts = [lg for lg in (load_run_log(out_dir / folder, f"link{i + 1}_firmware")
                           for folder in (f"link{i + 1}", f"link{i + 1}-restart")) if lg is not None and "t" in lg]
    if not parts:
        return None
    for p in parts:  # a stream holds the latencies only once a correction arrived
        p["correction_latency"] = np.asarray(p.get("correction_latency", np.zeros((0, 2)))).reshape(-1, 2)
    keys = set.intersection(*(set(p) for p in parts))
    return {k: np.concatenate([p[k] for p in parts], axis=0) for k in keys}


def _companion_log(sc: Scenario, out_dir: Path) -> dict[str, np.ndarray] | None:
    """The companions' step logs over the whole chain (a group's restarted companion continues
    its group's log; :func:`~sitl.steplog.merge_step_logs`)."""

    def parts(*folders: str) -> list[dict]:
        return [lg for lg in (load_run_log(out_dir / f, "companion_log") for f in folders) if lg is not None]

    if not sc.companion.distributed:
        logs = [parts("companion")]
    else:
        logs = [parts(f"companion-g{g + 1}", f"companion-g{g + 1}-restart")
                for g in range(len(sc.companion.group_layout(sc.skeleton.n_links)))]
    return merge_step_logs(logs, sc.skeleton.d_b_m, sc.companion.distributed)


def _companion_summaries(out_dir: Path) -> dict[str, dict]:
    out = {}
    for path in sorted(out_dir.glob("companion*/companion_summary.json")):
        try:
            out[path.parent.name] = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
    return out


_PORT_COUNTERS = ("signed", "unsigned", "rejected_unsigned", "rejected_signature", "rejected_replay", "peer_kept",
                  "dropped_frames", "dropped_unknown")


def _is_sim_url(url: str) -> bool:
    """A vehicle's simulator link: PX4's TCP, or the same-host link (its UDP ports are MAVLink's)."""
    return url.startswith("tcp") or is_simlink_url(url)


def mavlink_counters(out_dir: Path) -> dict:
    """Per process of a fleet run: its MAVLink ports' signing and rejection counters (from the
    vehicles' ``link<i>_ports.json`` and the companions' ``companion_summary.json``), the
    vehicles' refusals (out-of-bound corrections, disarms in flight, SETUP_SIGNING), and their
    simulator links' drops and refused peers (``sim_dropped_frames``, ``sim_rejected_peer``)."""
    out: dict = {}
    for path in sorted(out_dir.glob("link*/link*_ports.json")):
        try:
            ports = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        links = {url: p for url, p in ports.items() if url not in ("errors", "gps", "ekf", "thrust_limit")}
        sim = [p for url, p in links.items() if _is_sim_url(url)]
        mavlink = [p for url, p in links.items() if not _is_sim_url(url)]
        entry = {k: sum(p.get(k, 0) for p in mavlink) for k in _PORT_COUNTERS}
        entry.update(sim_dropped_frames=sum(p.get("dropped_frames", 0) for p in sim),
                     sim_rejected_peer=sum(p.get("rejected_peer", 0) for p in sim))
        entry.update(ports.get("errors", {}))
        out[path.parent.name] = entry
    for folder, summary in _companion_summaries(out_dir).items():
        links = summary.get("links", {}).values()
        out[folder] = {k: sum(lk.get(k, 0) for lk in links) for k in _PORT_COUNTERS}
    return out


def _impaired_links(sc: Scenario) -> list[int]:
    """0-based links whose onboard wire goes through :mod:`sitl.wire` (``[faults.mavlink]``)."""
    m = sc.faults.mavlink
    if not m.active:
        return []
    return [i - 1 for i in m.links] if m.links else list(range(sc.skeleton.n_links))


def _fault_windows(sc: Scenario, fault_log: dict, link_fault: dict, end_s: float) -> list[dict]:
    """The scripted faults' outage windows: a vehicle down (killed until back in the lockstep),
    a companion down (killed until restarted, or the end of the run)."""
    out = vehicle_down_windows(link_fault, end_s)
    if "killed_at_s" in fault_log:
        group = sc.companion.group_layout(sc.skeleton.n_links)[fault_log["group"] - 1]
        out.append({"kind": "companion_down", "start_s": fault_log["killed_at_s"],
                    "end_s": fault_log.get("restarted_at_s", end_s), "links": [i + 1 for i in group]})
    return out


def _fault_report(sc: Scenario, merged: dict, out_dir: Path, link_fault: dict, wired: list[int]) -> dict:
    """What the scripted faults did (metrics.json ``faults``): the vehicle reboot's timeline (killed,
    restarted, back in the lockstep, rotors on, first corrected by the companion), the impaired
    wires' counters, and the GPS glitch as the firmware reported it."""
    out: dict = {}
    if link_fault:
        out["link_reboot"] = reboot_timeline(link_fault, merged)
    if wired:
        path = out_dir / "wire" / "wire_stats.json"
        try:
            stats = json.loads(path.read_text())
        except (OSError, ValueError):
            stats = {}
        m = sc.faults.mavlink
        out["mavlink"] = {"loss": m.loss, "delay_ms": m.delay_ms, "jitter_ms": m.jitter_ms,
                          "links": [i + 1 for i in wired], "wires": stats}
    if sc.faults.gps.link:
        g = sc.faults.gps
        i = g.link - 1
        entry = {"link": g.link}
        for folder in (f"link{i + 1}", f"link{i + 1}-restart"):
            try:
                ports = json.loads((out_dir / folder / f"link{i + 1}_ports.json").read_text())
            except (OSError, ValueError):
                continue
            entry.setdefault("firmware", []).append(ports.get("gps", {}))
        out["gps"] = entry
    return out


def _start_cameras(sc: Scenario, plant: Plant, out_dir: Path, procs: _Processes, python: str):
    """The camera streamer (renders and publishes; :mod:`sitl.camera_stream`) and the vision
    consumer connected to it; returns once the consumer's subscription matches every key."""
    from .camera_stream import CameraStreamer  # OpenCV, rendering and Zenoh only for camera scenarios

    streamer = CameraStreamer(sc, plant.model.model, plant.model.data, plant.dt, sc.zenoh.runtime_env())
    try:
        config = out_dir / "vision.toml"
        streamer.write_consumer_config(config)
        procs.start("vision consumer", [python, "-m", "companion.vision", "--config", str(config),
                                        "--out", str(out_dir / "vision")], out_dir / "vision" / "console.log")
        try:
            streamer.wait_for_subscriber(STARTUP_TIMEOUT_S, procs.check)
        except TimeoutError as exc:
            raise FleetError(f"the vision consumer: {exc}") from None
    except BaseException:
        streamer.close()
        raise
    return streamer


def check_fleet_scenario(sc: Scenario) -> None:
    """``ValueError`` for a scenario that names its own companion links (a hardware config):
    fleet mode wires the simulated links itself (PX4 SITL ports)."""
    if sc.companion.links:
        raise ValueError(f"companion.links names hardware endpoints ({sc.companion.links[0].url}, ...); "
                         "fleet mode wires the simulated links itself: use a SITL config")


def check_instance_offset(sc: Scenario, instance_offset: int, gcs_port: int = GCS_PORT) -> None:
    """``ValueError`` unless a fleet shifted by ``instance_offset`` K keeps its companion ports
    14540+K+i clear of the GCS port (14550) and below the vehicles' own 14580+ (PX4's layout leaves
    room for 40 instances), and its impaired wire's 15540+K+i below 15580."""
    n, k = sc.skeleton.n_links, instance_offset
    first, last = SITL_STATE_PORT + k, SITL_STATE_PORT + k + n - 1
    if not 0 < gcs_port < 65536:
        raise ValueError(f"GCS port {gcs_port}: a UDP port is 1-65535")
    if k < 0 or last >= 14580 or first <= gcs_port <= last:
        raise ValueError(f"instance offset {k}: the companion ports of {n} links would be {first}-{last}; they must "
                         f"miss the GCS port {gcs_port} and stay below 14580"
                         + (f" (K + n <= 10, or 11 <= K <= {40 - n})" if gcs_port == GCS_PORT else ""))


def launch(sc: Scenario, out_dir: Path, speed: float = 1.0, progress=None, python: str = sys.executable,
           companion: bool = True, plots: bool = True, instance_offset: int = 0, sim_link: str = "tcp",
           batch_scheduling: bool | None = None, gcs_port: int = GCS_PORT) -> dict:
    """Run the scenario in fleet mode; returns the metrics (also written to ``out_dir``; the PNG plots
    too unless ``plots`` is false). ``instance_offset`` K: link ``i`` takes PX4 SITL instance
    K + i's ports (simulator TCP 4560+K+i, onboard UDP 14540+K+i from 14580+K+i, GCS from
    18570+K+i, the impaired wire's 15540+K+i and 15580+K+i) and the group companions Zenoh's
    ``base_port`` + K + g, so that fleets with offsets n apart run side by side on one host; the
    system ids stay 1..n. ``sim_link``: ``"tcp"`` (PX4's simulator API on TCP 4560+K+i) or
    ``"unix"`` (the same-host link, :mod:`link_firmware_sim.simlink`). ``batch_scheduling``: the
    harness and every process of the fleet under SCHED_BATCH (:func:`_enter_batch_scheduling`);
    ``None``: when unpaced (``speed`` 0), where only throughput counts (the metrics say which:
    ``scheduling``). ``gcs_port``: the UDP port every vehicle sends its ground-station traffic to."""
    if sim_link not in SIM_LINKS:
        raise ValueError(f"sim_link {sim_link!r}: one of {', '.join(SIM_LINKS)}")
    check_fleet_scenario(sc)
    check_instance_offset(sc, instance_offset, gcs_port)
    k = instance_offset
    out_dir.mkdir(parents=True, exist_ok=True)
    if sc.signing.active and not sc.signing.key_file:
        # A throwaway key for this run (never in the repository): the run folder holds it.
        key_file = out_dir / "signing.key"
        new_key_file(key_file, overwrite=True)
        sc = replace(sc, signing=replace(sc.signing, key_file=str(key_file.resolve())))
        log.info("signing: a new key for this run in %s", key_file)
    sc.signing.key()  # ValueError now, not in every process, for a missing or unreadable key
    (out_dir / "scenario.toml").write_text(dump_toml(sc))
    plant = Plant(sc)
    # Each process validates its own part of the scenario: the vehicles their link.toml, the
    # companions their companion.toml (the trajectory anchored where the simulated chain starts).
    link_config = out_dir / "link.toml"
    link_config.write_text(dump_toml(sc.vehicle_setup()))
    anchor = tuple(float(x) for x in plant.start_center())
    companion_setup = sc.companion_setup()
    if k:  # the companion listens where this fleet's vehicles send (its defaults are instance 0's)
        cfg = companion_setup.companion
        links = tuple(LinkEndpoint(e.system_id, f"udpin://127.0.0.1:{SITL_STATE_PORT + k + i}")
                      for i, e in enumerate(cfg.endpoints(sc.skeleton.n_links)))
        zc = companion_setup.zenoh
        companion_setup = replace(companion_setup, companion=replace(cfg, links=links),
                                  zenoh=zc if zc.endpoints else replace(zc, base_port=zc.base_port + k))
    if sc.companion.distributed and not sc.zenoh.users_file:
        # The companions authenticate to each other with throwaway credentials of this run: another
        # process on this host cannot join their Zenoh session (zenoh.users_file).
        users_file = out_dir / "zenoh_users.txt"
        new_users_file(users_file, len(sc.companion.group_layout(sc.skeleton.n_links)), overwrite=True)
        companion_setup = replace(companion_setup, zenoh=replace(companion_setup.zenoh, users_file=str(users_file.resolve())))
    # The companion bounds how fast a link's clock (simulated time) can run against its own wall
    # clock: the pace, with room for the catch-up after a slow tick (as fast as it goes: 20).
    rate = 20.0 if speed <= 0 else max(2.0, 4.0 * speed)
    cfg = companion_setup.companion
    companion_setup = replace(companion_setup, companion=replace(cfg, clock_rate_max=max(cfg.clock_rate_max, rate)))
    companion_config = out_dir / "companion.toml"
    companion_config.write_text(dump_toml(replace(companion_setup,
                                                  trajectory=replace(sc.trajectory, anchor_w_m=anchor))))
    n = sc.skeleton.n_links
    faults = sc.faults
    wired = _impaired_links(sc) if companion and sc.companion.enabled else []
    procs = _Processes()
    harness = None
    # The firmware's compiled kernels: compiled (or loaded) here once, so that the n vehicle processes
    # load numba's on-disk cache instead of each compiling them (link_firmware_sim._fast).
    log.info("firmware kernels ready in %.1f s", _fast.warm_up())
    # the same-host link's sockets: a private (0700) folder of its own, short enough for a socket path
    # (made after the last step that can fail before the ``try`` that removes it)
    sim_dir = Path(tempfile.mkdtemp(prefix="skeleton-sim-")) if sim_link == "unix" else None

    def sim_url(i: int, side: str) -> str:
        if sim_dir is not None:
            return f"{'unixin' if side == 'vehicle' else 'unix'}://{sim_dir / f'link{i + 1}.sock'}"
        return f"{'tcpin' if side == 'vehicle' else 'tcpout'}://127.0.0.1:{4560 + k + i}"

    def sim_listening(i: int) -> bool:
        if sim_dir is not None:
            return str(sim_dir / f"link{i + 1}.sock") in _listening_unix_paths()
        return 4560 + k + i in _bound_ports("tcp")
    interrupted = False
    aborted = ""
    fault_log: dict = {}  # the companion kill
    link_fault: dict = {}  # the vehicle reboot
    cameras = None  # sitl.camera_stream.CameraStreamer of a camera scenario

    def start_vehicle(i: int, name: str, folder: str, standby: bool = False) -> None:
        argv = [python, "-m", "link_firmware_sim", "--config", str(link_config), "--instance", str(i),
                "--out", str(out_dir / folder), "--log-rate", f"{sc.sim.log_rate_hz:g}",
                # a restarted Pixhawk keeps its parameters (the first process's file)
                "--params", str(out_dir / f"link{i + 1}" / f"link{i + 1}_params.json"),
                "--sim-url", sim_url(i, "vehicle"),
                "--gcs-url", f"udpout://127.0.0.1:{gcs_port}?bind={18570 + k + i}",
                # its onboard traffic to the companion, or through the impaired wire
                "--onboard-url", f"udpout://127.0.0.1:{(WIRE_VEHICLE_SIDE if i in wired else SITL_STATE_PORT) + k + i}"
                                 f"?bind={14580 + k + i}"]
        procs.start(name, argv + (["--standby"] if standby else []), out_dir / folder / "console.log",
                    stdin_pipe=standby)

    if batch_scheduling is None:
        batch_scheduling = speed <= 0
    policy_before = _enter_batch_scheduling() if batch_scheduling else None
    if policy_before is not None:
        log.info("the harness and the fleet's processes run under SCHED_BATCH (no wake-up preemption)")
    try:
        if wired:
            m = faults.mavlink
            pairs = [f"{WIRE_VEHICLE_SIDE + k + i}:{SITL_STATE_PORT + k + i}:{WIRE_COMPANION_SIDE + k + i}" for i in wired]
            procs.start("wire", [python, "-m", "sitl.wire", *(a for p in pairs for a in ("--pair", p)),
                                 "--loss", f"{m.loss:g}", "--delay-ms", f"{m.delay_ms:g}", "--jitter-ms",
                                 f"{m.jitter_ms:g}", "--seed", str(sc.seed), "--stats", str(out_dir / "wire" / "wire_stats.json")],
                        out_dir / "wire" / "console.log")
            _wait_udp_listening([WIRE_VEHICLE_SIDE + k + i for i in wired], procs, "the impaired wire")
        for i in range(n):
            start_vehicle(i, f"link {i + 1}", f"link{i + 1}")
        reboot = faults.link
        if reboot.kill and reboot.restart_after_s:
            # The replacement, loaded now and released at the kill: its start-up is not the host's
            start_vehicle(reboot.kill - 1, f"link {reboot.kill} (restarted)", f"link{reboot.kill}-restart", standby=True)
        def start_companion(group: int | None, folder: str, name: str | None = None) -> None:
            argv = [python, "-m", "companion", "--config", str(companion_config), "--out", str(out_dir / folder)]
            # The companions stand in for the onboard computers, which have no numba: the numpy path
            # (companion._fast off), their start-up (0.5-0.9 s less, a restart after a fault too) and
            # their memory (90 MB less each) as there.
            procs.start(name or _companion_name(group), argv + ([] if group is None else ["--group", str(group + 1)]),
                        out_dir / folder / "console.log", env=dict(os.environ, SKELETON_JIT="0"))

        if companion and sc.companion.enabled:
            if sc.companion.distributed:
                for g in range(len(sc.companion.group_layout(n))):
                    start_companion(g, f"companion-g{g + 1}")
            else:
                start_companion(None, "companion")
            # Lockstep starts once the companion listens, so that it sees the flight from t = 0.
            _wait_udp_listening([SITL_STATE_PORT + k + i for i in range(n)], procs)
        if sc.cameras:
            cameras = _start_cameras(sc, plant, out_dir, procs, python)
        print(endpoint_table(replace(sc, zenoh=companion_setup.zenoh), instance_offset=k, sim_dir=sim_dir,
                             gcs_port=gcs_port), flush=True)
        if cameras is not None:
            print(f"cameras: Zenoh {cameras.endpoint}, keys {cameras.prefix}/camera/<vehicle>/image "
                  f"(consumer: python -m companion.vision --config {out_dir / 'vision.toml'})", flush=True)
        try:
            harness = FleetHarness(sc, [sim_url(i, "harness") for i in range(n)], plant)
        except PortError as exc:
            procs.check()
            raise FleetError(str(exc)) from None
        if cameras is not None:
            harness.tick_hooks.append(cameras.on_tick)

        def link_reboot(t: float) -> None:
            i = reboot.kill - 1
            if "killed_at_s" not in link_fault and t >= reboot.kill_at_s:
                procs.kill(f"link {i + 1}")
                harness.detach(i)
                link_fault.update(link=i + 1, killed_at_s=round(t, 3))
                log.warning("fault: killed link %d's firmware at t = %.2f s (rotors stopped)", i + 1, t)
                if reboot.restart_after_s:
                    # The replacement (started with the fleet, loaded, waiting in --standby) opens its
                    # ports now and then waits for the simulator like PX4's SITL (silent until the
                    # lockstep connects): its power comes back when the harness attaches it,
                    # restart_after_s of simulated time after the kill. The physics does not wait for
                    # it (the companion, on wall time, would take the other links' silence for an
                    # outage): a host slower than that lengthens the outage, and says so.
                    procs.release(f"link {i + 1} (restarted)")
            if (reboot.restart_after_s and "killed_at_s" in link_fault and "restarted_at_s" not in link_fault
                    and t >= reboot.kill_at_s + reboot.restart_after_s):
                link_fault.update(restarted_at_s=round(t, 3))
                log.warning("fault: link %d's firmware powered on again at t = %.2f s", i + 1, t)
            if "restarted_at_s" in link_fault and "rejoined_at_s" not in link_fault and sim_listening(i):
                harness.attach(i, sim_url(i, "harness"))
                link_fault.update(rejoined_at_s=round(t, 3))
                late = t - link_fault["restarted_at_s"]
                (log.warning if late > 0.05 else log.info)(
                    "fault: link %d re-joined the lockstep at t = %.2f s%s", i + 1, t,
                    f" ({late:.2f} s of simulated time after its power-on: its process was still starting)"
                    if late > 0.05 else "")
            if "rejoined_at_s" in link_fault and "rotors_on_at_s" not in link_fault and np.any(
                    plant.rotors.command_n.reshape(n, -1)[i] != 0):
                link_fault.update(rotors_on_at_s=round(t, 3))

        def stop_check() -> bool:
            t = plant.time_s
            if reboot.kill:
                link_reboot(t)
            if faults.kill_companion_group and companion and sc.companion.enabled:
                g = faults.kill_companion_group - 1
                if "killed_at_s" not in fault_log and t >= faults.kill_at_s:
                    procs.kill(_companion_name(g))
                    fault_log.update(group=g + 1, killed_at_s=round(t, 3), killed_at_monotonic=time.monotonic())
                    log.warning("fault: killed the companion of group %d at t = %.2f s", g + 1, t)
                if (faults.restart_after_s and "killed_at_s" in fault_log and "restarted_at_s" not in fault_log
                        and t >= faults.kill_at_s + faults.restart_after_s):
                    start_companion(g, f"companion-g{g + 1}-restart", f"{_companion_name(g)} (restarted)")
                    fault_log.update(restarted_at_s=round(t, 3), restarted_at_monotonic=time.monotonic())
                    log.warning("fault: restarted the companion of group %d at t = %.2f s", g + 1, t)
            procs.check(every_s=0.02)  # FleetError if a process died (noticed within 20 ms)
            return False

        try:
            harness.run(sc.duration_s, speed, progress, stop_check)
        except KeyboardInterrupt:
            interrupted = True
            log.warning("interrupted: stopping the fleet")
        except FleetError as exc:  # a process died: what was flown is still measured below
            aborted = str(exc)
            log.error("the fleet stopped at t = %.2f s: %s", harness.sim_s, aborted)
    finally:
        if harness is not None:
            harness.close()
        try:
            procs.stop()  # the vision consumer drains the frames in flight before it exits
        finally:
            if cameras is not None:
                cameras.close()
            if sim_dir is not None:
                shutil.rmtree(sim_dir, ignore_errors=True)
            _restore_scheduling(policy_before)
    if harness is None:
        raise FleetError("the simulator never connected to the vehicles")
    if harness.sim_s <= sc.flight_start_s:
        raise FleetError(f"{aborted + '; ' if aborted else ''}stopped at t = {harness.sim_s:.1f} s, before the metrics "
                         f"window (from {sc.flight_start_s:g} s): no metrics, the vehicles' logs and tlogs are kept")
    truth = harness.truth_log()
    merged, latency, missing = _merge_logs(sc, truth, out_dir)
    metrics = compute_metrics(merged, sc.flight_start_s, plant.rotors.zero_crossings, plant.crashed,
                              plant.crash_reason, harness.sim_s / max(harness.wall_s, 1e-9),
                              sc.companion.enabled and "p_corr_sckf" in merged,
                              groups=sc.companion.group_layout(n), resting=sc.trajectory.kind == "rest",
                              motion=sc.motion if sc.trajectory.kind == "cpg" else None,
                              fault_windows=_fault_windows(sc, fault_log, link_fault, harness.sim_s),
                              rotor_limit_s=plant.rotors.limit_s, took_off=plant.took_off)
    lat = latency[latency[:, 0] >= sc.flight_start_s, 1] if latency.size else np.zeros(0)
    metrics["correction_latency_ms"] = (
        {"p50": round(float(np.percentile(lat, 50) * 1e3), 3), "p99": round(float(np.percentile(lat, 99) * 1e3), 3),
         "max": round(float(lat.max() * 1e3), 3), "samples": int(lat.size)} if lat.size else None
    )
    metrics.update(scenario=sc.name, seed=sc.seed, duration_s=harness.sim_s, mode="fleet", speed=speed, sim_link=sim_link,
                   scheduling="batch" if policy_before is not None else "default",
                   interrupted=interrupted, aborted=aborted or None,
                   missing_flight_logs=missing)
    if sc.companion.distributed and companion and sc.companion.enabled:
        metrics["distributed"] = _distributed_metrics(sc, merged, _companion_summaries(out_dir), fault_log)
    if sc.trajectory.feedforward and companion and sc.companion.enabled:
        metrics["carrying"] = carrying_metrics(_companion_summaries(out_dir))
    metrics["mavlink"] = mavlink_counters(out_dir)
    report = _fault_report(sc, merged, out_dir, link_fault, wired)
    if report:
        metrics["faults"] = report
    if n == 3:
        metrics["paper_reference"] = PAPER_THREE_LINK
    if cameras is not None:
        from .camera_stream import fleet_vision_metrics

        metrics["vision"], vision_arrays = fleet_vision_metrics(cameras, out_dir / "vision", sc.flight_start_s)
        np.savez_compressed(out_dir / "vision.npz", **vision_arrays)
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    np.savez_compressed(out_dir / "log.npz", **merged)
    if plots:
        from .plots import write_plots  # (matplotlib loaded after the flight, and only for plots)

        if sc.trajectory.kind == "cpg":
            period_s = 1.0 / InverseModel.load(sc.motion.model).steady.cpg_params.frequency_hz
            write_plots(merged, out_dir, motion=sc.motion, period_s=period_s)
        else:
            write_plots(merged, out_dir)
    (out_dir / "scenario.toml").write_text(dump_toml(replace(sc, duration_s=harness.sim_s)))
    if aborted:
        raise FleetError(f"{aborted}; the {harness.sim_s:.1f} s flown are measured in {out_dir / 'metrics.json'}")
    return metrics


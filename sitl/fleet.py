"""Fleet mode: the MuJoCo harness in lockstep with one firmware process per link, plus the companion.

``python -m sitl launch --config FILE`` starts, for an n-link scenario:

* n vehicle processes (``python -m link_firmware_sim``): link ``i`` is MAVLink system ``i + 1``,
  simulator TCP 4560+i, onboard UDP 14540+i (from 14580+i), GCS UDP 14550 (from 18570+i);
* the companion daemon (``python -m companion``), listening on UDP 14540+i;
* the harness (this process): the same :class:`~sitl.runner.Plant` as batch mode, talking to each
  vehicle over its simulator link. Lockstep: at every firmware tick the harness sends HIL_GPS /
  SKELETON_AHRS_REFERENCE (when due) and HIL_SENSOR to every vehicle, waits until every vehicle
  has answered with HIL_ACTUATOR_CONTROLS for that time, then advances the physics. ``--speed F``
  paces the simulation at F times real time (0: as fast as possible).

At the end (or on Ctrl-C) every process is stopped (SIGTERM, then SIGKILL after a grace period;
children also die with the launcher through PR_SET_PDEATHSIG), their logs are merged and the run
folder gets the same ``metrics.json``, ``log.npz`` and plots as batch mode, plus a .tlog per link.
"""

from __future__ import annotations

import ctypes
import json
import logging
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.configfile import dump_toml
from companion.mavlink.codec import usec
from companion.mavlink.hil import decode_actuators, encode_ahrs, encode_hil_gps, encode_hil_sensor
from companion.mavlink.port import MavlinkPort, PortError, wait_readable
from link_firmware_sim.allocation import Allocator
from link_firmware_sim.control import weight_wrench

from .metrics import PAPER_THREE_LINK, compute_metrics
from .plots import write_plots
from .runner import Plant, Schedule
from .scenario import Scenario

__all__ = ["FleetError", "FleetHarness", "check_fleet_scenario", "endpoint_table", "launch"]

log = logging.getLogger(__name__)

ANSWER_TIMEOUT_S = 10.0
STOP_GRACE_S = 10.0
STARTUP_TIMEOUT_S = 30.0


class FleetError(RuntimeError):
    """The fleet could not run (a process died, a link stopped answering the simulator)."""


def endpoint_table(sc: Scenario, host: str = "127.0.0.1") -> str:
    rows = [f"{'link':>4} | {'sysid':>5} | {'simulator (TCP)':>18} | {'onboard / companion (UDP)':>28} | {'GCS (UDP)':>17}",
            "-" * 86]
    for i in range(sc.skeleton.n_links):
        rows.append(f"{i + 1:>4} | {i + 1:>5} | {host}:{4560 + i:>5}    | {host}:{14540 + i} <- :{14580 + i}"
                    f"{'':>6} | {host}:14550 <- :{18570 + i}")
    rows.append("QGroundControl / MAVProxy: listen on UDP 14550. MAVSDK: udpin://0.0.0.0:14540+i (launch with --no-companion).")
    return "\n".join(rows)


class FleetHarness:
    """The physics of a scenario in lockstep with vehicles behind simulator links."""

    def __init__(self, sc: Scenario, sim_urls: list[str], plant: Plant | None = None):
        self.scenario = sc
        self.plant = plant if plant is not None else Plant(sc)
        self.schedule = Schedule.of(sc)
        self.n = self.plant.n
        self.ports = [MavlinkPort(url, system_id=255, component_id=190, accept=frozenset({"HIL_ACTUATOR_CONTROLS"}))
                      for url in sim_urls]
        if not sc.start.on_ground:
            self._prime_hover()
        self.rows: dict[str, list] = {k: [] for k in ("t", "p_true", "v_true", "q_true", "thrust")}
        self.wall_s = 0.0
        self.sim_s = 0.0

    def _prime_hover(self) -> None:
        """In-air start: the rotors spin at the thrusts that carry each link, as in batch mode."""
        sc, plant = self.scenario, self.plant
        allocator = Allocator(plant.geometry, sc.firmware.allocation)
        thrust = []
        for q in plant.model.truth().q_wxyz:
            thrust.append(allocator.allocate(weight_wrench(plant.inertia, q)).command_n)
            allocator.reset()
        plant.rotors.prime(np.concatenate(thrust))

    def _exchange(self, t: float, k: int, truth) -> np.ndarray:
        """Send this tick's sensor messages to every vehicle; collect every answer."""
        sch, sensors = self.schedule, self.plant.sensors
        outgoing: list[list] = [[] for _ in range(self.n)]
        if k % sch.gps == 0:
            pos, vel = sensors.gps(t, truth.p_w_m, truth.v_w_m_s)
            for i in range(self.n):
                outgoing[i].append(encode_hil_gps(t, pos[i], vel[i], self.scenario.origin))
        if k % sch.att == 0:
            att = sensors.attitude(t, truth.q_wxyz)
            for i in range(self.n):
                outgoing[i].append(encode_ahrs(t, att[i]))
        gyro, accel = sensors.imu(truth.specific_force_b_m_s2, truth.omega_b_rad_s, sch.fw * self.plant.dt)
        for i, port in enumerate(self.ports):
            outgoing[i].append(encode_hil_sensor(t, accel[i], gyro[i], truth.q_wxyz[i]))
            port.send_many(outgoing[i])  # one write per vehicle and tick
        want = usec(t)
        thrust = np.zeros((self.n, 8))
        pending = set(range(self.n))
        deadline = time.monotonic() + ANSWER_TIMEOUT_S
        while pending:
            ready = wait_readable([self.ports[i] for i in pending], deadline - time.monotonic())
            if not ready and time.monotonic() >= deadline:
                raise FleetError(f"link(s) {sorted(i + 1 for i in pending)} stopped answering the simulator at t = {t:.3f} s")
            for i in list(pending):
                port = self.ports[i]
                if port not in ready:
                    continue
                if not port.transport.connected:
                    raise FleetError(f"link {i + 1} closed its simulator connection at t = {t:.3f} s")
                for msg in port.read():
                    t_us, u = decode_actuators(msg, self.scenario.rotors.thrust_max_n)
                    if t_us == want:
                        thrust[i] = u
                        pending.discard(i)
        return thrust

    def run(self, duration_s: float, speed: float = 0.0, progress=None, stop=lambda: False) -> None:
        plant, sch = self.plant, self.schedule
        dt = plant.dt
        n_ticks = int(round(duration_s / dt))
        tick0 = int(round(plant.time_s / dt))
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
                    plant.check_crash(t, truth, None)
                plant.end_tick()
                self.sim_s += dt
                if progress is not None and (k - tick0) % 100 == 99:
                    progress(100 * dt)
        finally:
            self.wall_s += time.perf_counter() - wall0

    def truth_log(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(v) for k, v in self.rows.items()}

    def close(self) -> None:
        for port in self.ports:
            port.close()


def _die_with_parent() -> None:  # runs in the child before exec (Linux)
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


class _Processes:
    def __init__(self):
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, argv: list[str], log_path: Path) -> None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(log_path, "wb")
        # Own session: a Ctrl-C in the terminal reaches the launcher only, which stops the fleet in order.
        proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, preexec_fn=_die_with_parent,
                                start_new_session=True)
        fh.close()
        self.procs.append((name, proc))

    def check(self) -> None:
        for name, proc in self.procs:
            if proc.poll() is not None:
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


def _udp_listening() -> set[int]:
    """Local UDP ports with a bound socket (Linux: /proc/net/udp and udp6)."""
    ports = set()
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local = line.split()[1]  # "0100007F:38B4"
            ports.add(int(local.rsplit(":", 1)[1], 16))
    return ports


def _wait_udp_listening(ports: list[int], procs: _Processes) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while not set(ports) <= _udp_listening():
        procs.check()
        if time.monotonic() > deadline:
            raise FleetError(f"the companion did not open UDP {ports} within {STARTUP_TIMEOUT_S:.0f} s")
        time.sleep(0.05)


def _merge_logs(sc: Scenario, truth: dict[str, np.ndarray], out_dir: Path) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Align the vehicles', the companion's and the harness's logs on flight-controller time."""
    n = sc.skeleton.n_links
    t_us = np.round(truth["t"] * 1e6).astype(np.int64)
    index = {int(x): i for i, x in enumerate(t_us)}
    fw = [dict(np.load(out_dir / f"link{i + 1}" / f"link{i + 1}_firmware.npz")) for i in range(n)]
    common = set(t_us.tolist())
    for f in fw:
        common &= set(np.round(f["t"] * 1e6).astype(np.int64).tolist())
    times = np.array(sorted(common), dtype=np.int64)
    if times.size == 0:
        raise FleetError("the vehicles' flight logs and the simulator log share no time stamps")
    rows = [index[int(x)] for x in times]
    merged = {
        "t": times * 1e-6,
        "p_true": truth["p_true"][rows],
        "v_true": truth["v_true"][rows],
        "q_true": truth["q_true"][rows],
        "thrust": truth["thrust"][rows],
    }
    fw_rows = []  # per link: the rows of its log at the common times
    for f in fw:
        ft = {int(x): i for i, x in enumerate(np.round(f["t"] * 1e6).astype(np.int64))}
        fw_rows.append([ft[int(x)] for x in times])
    for key in ("p_ekf", "q_ekf", "p_ctrl", "q_ctrl", "p_target", "q_target"):
        merged[key] = np.stack([f[key][r] for f, r in zip(fw, fw_rows)], axis=1)
    comp_path = out_dir / "companion" / "companion_log.npz"
    if comp_path.exists():
        comp = dict(np.load(comp_path))
        # each step against the truth row nearest its state time (the log grid is 1 / log_rate_hz)
        ct = np.round(comp["t_sckf"] * 1e6).astype(np.int64)
        row = np.clip(np.searchsorted(t_us, ct), 1, len(t_us) - 1)
        row = np.where(np.abs(t_us[row - 1] - ct) <= np.abs(t_us[row] - ct), row - 1, row)
        keep = np.abs(t_us[row] - ct) <= 0.5e6 / sc.sim.log_rate_hz
        for key, value in comp.items():
            merged[key] = value[keep]
        merged["p_true_sckf"] = truth["p_true"][row[keep]]
    latency = np.concatenate([f["correction_latency"] for f in fw]) if fw else np.zeros((0, 2))
    return merged, latency


def check_fleet_scenario(sc: Scenario) -> None:
    """``ValueError`` for a scenario that names its own companion links (a hardware config):
    fleet mode wires the simulated links itself (PX4 SITL ports)."""
    if sc.companion.links:
        raise ValueError(f"companion.links names hardware endpoints ({sc.companion.links[0].url}, ...); "
                         "fleet mode wires the simulated links itself: use a SITL config")


def launch(sc: Scenario, out_dir: Path, speed: float = 1.0, progress=None, python: str = sys.executable,
           companion: bool = True) -> dict:
    """Run the scenario in fleet mode; returns the metrics (also written to ``out_dir``)."""
    check_fleet_scenario(sc)
    out_dir.mkdir(parents=True, exist_ok=True)
    config = out_dir / "scenario.toml"
    config.write_text(dump_toml(sc))
    n = sc.skeleton.n_links
    plant = Plant(sc)
    center = ",".join(f"{x:.6f}" for x in plant.start_center())
    procs = _Processes()
    harness = None
    interrupted = False
    try:
        for i in range(n):
            procs.start(f"link {i + 1}", [python, "-m", "link_firmware_sim", "--config", str(config), "--instance",
                                          str(i), "--out", str(out_dir / f"link{i + 1}")],
                        out_dir / f"link{i + 1}" / "console.log")
        if companion and sc.companion.enabled:
            procs.start("companion", [python, "-m", "companion", "--config", str(config), "--out",
                                      str(out_dir / "companion"), "--start-center", center],
                        out_dir / "companion" / "console.log")
            # Lockstep starts once the companion listens, so that it sees the flight from t = 0.
            _wait_udp_listening([14540 + i for i in range(n)], procs)
        print(endpoint_table(sc), flush=True)
        try:
            harness = FleetHarness(sc, [f"tcpout://127.0.0.1:{4560 + i}" for i in range(n)], plant)
        except PortError as exc:
            procs.check()
            raise FleetError(str(exc)) from None

        def stop_check() -> bool:
            procs.check()  # raises FleetError if a process died
            return False

        try:
            harness.run(sc.duration_s, speed, progress, stop_check)
        except KeyboardInterrupt:
            interrupted = True
            log.warning("interrupted: stopping the fleet")
    finally:
        if harness is not None:
            harness.close()
        procs.stop()
    if harness is None:
        raise FleetError("the simulator never connected to the vehicles")
    if harness.sim_s <= sc.flight_start_s:
        raise FleetError(f"stopped at t = {harness.sim_s:.1f} s, before the metrics window (from "
                         f"{sc.flight_start_s:g} s): no metrics, the vehicles' logs and tlogs are kept")
    truth = harness.truth_log()
    merged, latency = _merge_logs(sc, truth, out_dir)
    metrics = compute_metrics(merged, sc.flight_start_s, plant.rotors.zero_crossings, plant.crashed,
                              plant.crash_reason, harness.sim_s / max(harness.wall_s, 1e-9),
                              sc.companion.enabled and "t_sckf" in merged)
    lat = latency[latency[:, 0] >= sc.flight_start_s, 1] if latency.size else np.zeros(0)
    metrics["correction_latency_ms"] = (
        {"p50": round(float(np.percentile(lat, 50) * 1e3), 3), "p99": round(float(np.percentile(lat, 99) * 1e3), 3),
         "max": round(float(lat.max() * 1e3), 3), "samples": int(lat.size)} if lat.size else None
    )
    metrics.update(scenario=sc.name, seed=sc.seed, duration_s=harness.sim_s, mode="fleet", speed=speed,
                   interrupted=interrupted)
    if n == 3:
        metrics["paper_reference"] = PAPER_THREE_LINK
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    np.savez_compressed(out_dir / "log.npz", **merged)
    write_plots(merged, out_dir)
    (out_dir / "scenario.toml").write_text(dump_toml(replace(sc, duration_s=harness.sim_s)))
    return metrics


"""One fleet run (``python -m sitl launch``) as a :class:`Fleet`: its configs, its processes, the
lockstep flight with its scripted faults, the stop, and its metrics.

:func:`launch` is the whole run: :meth:`Fleet.prepare` (the run folder's configs and the plant),
:meth:`Fleet.start` (the processes, waited for until they listen, and the harness),
:meth:`Fleet.fly` (the lockstep, with the scripted faults at each firmware tick),
:meth:`Fleet.close` (every process stopped, whatever happened) and :meth:`Fleet.results` (the logs
merged and measured; the run folder's ``metrics.json``, ``log.npz``, plots, ``scenario.toml``).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.config import SITL_STATE_PORT, LinkEndpoint
from companion.configfile import dump_toml
from companion.fleetnet.config import new_users_file
from companion.mavlink.signing import new_key_file
from companion.mavlink.transport import PortError
from companion.motion.inverse import InverseModel
from sitl.metrics import PAPER_THREE_LINK, carrying_metrics, compute_metrics
from sitl.plant.plant import Plant
from companion.recording.mcap_log import write_beside_log
from sitl.scenario import Scenario
from sitl.warm import warm_up_kernels

from .fault_socket import FaultSocket
from .faults import FleetFaults, HarnessFault, scripted_faults
from .harness import FleetHarness
from .inject import FailureCommander, enable_failure_injection
from .sim_time import SimTimeWriter
from .task import FleetTask
from .layout import (COMPANION_KERNELS, GCS_PORT, SIM_LINKS, WIRE_COMPANION_SIDE, WIRE_VEHICLE_SIDE, FleetError,
                     check_fleet_scenario, check_instance_offset, endpoint_table, fleet_ports, impaired_links)
from .logs import (companion_summaries, distributed_metrics, fault_report, mavlink_counters, merge_logs,
                   neighbour_camera_metrics)
from .processes import (STARTUP_TIMEOUT_S, Processes, bound_ports, check_ports_free, enter_batch_scheduling,
                        interrupted_once, listening_unix_paths, restore_scheduling, wait_udp_listening)

__all__ = ["Fleet", "launch"]

log = logging.getLogger(__name__)


class Fleet:
    """One fleet run of a scenario (arguments: :func:`launch`)."""

    def __init__(self, sc: Scenario, out_dir: Path, speed: float = 1.0, python: str = sys.executable,
                 companion: bool = True, instance_offset: int = 0, sim_link: str = "tcp",
                 batch_scheduling: bool | None = None, gcs_port: int = GCS_PORT, task: FleetTask | None = None,
                 companion_kernels: str = "compiled"):
        if sim_link not in SIM_LINKS:
            raise ValueError(f"sim_link {sim_link!r}: one of {', '.join(SIM_LINKS)}")
        if companion_kernels not in COMPANION_KERNELS:
            raise ValueError(f"companion_kernels {companion_kernels!r}: one of {', '.join(COMPANION_KERNELS)}")
        check_fleet_scenario(sc)
        check_instance_offset(sc, instance_offset, gcs_port)
        self.sc, self.out_dir, self.speed, self.python = sc, out_dir, speed, python
        self.k, self.sim_link, self.gcs_port = instance_offset, sim_link, gcs_port
        #: what the scenario's kind adds (the chain's: nothing)
        self.task = task if task is not None else FleetTask()
        #: the companion(s) run: asked for, and the scenario has them
        self.companion = companion and self.task.companion_runs(sc)
        self.batch_scheduling = speed <= 0 if batch_scheduling is None else batch_scheduling
        #: the companions' path: their compiled kernels (where numba is installed) or the numpy path
        self.companion_kernels = companion_kernels
        self.n = sc.skeleton.n_links
        #: 0-based links whose onboard wire goes through the impaired wire (``[faults.mavlink]``)
        self.wired = impaired_links(sc) if self.companion else []
        self.procs = Processes()
        self.plant: Plant | None = None
        self.harness: FleetHarness | None = None
        self.sim_time: SimTimeWriter | None = None  # the lockstep's time for the impaired wire
        self.cameras = None  # sitl.cameras.stream.CameraStreamer of a camera scenario
        self.sim_dir: Path | None = None  # the same-host link's sockets
        self.policy_before: int | None = None  # the scheduling policy before SCHED_BATCH
        self.interrupted = False
        self.aborted = ""  # why the fleet stopped early (a process died)
        self.faults: FleetFaults | None = None  # the harness's faults (scripted and asked for at run time)
        self.fault_socket: FaultSocket | None = None  # run-time fault requests (RUN_DIR/faults.sock)
        self.commander = None  # sitl.fleet.inject.FailureCommander of [faults.inject]

    # -- the run folder's configs ----------------------------------------------------------------
    def prepare(self) -> None:
        """The run folder's ``scenario.toml``, ``link.toml`` and ``companion.toml`` (each process
        validates its own part; the companions' trajectory anchored where the simulated chain
        starts), a throwaway signing key or Zenoh users file where the scenario names none, and the
        plant."""
        sc, out_dir, k = self.sc, self.out_dir, self.k
        out_dir.mkdir(parents=True, exist_ok=True)
        if sc.signing.active and not sc.signing.key_file:
            # A throwaway key for this run (never in the repository): the run folder holds it.
            key_file = out_dir / "signing.key"
            new_key_file(key_file, overwrite=True)
            sc = self.sc = replace(sc, signing=replace(sc.signing, key_file=str(key_file.resolve())))
            log.info("signing: a new key for this run in %s", key_file)
        sc.signing.key()  # ValueError now, not in every process, for a missing or unreadable key
        (out_dir / "scenario.toml").write_text(dump_toml(sc))
        self.plant = self.task.plant(sc)
        self.link_config = out_dir / "link.toml"
        self.link_config.write_text(dump_toml(sc.vehicle_setup()))
        anchor = tuple(float(x) for x in self.plant.start_center())
        setup = sc.companion_setup()
        if k:  # the companion listens where this fleet's vehicles send (its defaults are instance 0's)
            cfg = setup.companion
            links = tuple(LinkEndpoint(e.system_id, f"udpin://127.0.0.1:{SITL_STATE_PORT + k + i}")
                          for i, e in enumerate(cfg.endpoints(self.n)))
            zc = setup.zenoh
            setup = replace(setup, companion=replace(cfg, links=links),
                            zenoh=zc if zc.endpoints else replace(zc, base_port=zc.base_port + k))
        # The vision consumer's measurements for the companions: chain cameras that see their neighbours'
        # markers, or what the kind's consumer publishes (a centralised companion opens a Zenoh session for them).
        self.neighbour_cameras = False
        if sc.cameras and sc.companion.neighbour_cameras and self.companion:
            from sitl.cameras.neighbours import neighbour_views  # OpenCV: camera scenarios only

            self.neighbour_cameras = bool(neighbour_views(sc.cameras, sc.markers))
        #: the companions' Zenoh endpoints the vision consumer publishes to
        self.consumer_endpoints: tuple[str, ...] = ()
        if self.companion and sc.cameras and (self.neighbour_cameras or self.task.consumer_publishes):
            zc = setup.zenoh
            if sc.companion.distributed:
                self.consumer_endpoints = tuple(zc.group_endpoint(g) for g in range(len(sc.companion.group_layout(self.n))))
            else:
                setup = replace(setup, zenoh=replace(zc, vision_session=True))
                self.consumer_endpoints = (zc.group_endpoint(0),)
        if (sc.companion.distributed or self.consumer_endpoints) and not sc.zenoh.users_file:
            # The companions (and the vision consumer) authenticate to each other with throwaway credentials
            # of this run: another process on this host cannot join their Zenoh session (zenoh.users_file).
            users_file = out_dir / "zenoh_users.txt"
            new_users_file(users_file, len(sc.companion.group_layout(self.n)), overwrite=True)
            setup = replace(setup, zenoh=replace(setup.zenoh, users_file=str(users_file.resolve())))
        setup = self.task.companion_setup(self, setup)
        # The companion bounds how fast a link's clock (simulated time) can run against its own wall
        # clock: the pace, with room for the catch-up after a slow tick (as fast as it goes: 20).
        rate = 20.0 if self.speed <= 0 else max(2.0, 4.0 * self.speed)
        cfg = setup.companion
        self.companion_setup = replace(setup, companion=replace(cfg, clock_rate_max=max(cfg.clock_rate_max, rate)))
        self.companion_config = out_dir / "companion.toml"
        self.companion_config.write_text(dump_toml(replace(self.companion_setup,
                                                           trajectory=replace(sc.trajectory, anchor_w_m=anchor))))

    # -- the processes ---------------------------------------------------------------------------
    def sim_url(self, i: int, side: str) -> str:
        """Link ``i``'s simulator link as the vehicle (``side`` ``"vehicle"``) or the harness sees it."""
        if self.sim_dir is not None:
            return f"{'unixin' if side == 'vehicle' else 'unix'}://{self.sim_dir / f'link{i + 1}.sock'}"
        return f"{'tcpin' if side == 'vehicle' else 'tcpout'}://127.0.0.1:{4560 + self.k + i}"

    def sim_listening(self, i: int) -> bool:
        """Whether link ``i``'s vehicle listens on its simulator link."""
        if self.sim_dir is not None:
            return str(self.sim_dir / f"link{i + 1}.sock") in listening_unix_paths()
        return 4560 + self.k + i in bound_ports("tcp")

    def start_vehicle(self, i: int, name: str, folder: str, standby: bool = False) -> None:
        k, out_dir = self.k, self.out_dir
        argv = [self.python, "-m", "link_firmware_sim", "--config", str(self.link_config), "--instance", str(i),
                "--out", str(out_dir / folder), "--log-rate", f"{self.sc.sim.log_rate_hz:g}",
                # a restarted Pixhawk keeps its parameters (the first process's file)
                "--params", str(out_dir / f"link{i + 1}" / f"link{i + 1}_params.json"),
                "--sim-url", self.sim_url(i, "vehicle"),
                "--gcs-url", f"udpout://127.0.0.1:{self.gcs_port}?bind={18570 + k + i}",
                # its onboard traffic to the companion, or through the impaired wire
                "--onboard-url", f"udpout://127.0.0.1:{(WIRE_VEHICLE_SIDE if i in self.wired else SITL_STATE_PORT) + k + i}"
                                 f"?bind={14580 + k + i}"]
        self.procs.start(name, argv + (["--standby"] if standby else []), out_dir / folder / "console.log",
                         stdin_pipe=standby)

    @staticmethod
    def companion_name(group: int | None) -> str:
        """The process name of group ``group``'s companion (0-based; ``None``: the one companion)."""
        return "companion" if group is None else f"companion of group {group + 1}"

    @staticmethod
    def companion_folder(group: int | None) -> str:
        """The run folder of group ``group``'s companion (0-based; ``None``: the one companion)."""
        return "companion" if group is None else f"companion-g{group + 1}"

    def start_companion(self, group: int | None, folder: str, name: str | None = None) -> None:
        argv = [self.python, "-m", "companion", "--config", str(self.companion_config), "--out",
                str(self.out_dir / folder)]
        # The numpy path stands in for an onboard computer without numba: the compiled kernels off.
        env = dict(os.environ, SKELETON_JIT="0") if self.companion_kernels == "numpy" else None
        self.procs.start(name or self.companion_name(group), argv + ([] if group is None else ["--group", str(group + 1)]),
                         self.out_dir / folder / "console.log", env=env)

    def start_wire(self) -> None:
        """The impaired wire (:mod:`sitl.fleet.wire`) between the wired links and the companion."""
        k, m = self.k, self.sc.faults.mavlink
        # its delays are simulated time: the lockstep's, published at every firmware tick
        self.sim_time = SimTimeWriter(self.out_dir / "wire" / "sim_time")
        pairs = [f"{WIRE_VEHICLE_SIDE + k + i}:{SITL_STATE_PORT + k + i}:{WIRE_COMPANION_SIDE + k + i}" for i in self.wired]
        self.procs.start("wire", [self.python, "-m", "sitl.fleet.wire", *(a for p in pairs for a in ("--pair", p)),
                                  "--loss", f"{m.loss:g}", "--delay-ms", f"{m.delay_ms:g}", "--jitter-ms",
                                  f"{m.jitter_ms:g}", "--seed", str(self.sc.seed),
                                  "--stats", str(self.out_dir / "wire" / "wire_stats.json"),
                                  "--sim-time", str(self.sim_time.path)],
                         self.out_dir / "wire" / "console.log")
        wait_udp_listening([WIRE_VEHICLE_SIDE + k + i for i in self.wired], self.procs, "the impaired wire")

    def start_cameras(self) -> None:
        """The camera streamer (renders and publishes; :mod:`sitl.cameras.stream`) and the vision
        consumer connected to it, both with the companions' Zenoh credentials (``companion.toml``'s
        ``[zenoh]``, the run's throwaway users file included); returns once the consumer's
        subscription matches every key."""
        from sitl.cameras.stream import CameraStreamer  # OpenCV, rendering and Zenoh only for camera scenarios

        sc, plant, out_dir = self.sc, self.plant, self.out_dir
        streamer = CameraStreamer(sc, plant.model.model, plant.model.data, plant.dt, sc.zenoh.runtime_env(),
                                  fleet=self.companion_setup.zenoh, fleet_file=str(self.companion_config.resolve()),
                                  companion_endpoints=self.consumer_endpoints, neighbours=self.neighbour_cameras)
        try:
            config = out_dir / "vision.toml"
            config.write_text(dump_toml(self.task.consumer_setup(self, streamer.consumer_setup())))
            self.procs.start("vision consumer", [self.python, "-m", "companion.vision", "--config", str(config),
                                                 "--out", str(out_dir / "vision")], out_dir / "vision" / "console.log")
            try:
                streamer.wait_for_subscriber(STARTUP_TIMEOUT_S, self.procs.check)
            except TimeoutError as exc:
                raise FleetError(f"the vision consumer: {exc}") from None
        except BaseException:
            streamer.close()
            raise
        self.cameras = streamer

    def start(self) -> None:
        """Every process of the fleet, each waited for until it listens, then the harness connected
        to the vehicles (:class:`FleetError` if one died or never listened)."""
        sc, k, n = self.sc, self.k, self.n
        ports = fleet_ports(n, k, self.sim_dir is None, self.companion, self.wired)
        if self.companion and sc.companion.distributed:  # (the group companions' Zenoh listeners)
            zc = self.companion_setup.zenoh
            for g in range(len(sc.companion.group_layout(n))):
                host, _, port = zc.group_endpoint(g).rpartition(":")
                if host.startswith("tcp/") and port.isdigit():
                    ports[("tcp", int(port))] = f"the Zenoh session of group {g + 1}'s companion"
        check_ports_free(ports)
        if self.wired:
            self.start_wire()
        inject = sc.faults.inject
        if inject.link:  # the operator enabled failure injection on that vehicle (PX4: SYS_FAILURE_EN)
            enable_failure_injection(self.out_dir / f"link{inject.link}" / f"link{inject.link}_params.json")
        for i in range(n):
            self.start_vehicle(i, f"link {i + 1}", f"link{i + 1}")
        self.faults = FleetFaults(self)
        for fault in scripted_faults(sc):  # (a scripted restart's vehicle process is loaded now)
            if fault.kind == "companion_off" and not self.companion:
                log.info("launched without the companion: faults.kill_companion_group is not played")
                continue
            self.faults.add(fault, 0.0)
        if self.companion:
            if sc.companion.distributed:
                for g in range(len(sc.companion.group_layout(n))):
                    self.start_companion(g, self.companion_folder(g))
            else:
                self.start_companion(None, self.companion_folder(None))
            # Lockstep starts once the companion listens, so that it sees the flight from t = 0.
            wait_udp_listening([SITL_STATE_PORT + k + i for i in range(n)], self.procs)
        if sc.cameras:
            self.start_cameras()
        print(endpoint_table(replace(sc, zenoh=self.companion_setup.zenoh), instance_offset=k, sim_dir=self.sim_dir,
                             gcs_port=self.gcs_port), flush=True)
        if self.cameras is not None:
            print(f"cameras: Zenoh {', '.join(self.cameras.endpoints.values())}, keys "
                  f"{self.cameras.prefix}/camera/<vehicle>/image (consumer: python -m companion.vision --config "
                  f"{self.out_dir / 'vision.toml'})", flush=True)
        try:
            self.harness = FleetHarness(sc, [self.sim_url(i, "harness") for i in range(n)], self.plant,
                                        truth_stream=self.out_dir / "truth.stream")
        except PortError as exc:
            self.procs.check()
            raise FleetError(str(exc)) from None
        self.harness.on_wait = self.procs.check  # (a vehicle that died is reported, not a silent link)
        if self.cameras is not None:
            self.harness.tick_hooks.append(self.cameras.on_tick)
        self.task.start(self)
        if inject.link:
            self.commander = FailureCommander(sc, 18570 + k + inject.link - 1)
        try:
            self.fault_socket = FaultSocket(self.out_dir / "faults.sock")
        except OSError as exc:  # (a run folder whose path is too long for a socket's)
            log.warning("no run-time faults for this fleet: %s: %s", self.out_dir / "faults.sock", exc)
        else:
            print(f"faults at run time: python -m sitl fault vehicle-off {self.out_dir} --link N "
                  "[--restart-after S]", flush=True)

    # -- the flight and its faults --------------------------------------------------------------
    def on_firmware_tick(self) -> bool:
        """Every firmware tick of the lockstep: the scripted faults due, then the processes checked
        (:class:`FleetError` if one died, noticed within 20 ms); never asks the lockstep to stop."""
        t = self.plant.time_s
        if self.sim_time is not None:
            self.sim_time.publish(t)
        if self.fault_socket is not None:
            self.fault_socket.serve(self._fault_request, t)
        self.faults.tick(t)
        if self.commander is not None:
            self.commander.tick(t)
        self.procs.check(every_s=0.02)
        return False

    def _fault_request(self, request, t: float) -> dict:
        """A run-time fault request (:mod:`.fault_socket`): played through :attr:`faults` as the
        scripted ones are; the reply says so or why not."""
        try:
            tl = self.faults.add(HarnessFault.from_request(request), t)
        except ValueError as exc:
            log.warning("fault request refused at t = %.2f s: %s", t, exc)
            return {"accepted": False, "error": str(exc), "t_s": round(t, 3)}
        log.warning("fault request at t = %.2f s: %s", t, {k: v for k, v in tl.items() if k != "source"})
        return {"accepted": True, "t_s": round(t, 3), **tl}

    def fly(self, progress=None) -> None:
        """The lockstep for the scenario's duration; a Ctrl-C or a process that died ends it early
        (:attr:`interrupted`, :attr:`aborted`): what was flown is measured all the same."""
        try:
            self.harness.run(self.sc.duration_s, self.speed, progress, self.on_firmware_tick)
        except KeyboardInterrupt:
            self.interrupted = True
            log.warning("interrupted: stopping the fleet")
        except FleetError as exc:
            self.aborted = str(exc)
            log.error("the fleet stopped at t = %.2f s: %s", self.harness.sim_s, self.aborted)

    def close(self) -> None:
        """The harness's links closed, every process stopped (the vision consumer first: it drains
        the frames in flight, and the neighbour poses it publishes on its way out still reach the
        companions), the cameras closed, the sockets' folder removed and the scheduling policy
        restored."""
        if self.harness is not None:
            self.harness.close()
        if self.commander is not None:
            self.commander.close()
        if self.fault_socket is not None:
            self.fault_socket.close()
        try:
            self.procs.stop(self.harness.sim_s if self.harness is not None else 0.0, first=("vision consumer",))
        finally:
            if self.cameras is not None:
                self.cameras.close()
            if self.sim_time is not None:
                self.sim_time.close()
            if self.sim_dir is not None:
                shutil.rmtree(self.sim_dir, ignore_errors=True)
            restore_scheduling(self.policy_before)

    def run(self, progress=None, plots: bool = True) -> dict:
        """The whole run (module docstring); returns the metrics."""
        self.prepare()
        # The firmware's and the companion's compiled kernels: compiled (or loaded) here once, so that the
        # vehicles and the companions load numba's on-disk cache instead of each compiling them.
        warm_up_kernels("fleet", cpg=self.sc.trajectory.kind == "cpg",
                        companion=self.companion and self.companion_kernels == "compiled")
        # the same-host link's sockets: a private (0700) folder of its own, short enough for a socket path
        # (made after the last step that can fail before the ``try`` that removes it)
        self.sim_dir = Path(tempfile.mkdtemp(prefix="skeleton-sim-")) if self.sim_link == "unix" else None
        self.policy_before = enter_batch_scheduling() if self.batch_scheduling else None
        if self.policy_before is not None:
            log.info("the harness and the fleet's processes run under SCHED_BATCH (no wake-up preemption)")
        with interrupted_once() as flown:
            try:
                self.start()
                self.fly(progress)
            finally:
                flown()
                self.close()
            return self.results(plots)

    # -- the metrics -----------------------------------------------------------------------------
    def results(self, plots: bool = True) -> dict:
        """The logs merged and measured; ``metrics.json``, ``log.npz``, ``run.mcap``, ``vision.npz`` (cameras),
        the plots and the flown ``scenario.toml`` in the run folder. :class:`FleetError` for a run
        stopped before the metrics' window, or (after writing them) for one a process cut short."""
        sc, harness, plant, out_dir, n = self.sc, self.harness, self.plant, self.out_dir, self.n
        aborted = self.aborted
        if harness is None:
            raise FleetError("the simulator never connected to the vehicles")
        if harness.sim_s <= sc.flight_start_s:
            raise FleetError(f"{aborted + '; ' if aborted else ''}stopped at t = {harness.sim_s:.1f} s, before the "
                             f"metrics window (from {sc.flight_start_s:g} s): no metrics, the vehicles' logs and tlogs "
                             "are kept")
        merged, latency, missing = merge_logs(sc, harness.truth_log(), out_dir)
        plant.crash.check_logged(merged["t"], merged["p_true"], merged["q_true"], merged["q_target"])
        metrics = compute_metrics(merged, sc.flight_start_s, plant.rotors.zero_crossings, plant.crashed,
                                  plant.crash_reason, harness.sim_s / max(harness.wall_s, 1e-9),
                                  sc.companion.enabled and "p_corr_sckf" in merged,
                                  groups=sc.companion.group_layout(n), resting=sc.trajectory.kind == "rest",
                                  motion=sc.motion if sc.trajectory.kind == "cpg" else None,
                                  fault_windows=self.faults.windows(harness.sim_s),
                                  rotor_limit_s=plant.rotors.limit_s, took_off=plant.took_off,
                                  crash_time_s=plant.crash_time_s)
        lat = latency[latency[:, 0] >= sc.flight_start_s, 1] if latency.size else np.zeros(0)
        metrics["correction_latency_ms"] = (
            {"p50": round(float(np.percentile(lat, 50) * 1e3), 3), "p99": round(float(np.percentile(lat, 99) * 1e3), 3),
             "max": round(float(lat.max() * 1e3), 3), "samples": int(lat.size)} if lat.size else None
        )
        metrics.update(scenario=sc.name, seed=sc.seed, duration_s=harness.sim_s, mode="fleet", speed=self.speed,
                       sim_link=self.sim_link, scheduling="batch" if self.policy_before is not None else "default",
                       companion_kernels=self.companion_kernels if self.companion else None,
                       interrupted=self.interrupted, aborted=aborted or None, missing_flight_logs=missing)
        if sc.companion.distributed and self.companion:
            metrics["distributed"] = distributed_metrics(sc, merged, companion_summaries(out_dir),
                                                         self.faults.first("companion_off"))
        if sc.trajectory.feedforward and self.companion:
            metrics["carrying"] = carrying_metrics(companion_summaries(out_dir))
        metrics["mavlink"] = mavlink_counters(out_dir)
        report = fault_report(sc, merged, out_dir, self.faults, self.wired,
                              self.commander.sent if self.commander is not None else None,
                              self.fault_socket.counts if self.fault_socket is not None else None)
        if report:
            metrics["faults"] = report
        if n == 3 and sc.kind == "chain":
            metrics["paper_reference"] = PAPER_THREE_LINK
        if self.cameras is not None:
            from sitl.cameras.stream import fleet_vision_metrics

            metrics["vision"], vision_arrays = fleet_vision_metrics(self.cameras, out_dir / "vision", sc.flight_start_s)
            np.savez_compressed(out_dir / "vision.npz", **vision_arrays)
        if self.neighbour_cameras and self.consumer_endpoints:
            metrics["neighbour_cameras"] = neighbour_camera_metrics(out_dir, companion_summaries(out_dir))
        metrics.update(self.task.metrics(self, plots))
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        np.savez_compressed(out_dir / "log.npz", **merged)
        write_beside_log(out_dir)
        if plots:
            from sitl.plots import write_plots  # (matplotlib loaded after the flight, and only for plots)

            if sc.trajectory.kind == "cpg":
                period_s = 1.0 / InverseModel.load(sc.motion.model).steady.cpg_params.frequency_hz
                write_plots(merged, out_dir, motion=sc.motion, period_s=period_s)
            else:
                write_plots(merged, out_dir)
        (out_dir / "scenario.toml").write_text(dump_toml(replace(sc, duration_s=harness.sim_s)))
        if aborted:
            raise FleetError(f"{aborted}; the {harness.sim_s:.1f} s flown are measured in {out_dir / 'metrics.json'}")
        return metrics


def launch(sc: Scenario, out_dir: Path, speed: float = 1.0, progress=None, python: str = sys.executable,
           companion: bool = True, plots: bool = True, instance_offset: int = 0, sim_link: str = "tcp",
           batch_scheduling: bool | None = None, gcs_port: int = GCS_PORT, task: FleetTask | None = None,
           companion_kernels: str = "compiled") -> dict:
    """Run the scenario in fleet mode; returns the metrics (also written to ``out_dir``; the PNG plots
    too unless ``plots`` is false). ``instance_offset`` K: link ``i`` takes PX4 SITL instance
    K + i's ports (simulator TCP 4560+K+i, onboard UDP 14540+K+i from 14580+K+i, GCS from
    18570+K+i, the impaired wire's 15540+K+i and 15580+K+i) and the group companions Zenoh's
    ``base_port`` + K + g, so that fleets with offsets n apart run side by side on one host; the
    system ids stay 1..n. ``sim_link``: ``"tcp"`` (PX4's simulator API on TCP 4560+K+i) or
    ``"unix"`` (the same-host link, :mod:`link_firmware_sim.vehicle.simlink`). ``batch_scheduling``: the
    harness and every process of the fleet under SCHED_BATCH
    (:func:`~sitl.fleet.processes.enter_batch_scheduling`); ``None``: when unpaced (``speed`` 0),
    where only throughput counts (the metrics say which: ``scheduling``). ``gcs_port``: the UDP
    port every vehicle sends its ground-station traffic to. ``task``: what the scenario's kind adds
    (:class:`~sitl.fleet.task.FleetTask`; default: the chain's). ``companion_kernels``: the
    companions run their ``"compiled"`` kernels (where numba is installed; the daemon's default) or
    the ``"numpy"`` path, as an onboard computer without numba does (``SKELETON_JIT=0``)."""
    fleet = Fleet(sc, out_dir, speed=speed, python=python, companion=companion, instance_offset=instance_offset,
                  sim_link=sim_link, batch_scheduling=batch_scheduling, gcs_port=gcs_port, task=task,
                  companion_kernels=companion_kernels)
    return fleet.run(progress, plots)

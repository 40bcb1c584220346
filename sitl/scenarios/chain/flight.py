"""A chain flight in batch mode (``python -m sitl fly``): one flight in one process, its metrics and artefacts.

:func:`fly` runs a :class:`~sitl.runner.BatchRunner` (physics, every link's firmware and the
companion engine on one clock) for the scenario's duration; its ``[[cameras]]`` and a video are
tick hooks (:class:`~sitl.cameras.flight.FlightCameras`), its ``[faults]`` the runner's own. The
run folder receives ``metrics.json``, ``log.npz`` (truth, EKF, control estimate, targets, thrusts
and cable forces at the log rate; the companion's step log with constraint errors and estimates
at its steps), ``scenario.toml`` (the resolved configuration), ``vision.npz`` with cameras, and
PNG plots.
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.configfile import dump_toml
from companion.trajectory import CpgChainTrajectory

from sitl.cameras.flight import FlightCameras
from sitl.metrics import PAPER_THREE_LINK, carrying_metrics, compute_metrics, reboot_timeline, vehicle_down_windows
from sitl.runner import BatchRunner
from sitl.scenario import Scenario

__all__ = ["fly"]

log = logging.getLogger(__name__)


def fly(
    scenario: Scenario,
    out_dir: Path | None,
    *,
    sckf: bool | None = None,
    selective_mapping: bool | None = None,
    progress=None,
    plots: bool = True,
    video: Path | None = None,
) -> dict:
    """Run ``scenario`` for its ``duration_s``; returns the metrics (and writes them to ``out_dir``).

    ``video``: write an MP4 of the flight there (:mod:`sitl.cameras.video`). A scenario with cameras
    renders them and runs the vision pipeline on their frames (:mod:`sitl.cameras.vision_log`):
    ``metrics["vision"]`` and ``vision.npz``; a camera seeing a neighbouring link's marker feeds the
    companion's step (``metrics["neighbour_cameras"]``). ``sckf``, ``selective_mapping``: the command line's
    flight options (:func:`~sitl.scenario.with_options`)."""
    runner = BatchRunner(scenario, sckf=sckf, selective_mapping=selective_mapping)
    sc = runner.scenario
    neighbours = _neighbour_cameras(sc, runner)
    with FlightCameras(runner, video, consumers=(neighbours.on_frame,) if neighbours else ()) as vision:
        runner.run(sc.duration_s, progress=progress)
    arrays = runner.arrays()
    metrics = compute_metrics(
        arrays,
        sc.flight_start_s,
        runner.rotors.zero_crossings,
        runner.crashed,
        runner.crash_reason,
        runner.sim_s / runner.wall_s if runner.wall_s > 0 else float("inf"),
        sc.companion.enabled,
        groups=runner.groups,
        resting=sc.trajectory.kind == "rest",
        motion=sc.motion if sc.trajectory.kind == "cpg" else None,
        fault_windows=vehicle_down_windows(runner.link_fault, runner.sim_s),
        rotor_limit_s=runner.rotors.limit_s,
        took_off=runner.plant.took_off,
        crash_time_s=runner.plant.crash_time_s,
    )
    metrics["scenario"] = sc.name
    metrics["seed"] = sc.seed
    metrics["duration_s"] = runner.sim_s
    metrics["selective_mapping"] = sc.firmware.allocation.selective_mapping
    metrics["corrections_rejected"] = runner.corrections_rejected
    # the firmware's own account (a fleet's linkN_ports.json), since each link's last boot
    metrics["thrust_limit"] = [fw.thrust_limit.report() for fw in runner.firmware]
    if sc.faults.touches_gps:  # what each link's firmware made of it (GPS health)
        metrics.setdefault("faults", {})["gps"] = {
            "link": sc.faults.gps.link, "firmware": [fw.gps_report(runner.sim_s) for fw in runner.firmware]}
    if runner.link_fault:
        metrics.setdefault("faults", {})["link_reboot"] = reboot_timeline(runner.link_fault, arrays)
    if runner.failures is not None:  # what the vehicle's failure filter did ([faults.inject])
        metrics.setdefault("faults", {})["inject"] = {"link": sc.faults.inject.link, **runner.inject_log,
                                                      **runner.failures.report()}
    if sc.trajectory.feedforward and sc.companion.enabled:
        metrics["carrying"] = carrying_metrics({"companion" if e.group is None else f"companion-g{e.group + 1}": e.summary()
                                                for e in runner.engines})
    if sc.skeleton.n_links == 3:
        metrics["paper_reference"] = PAPER_THREE_LINK
    metrics.update(vision.metrics())
    if neighbours:
        metrics["neighbour_cameras"] = neighbours.metrics()
    if runner.crashed:
        log.warning("crash: %s", runner.crash_reason)
    elif not runner.plant.took_off and sc.trajectory.kind != "rest":
        log.warning("the chain never took off (on the ground for the whole flight)")
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        np.savez_compressed(out_dir / "log.npz", **arrays)
        if vision.log is not None:
            np.savez_compressed(out_dir / "vision.npz", **vision.log.arrays())
        vision.save_frames(out_dir)
        (out_dir / "scenario.toml").write_text(dump_toml(replace(sc, duration_s=runner.sim_s)))
        if plots:
            from sitl.plots import write_plots  # (matplotlib loaded after the flight, and only for plots)

            cpg = isinstance(runner.trajectory, CpgChainTrajectory)
            write_plots(arrays, out_dir, motion=sc.motion if cpg else None,
                        period_s=runner.trajectory.generator.period_s if cpg else 4.0)
    return metrics


def _neighbour_cameras(sc: Scenario, runner: BatchRunner):
    """The chain cameras that see a neighbour's marker, feeding the companion's step
    (:mod:`sitl.cameras.neighbours`), when the scenario has any (else ``None``: OpenCV is not
    imported for a flight without cameras)."""
    if not sc.cameras or not sc.companion.enabled:
        return None
    from sitl.cameras.neighbours import NeighbourCameras

    return NeighbourCameras(sc.cameras, sc.markers, runner.engines) or None

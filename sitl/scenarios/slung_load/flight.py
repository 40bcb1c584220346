"""The slung-load flight: three (or more) vehicles of this stack carry a box by cables in MuJoCo,
the load's pose estimated from the vehicles' cameras.

**Flight** (:class:`SlungLoadTask` on a :class:`~sitl.runner.BatchRunner`): the runner starts as
the scenario's vehicles; the task puts in the slung-load model (:mod:`.model`: the vehicles, the
load, the cables) and starts the firmware again on it: the vehicles start hovering in formation
with the load hanging at rest below. The companion engine arms them (its chain constraint is off:
``companion.enabled = false``) and sends them the formation's targets (``trajectory.kind =
"formation"``: :class:`companion.load.formation.FormationTrajectory`, the report's 2 m circle at
1.5 m/s, yawing with it, with the cables' feed-forward force), as the companion daemon does.

**Estimation** (:class:`~.estimation.LoadEstimation`, as the companion would run it): a tick hook
beside the flight, fed every delivered camera frame (:class:`~sitl.cameras.flight.FlightCameras`).

**Outputs** (:func:`fly_slung_load`): ``metrics.json`` with ``load_pose_err`` (EKF, UKF,
unfiltered: position RMS [m], orientation RMS [deg], after ``load.settle_s``), the per-PnP-method
table (``vision.pnp``: every method on every frame against the truth, the report's Figs. 3, 7, 8),
the detection rate, detection + PnP time per frame, the filters' counters and pose NEES, the
real-time factor; ``log.npz``, ``load.npz``, ``vision.npz``, ``scenario.toml``; plots
``load_pose_error.png`` (Figs. 4, 9) and ``pnp_error.png`` (Figs. 3, 7, 8) (:mod:`.plots`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.config import project
from companion.configfile import dump_toml
from companion.trajectory import planned_positions
from sitl.cameras.flight import FlightCameras
from sitl.cameras.scene import SceneConfig
from sitl.runner import BatchRunner
from sitl.scenario import Scenario
from sitl.task import Task

from .config import SlungLoadScenario
from .estimation import LoadEstimation
from .model import put_in
from .plots import write_load_plots

__all__ = ["SlungLoadTask", "slung_load_runner", "fly_slung_load"]

log = logging.getLogger(__name__)


class SlungLoadTask(Task):
    """The slung-load model in place of the chain's (module docstring)."""

    def __init__(self, scenario: SlungLoadScenario):
        self.scenario = scenario

    def initialize(self, runner) -> None:
        """The runner flies the slung-load scenario on its model from now on; every vehicle's
        firmware starts again there (hovering, the load hanging below)."""
        runner.scenario = self.scenario
        put_in(runner.plant, self.scenario)
        runner.start_firmware()


def vehicles_scenario(scenario: SlungLoadScenario) -> Scenario:
    """The slung-load scenario's vehicles as a chain scenario, without cameras nor scene (its
    companion setup, ``[load]`` and ``trajectory.kind = "formation"`` included): what the plant is
    built from before the slung-load model goes in."""
    return replace(project(scenario, Scenario), kind="chain", cameras=(), markers=(), scene=SceneConfig())


def slung_load_runner(scenario: SlungLoadScenario) -> BatchRunner:
    """A runner of the slung-load scenario: built as its vehicles' chain scenario
    (:func:`vehicles_scenario`), then :class:`SlungLoadTask` puts in the slung-load model."""
    return BatchRunner(vehicles_scenario(scenario), task=SlungLoadTask(scenario))


def fly_slung_load(scenario: SlungLoadScenario, out_dir: Path | None, *, progress=None, plots: bool = True,
                   video: Path | None = None) -> dict:
    """Fly the slung-load scenario for its ``duration_s``; returns the metrics (and writes the
    run folder's files when ``out_dir`` is given). ``video``: an MP4 of the flight."""
    runner = slung_load_runner(scenario)
    sc = runner.scenario
    estimation = LoadEstimation(runner, sc.duration_s)
    runner.tick_hooks.append(estimation.on_tick)
    with FlightCameras(runner, video, consumers=(estimation.on_frame,)) as vision:
        runner.run(sc.duration_s, progress=progress)
    arrays = runner.arrays()
    metrics = {"scenario": sc.name, "seed": sc.seed, "duration_s": runner.sim_s,
               "took_off": runner.plant.took_off, "crashed": runner.crashed,
               "crash_reason": runner.crash_reason,
               "realtime_factor": runner.sim_s / runner.wall_s if runner.wall_s > 0 else None}
    metrics.update(estimation.metrics())
    metrics.update(vision.metrics())
    if vision.rig is not None:
        metrics["load_vision"]["render_ms_per_frame"] = metrics["vision"]["render_ms_per_frame"]
        _add_spikes(metrics["vision"], vision.log)
    if "t" in arrays:  # the vehicles' tracking of the formation (truth against target)
        w = arrays["t"] >= sc.load.settle_s
        err = np.linalg.norm(arrays["p_true"][w] - planned_positions(arrays)[w], axis=-1)
        metrics["vehicle_track_true_rms_m"] = [float(np.sqrt(np.mean(e**2))) for e in err.T]
        est_err = np.linalg.norm(arrays["p_true"][w] - arrays["p_ekf"][w], axis=-1)
        metrics["vehicle_ekf_err_rms_m"] = [float(np.sqrt(np.mean(e**2))) for e in est_err.T]
    if runner.crashed:
        log.warning("crash: %s", runner.crash_reason)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=_json_default) + "\n")
        np.savez_compressed(out_dir / "log.npz", **arrays)
        np.savez_compressed(out_dir / "load.npz", **estimation.arrays())
        if vision.log is not None:
            np.savez_compressed(out_dir / "vision.npz", **vision.log.arrays())
        vision.save_frames(out_dir)
        (out_dir / "scenario.toml").write_text(dump_toml(replace(sc, duration_s=runner.sim_s)))
        if plots:
            write_load_plots(estimation.arrays(), vision.log.arrays() if vision.log is not None else None, out_dir,
                             sc.load.settle_s)
    return metrics


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(type(o))


def _add_spikes(vision_metrics: dict, vlog, spike_m: float = 0.5) -> None:
    """Per PnP method: the count of position errors above ``spike_m`` (the report's P3P spikes)
    and the marker's median side in the image at them."""
    a = vlog.arrays()
    for j, m in enumerate(a["vision_methods"]):
        sel = a["vision_method"] == j
        big = sel & (a["vision_pos_err_m"] > spike_m)
        row = vision_metrics["pnp"][str(m)]
        row["spikes_over_0_5_m"] = int(big.sum())
        row["side_px_median"] = float(np.median(a["vision_side_px"][sel])) if sel.any() else None

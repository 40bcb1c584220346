"""Batch mode (``python -m sitl fly``): one flight of a scenario in one process, its metrics and artefacts.

:func:`fly` runs a :class:`~sitl.runner.BatchRunner` (physics, every link's firmware and the
companion engine on one clock) for the scenario's duration. The run folder receives
``metrics.json``, ``log.npz`` (truth, EKF, control estimate, targets, thrusts and cable forces
at the log rate; the companion's step log with constraint errors and estimates at its steps),
``scenario.toml`` (the resolved configuration) and PNG plots.
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.configfile import dump_toml
from companion.trajectory import CpgChainTrajectory

from .metrics import PAPER_THREE_LINK, compute_metrics
from .plots import write_plots
from .runner import BatchRunner
from .scenario import Scenario

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
) -> dict:
    """Run ``scenario`` for its ``duration_s``; returns the metrics (and writes them to ``out_dir``)."""
    runner = BatchRunner(scenario, sckf=sckf, selective_mapping=selective_mapping)
    sc = runner.scenario
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
    )
    metrics["scenario"] = sc.name
    metrics["seed"] = sc.seed
    metrics["duration_s"] = runner.sim_s
    metrics["selective_mapping"] = sc.firmware.allocation.selective_mapping
    metrics["corrections_rejected"] = runner.corrections_rejected
    if sc.faults.gps.link:  # what each link's firmware made of the glitch (GPS health)
        metrics["faults"] = {"gps": {"link": sc.faults.gps.link,
                                     "firmware": [fw.gps_health.report(runner.sim_s) for fw in runner.firmware]}}
    if sc.skeleton.n_links == 3:
        metrics["paper_reference"] = PAPER_THREE_LINK
    if runner.crashed:
        log.warning("crash: %s", runner.crash_reason)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        np.savez_compressed(out_dir / "log.npz", **arrays)
        (out_dir / "scenario.toml").write_text(dump_toml(replace(sc, duration_s=runner.sim_s)))
        if plots:
            cpg = isinstance(runner.trajectory, CpgChainTrajectory)
            write_plots(arrays, out_dir, motion=sc.motion if cpg else None,
                        period_s=runner.trajectory.generator.period_s if cpg else 4.0)
    return metrics

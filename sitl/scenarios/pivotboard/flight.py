"""A pivotboard run: the CPG of thesis sec. 4.3.3 drives the foot plates' servos of the MuJoCo
board (:class:`~sitl.scenarios.ground.run.GroundRun`: the loop, {B}'s velocities, the metrics).

:class:`PivotCpg` holds the CPG's state: its targets are ``(theta_r, theta_l)``; it advances with
the command's ``A``, ``B`` and ``v_dot_d`` (the phase difference is the map's while speeding up,
zero while slowing down).

**Outputs** (:func:`fly_pivotboard`): ``metrics.json`` (per command, the mean and standard
deviation of ``v_x``, ``v_y``, ``omega`` in {B} from ``settle_s`` after it starts; the distance,
path length and heading change; the servos' RMS tracking error), ``pivotboard.npz`` (the log),
``pivotboard.png`` (the path, the velocities).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from companion.motion.ground_cpgs import PivotCpgState, pivot_joint_angles, pivot_step

from ..ground.run import GroundRun, run_metrics, write_run
from .config import PivotCommand, PivotScenario
from .model import PivotModel

__all__ = ["PivotCpg", "pivot_run", "fly_pivotboard"]


class PivotCpg:
    """The pivotboard's CPG driving the plates' servos (module docstring)."""

    axes = {"plates": [0, 1]}

    def __init__(self, sc: PivotScenario):
        self.params = sc.cpg
        self.state = PivotCpgState.at_rest()
        self.period_s = 1.0 / sc.cpg.frequency_hz

    def targets(self) -> np.ndarray:
        return pivot_joint_angles(self.state)

    def advance(self, command: PivotCommand, dt_s: float) -> None:
        self.state = pivot_step(self.state, self.params, math.radians(command.A_deg), math.radians(command.B_deg),
                                command.v_dot_d_m_s2, dt_s)


def pivot_run(sc: PivotScenario) -> GroundRun:
    """A run of the scenario, not started."""
    return GroundRun(sc, PivotModel(sc), PivotCpg(sc))


def fly_pivotboard(sc: PivotScenario, out_dir: Path | None, *, progress=None, plots: bool = True) -> dict:
    """Run the scenario; returns the metrics (and writes the run folder when ``out_dir`` is given)."""
    run = pivot_run(sc)
    run.run(progress)
    metrics = run_metrics(sc, run.arrays(), run.wall_s, run.cpg.axes)
    if out_dir is not None:
        write_run(sc, run, metrics, out_dir, "pivotboard", plots)
    return metrics

"""A pivotboard run: the CPG of thesis sec. 4.3.3 drives the foot plates' servos of the MuJoCo
board (:class:`~sitl.scenarios.ground.run.GroundRun`: the loop, {B}'s velocities, the metrics).

:class:`PivotCpg` holds the CPG's state: its targets are ``(theta_r, theta_l)``; it advances with
the command's ``A``, ``B`` and ``v_dot_d`` (the phase difference is the map's while speeding up,
zero while slowing down), or with a motion command those of its control (:mod:`.control`).

**Outputs** (:func:`fly_pivotboard`): ``metrics.json`` (per command, the mean and standard
deviation of ``v_x``, ``v_y``, ``omega`` in {B} from ``settle_s`` after it starts; the distance,
path length and heading change; the servos' RMS tracking error; for motion commands their
tracking errors as the thesis reports them), ``pivotboard.npz`` (the log),
``pivotboard.png`` (the path, the velocities).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from companion.motion.ground_cpgs import PivotCpgState, pivot_joint_angles, pivot_step

from ..ground.control import PeriodClock
from ..ground.run import GroundRun, fly_ground, period_acceleration, speed_error
from .config import PivotCommand, PivotScenario
from .model import PivotModel

__all__ = ["PivotCpg", "pivot_run", "fly_pivotboard"]


class PivotCpg:
    """The pivotboard's CPG driving the plates' servos (module docstring); with motion commands,
    their control (:class:`~.control.MotionControl`) sets the inputs at every period boundary."""

    axes = {"plates": [0, 1]}

    def __init__(self, sc: PivotScenario, robot: PivotModel):
        self.params = sc.cpg
        self.state = PivotCpgState.at_rest()
        self.period_s = 1.0 / sc.cpg.frequency_hz
        self.control = None
        if any(c.mode != "cpg" for c in sc.commands):
            from .control import MotionControl

            self.control = MotionControl(sc, robot)
        self.clock = PeriodClock(self.period_s)
        self._inputs = (0.0, 0.0, 0.0)

    def targets(self) -> np.ndarray:
        return pivot_joint_angles(self.state)

    def advance(self, command: PivotCommand, dt_s: float) -> None:
        if command.mode != "cpg":
            if self.clock.due():  # a period boundary: new inputs
                self._inputs = self.control.update(self.clock.t_s, command)
            else:
                self.control.meter.sample()
            A, B, v_dot_d = self._inputs
        else:
            A, B, v_dot_d = math.radians(command.A_deg), math.radians(command.B_deg), command.v_dot_d_m_s2
        self.state = pivot_step(self.state, self.params, A, B, v_dot_d, dt_s)
        self.clock.advance(dt_s)


def pivot_run(sc: PivotScenario) -> GroundRun:
    """A run of the scenario, not started."""
    robot = PivotModel(sc)
    return GroundRun(sc, robot, PivotCpg(sc, robot))


def _forward_error(sc: PivotScenario):
    """A motion command's forward tracking: the RMS of the acceleration's error (``mode =
    "acceleration"``: the change of the period velocity ``v_x`` over a period, against
    ``v_dot_d_m_s2``) or of the speed's (``mode = "velocity"``:
    :func:`~sitl.scenarios.ground.run.speed_error`)."""
    def forward(a: dict, row: dict, cmd: PivotCommand, w, t0: float, t1: float) -> None:
        if cmd.mode != "acceleration":
            speed_error(a, row, cmd, w, t0, t1)
            return
        t_acc, acc = period_acceleration(a, 1.0 / sc.cpg.frequency_hz, sc.log_rate_hz)
        wa = (t_acc >= t0) & (t_acc <= t1)
        row["v_dot_rms_err_m_s2"] = float(np.sqrt(np.mean((acc[wa] - cmd.v_dot_d_m_s2) ** 2)))

    return forward


def fly_pivotboard(sc: PivotScenario, out_dir: Path | None, *, progress=None, plots: bool = True) -> dict:
    """Run the scenario; returns the metrics (and writes the run folder when ``out_dir`` is given):
    :func:`~sitl.scenarios.ground.run.fly_ground`'s, the acceleration commands' error included."""
    return fly_ground(sc, pivot_run(sc), out_dir, "pivotboard", progress=progress, plots=plots,
                      forward=_forward_error(sc))

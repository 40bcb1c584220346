"""A snake run: the CPG of thesis sec. 4.3.2 drives the joints' servos of the MuJoCo robot
(:class:`~sitl.scenarios.ground.run.GroundRun`: the loop, {B}'s velocities, the metrics).

:class:`SnakeCpg` holds the CPG's state: its targets are ``theta_h`` on the horizontal joints and
``theta_v`` on the vertical ones; it advances with the command's ``A``, ``B``.

**Outputs** (:func:`fly_snake`): ``metrics.json`` (per command, the mean and standard deviation of
``v_x``, ``v_y``, ``omega`` in {B} from ``settle_s`` after it starts; the distance, path length and
heading change; the servos' RMS tracking error per axis; ``flipped``: whether the body left the
ground), ``snake.npz`` (the log), ``snake.png`` (the path with the body every 2 s, the velocities).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.motion.ground_cpgs import SnakeCpgState, snake_joint_angles, snake_step

from ..ground.control import PeriodClock
from ..ground.run import GroundRun, fly_ground
from .config import CpgCommand, SnakeScenario
from .model import SnakeModel

__all__ = ["SnakeCpg", "snake_run", "fly_snake", "steady_motion"]


class SnakeCpg:
    """The snake's CPG driving ``robot``'s servos (module docstring); with velocity commands, their
    control (:class:`~.control.VelocityControl`) sets the inputs at every period boundary."""

    def __init__(self, sc: SnakeScenario, robot: SnakeModel):
        self.params = sc.cpg
        self.state = SnakeCpgState.at_rest(sc.cpg)
        self.robot = robot
        self.period_s = 1.0 / sc.cpg.frequency_hz
        self.axes = {"horizontal": [int(j) for j in robot.horizontal], "vertical": [int(j) for j in robot.vertical]}
        self.control = None
        if any(c.mode == "velocity" for c in sc.commands):
            from .control import VelocityControl

            self.control = VelocityControl(sc, robot)
        self.clock = PeriodClock(self.period_s)
        self._eta = np.zeros(2)

    def targets(self) -> np.ndarray:
        out = np.zeros(self.robot.model.nu)
        out[self.robot.horizontal], out[self.robot.vertical] = snake_joint_angles(self.state, self.params)
        return out

    def advance(self, command: CpgCommand, dt_s: float) -> None:
        if command.mode == "velocity":
            if self.clock.due():  # a period boundary: new inputs
                self._eta = self.control.update(self.clock.t_s, command)
            else:
                self.control.meter.sample()
            A, B = self._eta
        else:
            A, B = math.radians(command.A_deg), math.radians(command.B_deg)
        self.state = snake_step(self.state, self.params, A, B, dt_s)
        self.clock.advance(dt_s)


def snake_run(sc: SnakeScenario) -> GroundRun:
    """A run of the scenario, not started."""
    robot = SnakeModel(sc)
    return GroundRun(sc, robot, SnakeCpg(sc, robot))


def steady_motion(sc: SnakeScenario, A_deg: float, B_deg: float, phase_hv=None) -> np.ndarray:
    """The robot's steady motion ``[v_x, v_y, omega]`` in {B} with ``(A, B)`` held from rest: the
    period velocities' means over the scenario's duration after ``settle_s`` (``nan`` if that
    window is empty); ``phase_hv``: a :class:`~companion.motion.oscillators.PhaseMap` in place of
    the scenario's (eq. 4.1's sweep holds it constant)."""
    cpg = sc.cpg if phase_hv is None else replace(sc.cpg, phase_hv=phase_hv)
    run = snake_run(replace(sc, cpg=cpg, commands=(CpgCommand(0.0, A_deg, B_deg),)))
    run.run()
    a = run.arrays()
    w = a["period_t"] >= sc.settle_s
    if not w.any():
        return np.full(3, np.nan)
    return np.array([a["v_x"][w].mean(), a["v_y"][w].mean(), a["omega"][w].mean()])


def fly_snake(sc: SnakeScenario, out_dir: Path | None, *, progress=None, plots: bool = True) -> dict:
    """Run the scenario; returns the metrics (and writes the run folder when ``out_dir`` is given):
    :func:`~sitl.scenarios.ground.run.fly_ground`'s, and ``flipped``."""
    def flipped(a, metrics):
        lift = a["com_w"][:, 2] - a["com_w"][0, 2]
        metrics["flipped"] = bool(np.any(lift > 0.5 * sc.body.modules * sc.body.module_length_m))

    return fly_ground(sc, snake_run(sc), out_dir, "snake", progress=progress, plots=plots, more=flipped)

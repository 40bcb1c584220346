"""A scenario kind's part in a batch flight: the public hooks :class:`~sitl.runner.BatchRunner` calls.

The runner is the physics, the firmware and the companion engines on one clock (dm_control's
``Physics``); a :class:`Task` is what a kind of scenario adds to them (dm_control's ``Task``): its
own MuJoCo model, targets or contacts of its own, its log rows. Every hook does nothing here; a
kind overrides those it needs (:mod:`sitl.scenarios`).

Within physics tick ``k`` at time ``t`` the runner calls, in this order:

1. the kinematics and the truth of ``t``; on a firmware tick the sensors, every link's firmware,
   then the companion engines' exchange, where every polled engine's outputs pass through
   :meth:`Task.before_outputs`, are applied to the firmware, then :meth:`Task.after_outputs`;
2. on a log tick the run's log row, then :meth:`Task.after_log`, then the crash check;
3. the runner's ``tick_hooks`` (observers: cameras, video, an estimator beside the flight);
4. the rotors, wind and integration of the step, then :meth:`Task.after_step`.

:meth:`Task.initialize` runs once, at the end of the runner's start-up (plant built, firmware
started, engines made), before the first tick.
"""

from __future__ import annotations

__all__ = ["Task"]


class Task:
    """The hooks of a batch flight (module docstring); this base class changes nothing."""

    def initialize(self, runner) -> None:
        """Once, after the runner's start-up and before its first tick (e.g. a model of the
        scenario's own with :meth:`~sitl.plant.plant.Plant.use_model`, then
        :meth:`~sitl.runner.BatchRunner.start_firmware` again)."""

    def before_outputs(self, runner, engine, outputs: list, t: float) -> list:
        """An engine's outputs at ``t`` before the firmware gets them; returns those the runner is
        to apply (the task has dealt with the others itself)."""
        return outputs

    def after_outputs(self, runner, engine, outputs: list, t: float) -> None:
        """After the runner applied an engine's outputs at ``t`` (on every poll of an engine)."""

    def after_log(self, runner, t: float, truth) -> None:
        """After the run's log row at ``t`` (the log rate), with that tick's truth."""

    def after_step(self, runner, k: int, t: float) -> None:
        """After physics tick ``k`` (at ``t``) integrated the state: what only the new state shows
        (contact forces)."""

"""What the ground robots' motion control shares (thesis secs. 4.6, 4.7.2): the body's velocity
measured once per CPG period, and the line-holding law that regulates the lateral position.

* :class:`PeriodMeter`: at each CPG period boundary, the velocity ``[v_x, v_y, omega]`` in {B}
  over the period that ended (:func:`~.run.body_velocity`: the centre of mass's displacement in
  {B} at the period's mean heading, sampled at every CPG step, and the heading's change), as the
  thesis averages its velocities over a period;
* :func:`line_holding_rate`: ``omega_d = -k_y y - k_heading psi``, limited to ``omega_max``, the
  angular velocity that brings the robot back onto the line ``y = 0`` heading along +x;
* :class:`PeriodClock`: the CPG's clock, which says when a period boundary is due (the thesis
  updates the CPG's inputs once per oscillation period).
"""

from __future__ import annotations

import math

import numpy as np

from .run import body_velocity

__all__ = ["PeriodMeter", "line_holding_rate", "PeriodClock"]


class PeriodMeter:
    """``robot``'s velocity over each CPG period of ``period_s`` (module docstring): call
    :meth:`sample` at every CPG step and :meth:`boundary` at every period boundary."""

    def __init__(self, robot, period_s: float):
        self.robot = robot
        self.period_s = period_s
        self._last = None  # (com in plane, heading) at the last boundary
        self._headings: list[float] = []  # unwrapped, since the last boundary

    def sample(self) -> None:
        """The heading now, towards the period's mean heading."""
        h = self.robot.heading()
        if self._headings:
            h = self._headings[-1] + math.remainder(h - self._headings[-1], 2.0 * math.pi)
        self._headings.append(h)

    def boundary(self) -> np.ndarray | None:
        """At a period boundary: ``[v_x, v_y, omega]`` over the period that ended (``None`` at the
        first boundary); {B} at the period's mean heading (of the samples since the last boundary
        and its ends: a body that undulates turns its heading to and fro within the period)."""
        com = self.robot.in_plane(self.robot.centre_of_mass())
        self.sample()
        headings, self._headings = self._headings, [self._headings[-1]]
        heading = headings[-1]
        measured = None
        if self._last is not None:
            p0, h0 = self._last
            dh = heading - h0 if len(headings) > 1 else math.remainder(heading - h0, 2.0 * math.pi)
            mean = float(np.mean(headings)) if len(headings) > 1 else h0 + 0.5 * dh
            measured = np.array([float(x) for x in body_velocity(com - p0, mean, dh, self.period_s)])
        self._last = (com, heading)
        return measured


def line_holding_rate(robot, k_y_per_s: float, k_heading_per_s: float, omega_max_rad_s: float) -> float:
    """The line-holding angular velocity [rad/s] for ``robot`` now (module docstring)."""
    y = float(robot.in_plane(robot.centre_of_mass())[1])
    psi = math.remainder(robot.heading(), 2.0 * math.pi)
    omega = -k_y_per_s * y - k_heading_per_s * psi
    return max(-omega_max_rad_s, min(omega_max_rad_s, omega))


class PeriodClock:
    """The CPG's time ``t_s`` and its period boundaries (every ``period_s`` from 0)."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self.t_s = 0.0
        self._next_s = 0.0

    def due(self) -> bool:
        """Whether a boundary is due now (then the next one is a period on)."""
        if self.t_s < self._next_s - 1e-9:
            return False
        self._next_s = (math.floor(self.t_s / self.period_s + 1e-9) + 1) * self.period_s
        return True

    def advance(self, dt_s: float) -> None:
        self.t_s += dt_s

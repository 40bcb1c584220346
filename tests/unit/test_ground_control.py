"""What the ground robots' motion control shares (sitl.scenarios.ground.control, .run): the CPG's
period clock, the period velocity in {B} at the period's mean heading (an undulating body makes no
sideways velocity), and the line-holding law."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.scenarios.ground.control import PeriodClock, PeriodMeter, line_holding_rate
from sitl.scenarios.ground.run import period_velocities


class _Robot:
    """A stand-in robot moving along a path ``p(t)`` with the heading ``heading(t)``."""

    def __init__(self, p, heading):
        self.p, self.h, self.t = p, heading, 0.0

    def centre_of_mass(self):
        return np.array([*self.p(self.t), 0.0])

    def in_plane(self, x):
        return np.asarray(x)[:2]

    def heading(self):
        return self.h(self.t)


def test_the_clock_is_due_once_per_period_from_zero():
    clock = PeriodClock(0.5)
    due = []
    for _ in range(130):  # 1.3 s in 10 ms steps
        due.append(clock.due())
        clock.advance(0.01)
    assert [k for k, d in enumerate(due) if d] == [0, 50, 100]


@pytest.mark.parametrize("amplitude", [0.0, 0.3, 0.6])
def test_an_undulating_heading_makes_no_sideways_velocity(amplitude):
    """Straight along x at 0.5 m/s while the heading swings by ``amplitude`` at the CPG's
    frequency, out of phase with the period's ends: the period's mean heading is the path's; the
    ends' heading would read the swing as a sideways velocity (0.5 sin(amplitude sin 0.7))."""
    def heading(t):
        return amplitude * np.sin(2.0 * np.pi * t + 0.7)

    robot = _Robot(lambda t: (0.5 * t, 0.0), heading)
    meter = PeriodMeter(robot, 1.0)
    rows = []
    for k in range(401):  # 4 s at 100 Hz, a boundary every second
        robot.t = 0.01 * k
        if k % 100 == 0:
            rows.append(meter.boundary())
        else:
            meter.sample()
    assert rows[0] is None
    for v in rows[1:]:
        assert v[0] == pytest.approx(0.5, abs=0.01) and abs(v[1]) < 0.005 and abs(v[2]) < 1e-9, v
    t = np.arange(0.0, 4.0, 0.02)
    _, vx, vy, om = period_velocities(t, np.stack((0.5 * t, 0 * t), axis=1), heading(t), 1.0)
    np.testing.assert_allclose(vx, 0.5, atol=0.01)
    assert np.abs(vy).max() < 0.01 and np.abs(om).max() < 1e-9


def test_a_turn_at_a_steady_rate_is_read_in_the_frame_of_the_chord():
    robot = _Robot(lambda t: (math.sin(0.3 * t), 1.0 - math.cos(0.3 * t)), lambda t: 0.3 * t)
    meter = PeriodMeter(robot, 1.0)
    for k in range(201):
        robot.t = 0.01 * k
        if k % 100 == 0:
            v = meter.boundary()
        else:
            meter.sample()
    assert v[0] == pytest.approx(2.0 * math.sin(0.15), abs=1e-4) and abs(v[1]) < 1e-4 and v[2] == pytest.approx(0.3)


@pytest.mark.parametrize("y, psi, want", [(0.0, 0.0, 0.0), (1.0, 0.0, -0.2), (-1.0, 0.2, 0.1), (10.0, 0.0, -0.6)])
def test_the_line_holding_law_turns_back_to_the_line_and_is_limited(y, psi, want):
    robot = _Robot(lambda t: (0.0, y), lambda t: psi)
    assert line_holding_rate(robot, 0.2, 0.5, 0.6) == pytest.approx(want)

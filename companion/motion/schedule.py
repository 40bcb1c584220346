"""The motion command schedule: what the operator asks of the undulating chain, over time.

A scenario's ``[motion]`` section (and the leader companion) holds a list of commands, each
active from its ``at_s`` (seconds after the motion starts) until the next one::

    [[motion.commands]]
    at_s = 0.0
    speed_m_s = 0.3          # forward, head first
    gait = "horizontal"      # undulate in the body's x-y plane (thesis Fig. 5-4); "vertical": x-z (Fig. 5-5)

    [[motion.commands]]
    at_s = 20.0
    speed_m_s = 0.3
    gait = "vertical"
    yaw_deg = 45.0           # heading target, high-level P control (thesis sec. 5.2); or yaw_rate_deg_s

:func:`desired_motion` turns the active command and the body's pose into the desired steady
motion ``xi_d = [v; omega; theta]`` of the inverse model (thesis sec. 4.5.1): the chain swims
head first along ``-x`` of ``{B}``, so ``v = [-speed, 0, 0]``; ``omega = [0, pitch rate, yaw
rate]``; ``theta`` is 0 for the horizontal and ``pi/2`` for the vertical gait.

The expected physics is a neutrally buoyant body in water: nothing holds its depth, and a
vertical undulation (or a turn) drifts it up or down by metres a minute. A flying chain must
keep its altitude, so (like the thesis's high-level regulators of sec. 4.7.2, which hold the
lateral position) an altitude hold asks for a pitch rate: the desired pitch of the swimming
direction is ``k_z (z_ref - z)`` (limited), and the pitch rate ``k_pitch (pitch_d - pitch)``
(limited). Positive pitch about ``{B}``'s y axis lowers its x axis, i.e. raises the head (which
leads along ``-x``). Pure: no clocks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from companion.configfile import require_nonnegative, require_positive

__all__ = ["MotionCommand", "MotionConfig", "desired_motion", "heading_rad", "pitch_rad", "GAIT_THETA",
           "PACKAGED_MODEL"]

GAIT_THETA = {"horizontal": 0.0, "vertical": 0.5 * math.pi}

#: the inverse CPG model that comes with the package: the seven-link chain's (``models/README.md``
#: beside it says how it was made)
PACKAGED_MODEL = str(Path(__file__).resolve().parent / "models" / "inverse_cpg_7link.npz")


@dataclass(frozen=True)
class MotionCommand:
    """One command of the schedule. ``yaw_deg`` (heading of ``{B}``'s x axis in the world,
    counter-clockwise from world x) selects heading control; otherwise ``yaw_rate_deg_s``."""

    at_s: float
    speed_m_s: float = 0.0
    gait: Literal["horizontal", "vertical"] = "horizontal"
    yaw_rate_deg_s: float = 0.0
    yaw_deg: float | None = None

    def __post_init__(self) -> None:
        require_nonnegative(self, "at_s", "speed_m_s")
        if self.yaw_deg is not None and self.yaw_rate_deg_s != 0.0:
            raise ValueError("yaw_deg and yaw_rate_deg_s exclude each other: give one")


@dataclass(frozen=True)
class MotionConfig:
    """CPG motion generation on the leader (thesis ch. 4).

    ``model``: the inverse CPG model file (relative paths are relative to the config file; by
    default the packaged seven-link model, :data:`PACKAGED_MODEL`); the CPG and expected physics
    are the ones it records. ``start_s``: scenario time at which the
    motion starts (the chain hovers straight before). ``dt_s``: the generator's step (the
    targets are sampled from it). ``adapt``: eq. 4.3 on. ``yaw_kp_1_s``, ``yaw_rate_max_deg_s``:
    the heading controller of ``yaw_deg`` commands. ``hold_altitude`` with ``altitude_kp_deg_m``,
    ``pitch_max_deg``, ``pitch_kp_1_s``, ``pitch_rate_max_deg_s``: the altitude hold (module
    docstring). The controllers are sampled once per undulation period.
    """

    model: str = PACKAGED_MODEL
    start_s: float = 10.0
    dt_s: float = 0.01
    adapt: bool = True
    yaw_kp_1_s: float = 0.2
    yaw_rate_max_deg_s: float = 3.0
    hold_altitude: bool = True
    altitude_kp_deg_m: float = 10.0
    pitch_max_deg: float = 10.0
    pitch_kp_1_s: float = 0.5
    pitch_rate_max_deg_s: float = 4.0
    commands: tuple[MotionCommand, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        require_positive(self, "dt_s", "yaw_kp_1_s", "yaw_rate_max_deg_s", "altitude_kp_deg_m", "pitch_max_deg",
                         "pitch_kp_1_s", "pitch_rate_max_deg_s")
        require_nonnegative(self, "start_s")
        times = [c.at_s for c in self.commands]
        if times and (times[0] != 0.0 or any(b <= a for a, b in zip(times, times[1:]))):
            raise ValueError(f"commands: at_s must start at 0 and increase, got {times}")

    def active(self, t_motion_s: float) -> MotionCommand | None:
        """The command in force ``t_motion_s`` after the start (``None`` before it or with none)."""
        current = None
        for command in self.commands:
            if command.at_s <= t_motion_s:
                current = command
        return current


def _clip(x: float, limit: float) -> float:
    return min(max(x, -limit), limit)


def heading_rad(R_wb: np.ndarray) -> float:
    """Heading of ``{B}``'s x axis in the world's horizontal plane."""
    return math.atan2(R_wb[1, 0], R_wb[0, 0])


def pitch_rad(R_wb: np.ndarray) -> float:
    """Pitch of ``{B}`` (z-y-x Euler): positive lowers its x axis."""
    return math.asin(_clip(-R_wb[2, 0], 1.0))


def desired_motion(cfg: MotionConfig, command: MotionCommand | None, R_wb: np.ndarray,
                   altitude_error_m: float) -> np.ndarray:
    """``xi_d`` (7,) of ``command`` for a body at attitude ``R_wb`` that is ``altitude_error_m``
    above its reference altitude (zero motion without a command)."""
    if command is None:
        return np.zeros(7)
    if command.yaw_deg is not None:
        error = (math.radians(command.yaw_deg) - heading_rad(R_wb) + math.pi) % (2 * math.pi) - math.pi
        yaw_rate = _clip(cfg.yaw_kp_1_s * error, math.radians(cfg.yaw_rate_max_deg_s))
    else:
        yaw_rate = math.radians(command.yaw_rate_deg_s)
    pitch_rate = 0.0
    if cfg.hold_altitude:
        pitch_d = _clip(-math.radians(cfg.altitude_kp_deg_m) * altitude_error_m, math.radians(cfg.pitch_max_deg))
        pitch_rate = _clip(cfg.pitch_kp_1_s * (pitch_d - pitch_rad(R_wb)), math.radians(cfg.pitch_rate_max_deg_s))
    return np.array([-command.speed_m_s, 0.0, 0.0, 0.0, pitch_rate, yaw_rate, GAIT_THETA[command.gait]])

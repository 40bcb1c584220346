"""The PSPM jump's configuration: a single-link scenario with a ``[teleop]`` table (no MuJoCo here).

A :class:`PspmJumpScenario` (``kind = "pspm_jump"``) is a :class:`~sitl.scenario.Scenario` of one
link with a scripted operator (:class:`TeleopConfig`): the hover pose moved by ``jump_m`` along
``jump_axis_w`` from ``jump_s`` on, and turned by ``yaw_jump_deg`` about the vertical from
``yaw_jump_s`` on, and the master side's haptic gains (:mod:`.flight` flies it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from link_firmware_sim.controllers.pspm import HapticGains
from sitl.scenario import Scenario, load_scenario

__all__ = ["TeleopConfig", "PspmJumpScenario", "load_teleop_scenario"]


@dataclass(frozen=True)
class TeleopConfig:
    """The scripted operator (module docstring) and the master side's haptic gains."""

    jump_m: float = 1.0
    jump_axis_w: tuple[float, float, float] = (1.0, 0.0, 0.0)
    jump_s: float = 4.0
    yaw_jump_deg: float = 60.0
    yaw_jump_s: float = 11.0
    haptic: HapticGains = field(default_factory=HapticGains)

    def __post_init__(self) -> None:
        axis = np.asarray(self.jump_axis_w, dtype=float)
        if not abs(np.linalg.norm(axis) - 1.0) < 1e-6:
            raise ValueError(f"jump_axis_w must be a unit vector, got {self.jump_axis_w}")
        for name in ("jump_m", "jump_s", "yaw_jump_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite non-negative number, got {v!r}")
        if not (math.isfinite(self.yaw_jump_deg) and abs(self.yaw_jump_deg) <= 180.0):
            raise ValueError(f"yaw_jump_deg must be within [-180, 180], got {self.yaw_jump_deg!r}")
        if not self.yaw_jump_s > self.jump_s:
            raise ValueError("yaw_jump_s must come after jump_s (the position jump is measured before it)")


@dataclass(frozen=True)
class PspmJumpScenario(Scenario):
    """A single-link scenario with a scripted operator (``kind = "pspm_jump"``, ``[teleop]``)."""

    kind: Literal["pspm_jump"] = "pspm_jump"
    teleop: TeleopConfig = field(default_factory=TeleopConfig)

    def __post_init__(self) -> None:
        Scenario.__post_init__(self)
        if self.skeleton.n_links != 1:
            raise ValueError(f"the PSPM jump flies one link, got skeleton.n_links = {self.skeleton.n_links}")
        if not self.teleop.jump_s >= self.flight_start_s:
            raise ValueError(f"teleop.jump_s must come after the take-off ({self.flight_start_s:g} s)")
        if not self.duration_s > self.teleop.yaw_jump_s:
            raise ValueError(f"duration_s must exceed teleop.yaw_jump_s ({self.teleop.yaw_jump_s:g} s)")


def load_teleop_scenario(path, **overrides) -> PspmJumpScenario:
    """Read a PSPM-jump scenario (:class:`~companion.configfile.ConfigError` if invalid), tuned for its
    sensors as every scenario is (:func:`~sitl.scenario.load_scenario`)."""
    return load_scenario(path, PspmJumpScenario, **overrides)

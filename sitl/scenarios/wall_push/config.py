"""The wall push's configuration: a single-link scenario with a ``[contact]`` table (no MuJoCo here).

A :class:`WallPushScenario` (``kind = "wall_push"``) is a :class:`~sitl.scenario.Scenario` of one
link under ``firmware.controller = "hybrid"`` with a :class:`ContactConfig`: the wall (a box whose
face passes through ``wall_point_w_m``, its unit normal ``normal_w`` pointing into it), the
approach along the normal until the contact point ``contact_b_m`` (default: the right tip) is
``preload_m`` inside the wall, the commanded force ``force_n`` and its ramp, and the settling time
before the metrics' window (:mod:`.flight` flies it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from sitl.scenario import Scenario, load_scenario

__all__ = ["ContactConfig", "WallPushScenario", "load_wall_scenario"]


@dataclass(frozen=True)
class ContactConfig:
    """The wall and the push (see the module docstring)."""

    normal_w: tuple[float, float, float] = (1.0, 0.0, 0.0)
    wall_point_w_m: tuple[float, float, float] = (1.0, 0.0, 2.0)
    #: contact point on the link, body frame; ``None``: the right tip
    contact_b_m: tuple[float, float, float] | None = None
    force_n: float = 10.0
    approach_start_s: float = 6.0
    approach_duration_s: float = 4.0
    preload_m: float = 0.02
    contact_start_s: float = 12.0
    force_ramp_s: float = 2.0
    settle_s: float = 3.0
    wall_friction: float = 0.6

    def __post_init__(self) -> None:
        n = np.asarray(self.normal_w, dtype=float)
        if not abs(np.linalg.norm(n) - 1.0) < 1e-6:
            raise ValueError(f"normal_w must be a unit vector, got {self.normal_w}")
        for name in ("force_n", "approach_start_s", "approach_duration_s", "preload_m", "force_ramp_s", "settle_s",
                     "wall_friction"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite non-negative number, got {v!r}")
        if self.contact_start_s < self.approach_start_s + self.approach_duration_s:
            raise ValueError("contact_start_s must come after the approach (approach_start_s + approach_duration_s)")

    @property
    def steady_start_s(self) -> float:
        return self.contact_start_s + self.force_ramp_s + self.settle_s


@dataclass(frozen=True)
class WallPushScenario(Scenario):
    """A single-link scenario with a wall to push on (``kind = "wall_push"``, ``[contact]``)."""

    kind: Literal["wall_push"] = "wall_push"
    contact: ContactConfig = field(default_factory=ContactConfig)

    def __post_init__(self) -> None:
        Scenario.__post_init__(self)
        if self.skeleton.n_links != 1:
            raise ValueError(f"the wall push flies one link, got skeleton.n_links = {self.skeleton.n_links}")
        if self.firmware.controller != "hybrid":
            raise ValueError(f"firmware.controller must be 'hybrid' for the wall push, got {self.firmware.controller!r}")
        if not self.duration_s > self.contact.steady_start_s:
            raise ValueError(f"duration_s must exceed the steady window's start {self.contact.steady_start_s:g} s")

    @property
    def contact_b_m(self) -> np.ndarray:
        c = self.contact.contact_b_m
        return np.array(c if c is not None else (0.5 * self.skeleton.link_length_m, 0.0, 0.0))


def load_wall_scenario(path, **overrides) -> WallPushScenario:
    """Read a wall-push scenario (:class:`~companion.configfile.ConfigError` if invalid), tuned for its
    sensors as every scenario is (:func:`~sitl.scenario.load_scenario`)."""
    return load_scenario(path, WallPushScenario, **overrides)

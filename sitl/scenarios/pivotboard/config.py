"""The pivotboard's scenario (``kind = "pivotboard"``): its body, the ground, the CPG (thesis sec.
4.3.3) and the commanded CPG inputs over time. No MuJoCo here.

The thesis (sec. 4.2.2) gives the structure only: a main deck, two foot plates on revolute joints
at the deck's tips, two wheels on each plate, "as usual skateboard"; the board moves by oscillating
the plates with a phase difference, through the wheels' nonholonomic constraint. Every dimension,
mass, servo gain and friction value below is this project's choice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from companion.configfile import require_nonnegative, require_positive
from companion.motion.ground_cpgs import PivotCpgParams

from ..ground.config import GroundScenario, load_ground_scenario

__all__ = ["PivotBody", "PivotGround", "PivotCommand", "PivotScenario", "load_pivot_scenario"]


@dataclass(frozen=True)
class PivotBody:
    """The board: a deck ``2 deck_half_length_m`` long (its x axis forward); the right foot plate's
    joint ``plate_offset_m`` ahead of the deck's centre, the left one as far behind (the thesis's
    ``r`` and ``l``), both turning about the deck's normal; on each plate two wheels
    ``wheel_track_m`` apart on an axle across the plate, ``wheel_drop_m`` below it, free to roll.
    Each plate joint is a position servo (the thesis's "simple PD control"): ``servo_kp_nm_rad``,
    ``servo_kd_nms_rad``, torque ``servo_max_nm``, angle ``joint_limit_deg``."""

    deck_half_length_m: float = 0.4
    deck_mass_kg: float = 2.0
    plate_offset_m: float = 0.35
    plate_mass_kg: float = 1.0
    wheel_radius_m: float = 0.03
    wheel_track_m: float = 0.2
    wheel_drop_m: float = 0.035
    wheel_mass_kg: float = 0.05
    wheel_damping_nms_rad: float = 0.0005
    servo_kp_nm_rad: float = 30.0
    servo_kd_nms_rad: float = 0.5
    servo_max_nm: float = 10.0
    joint_limit_deg: float = 80.0

    def __post_init__(self) -> None:
        require_positive(self, "deck_half_length_m", "deck_mass_kg", "plate_offset_m", "plate_mass_kg",
                         "wheel_radius_m", "wheel_track_m", "wheel_drop_m", "wheel_mass_kg", "servo_kp_nm_rad",
                         "servo_max_nm", "joint_limit_deg")
        require_nonnegative(self, "wheel_damping_nms_rad", "servo_kd_nms_rad")
        if self.plate_offset_m >= self.deck_half_length_m:
            raise ValueError("plate_offset_m: the plates' joints sit on the deck, inside deck_half_length_m")


@dataclass(frozen=True)
class PivotGround:
    """The plane the board rolls on, tilted ``incline_deg`` about the world y axis (uphill along
    +x), and its friction coefficient ``friction`` (the thesis's planes: 1.0 and, slippery, 0.3)."""

    incline_deg: float = 0.0
    friction: float = 1.0

    def __post_init__(self) -> None:
        if not -30.0 <= self.incline_deg <= 30.0:
            raise ValueError(f"incline_deg must be in [-30, 30], got {self.incline_deg}")
        require_positive(self, "friction")


@dataclass(frozen=True)
class PivotCommand:
    """From ``t_s`` on, the CPG's inputs: the plates' amplitude ``A_deg``, the bias ``B_deg`` (on the
    right plate: it curves the path) and the desired acceleration ``v_dot_d_m_s2``, whose sign
    picks the plates' phase difference (the speed-maximising map when speeding up, zero when
    slowing down)."""

    t_s: float
    A_deg: float
    B_deg: float = 0.0
    v_dot_d_m_s2: float = 0.0

    def __post_init__(self) -> None:
        require_nonnegative(self, "t_s", "A_deg")
        if not (math.isfinite(self.B_deg) and abs(self.B_deg) <= 45.0 and self.A_deg <= 60.0
                and math.isfinite(self.v_dot_d_m_s2)):
            raise ValueError(f"A_deg in [0, 60], B_deg in [-45, 45], v_dot_d_m_s2 finite; got {self.A_deg}, "
                             f"{self.B_deg}, {self.v_dot_d_m_s2}")


@dataclass(frozen=True)
class PivotScenario(GroundScenario):
    """A pivotboard run (:class:`~sitl.scenarios.ground.config.GroundScenario`: rates, settling,
    commands): its body, ground and CPG (``[cpg]``:
    :class:`~companion.motion.ground_cpgs.PivotCpgParams`), ``[[commands]]`` (:class:`PivotCommand`)."""

    kind: Literal["pivotboard"] = "pivotboard"
    name: str = "pivotboard"
    body: PivotBody = field(default_factory=PivotBody)
    ground: PivotGround = field(default_factory=PivotGround)
    cpg: PivotCpgParams = field(default_factory=PivotCpgParams)
    commands: tuple[PivotCommand, ...] = (PivotCommand(0.0, 20.0, 0.0, 0.1),)


def load_pivot_scenario(path: str | Path, settings=None, **overrides) -> PivotScenario:
    """Read a pivotboard scenario (:class:`~companion.configfile.ConfigError` naming the key)."""
    return load_ground_scenario(PivotScenario, path, settings, **overrides)

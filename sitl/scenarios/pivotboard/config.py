"""The pivotboard's scenario (``kind = "pivotboard"``): its body, the ground, the CPG (thesis sec.
4.3.3) and the commanded CPG inputs over time. No MuJoCo here.

The thesis (sec. 4.2.2) gives the structure only: a main deck, two foot plates on revolute joints
at the deck's tips, two wheels on each plate, "as usual skateboard"; the board moves by oscillating
the plates with a phase difference, through the wheels' nonholonomic constraint. Every dimension,
mass, servo gain and friction value below is this project's choice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from companion.configfile import require_nonnegative, require_positive
from companion.motion.ground_cpgs import PivotCpgParams

from ..ground.config import GroundControl, GroundScenario, load_ground_scenario, with_phase_map

__all__ = ["PivotBody", "PivotGround", "PivotCommand", "PivotControl", "PivotScenario", "load_pivot_scenario",
           "BRANCHES", "model_path"]

#: the CPG's branches (the phase difference of the map while speeding up, zero while slowing
#: down), each with its inverse model; in the order :func:`~.da_fit.fit_runs` returns their fits
BRANCHES = ("accelerating", "decelerating")


def model_path(folder: str | Path, branch: str) -> Path:
    """The file of ``branch``'s inverse model in ``folder`` (:mod:`.inverse` writes it)."""
    return Path(folder) / f"inverse_{branch}.npz"


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
    """From ``t_s`` on, either (``mode = "cpg"``) the CPG's inputs themselves: the plates'
    amplitude ``A_deg``, the bias ``B_deg`` (on the right plate: it curves the path) and the desired
    acceleration ``v_dot_d_m_s2``, whose sign picks the plates' phase difference (the
    speed-maximising map when speeding up, zero when slowing down); or a motion the inverse model
    (and the adaptation) turn into them once per CPG period (``[control]``, thesis sec. 4.6):
    ``mode = "acceleration"``, the forward acceleration ``v_dot_d_m_s2``; ``mode = "velocity"``,
    the forward speed ``v_x_m_s`` (held by ``v_dot_d = k_v (v_x - v)``). Either with the angular
    velocity ``omega_rad_s`` or, with ``hold_line``, the one that brings the board back onto the
    line ``y = 0`` heading along +x (the thesis's "y (lateral) position is regulated to be zero")."""

    t_s: float
    A_deg: float = 0.0
    B_deg: float = 0.0
    v_dot_d_m_s2: float = 0.0
    mode: Literal["cpg", "acceleration", "velocity"] = "cpg"
    v_x_m_s: float = 0.0
    omega_rad_s: float = 0.0
    hold_line: bool = False

    def __post_init__(self) -> None:
        require_nonnegative(self, "t_s", "A_deg")
        if not (math.isfinite(self.B_deg) and abs(self.B_deg) <= 45.0 and self.A_deg <= 60.0):
            raise ValueError(f"A_deg in [0, 60], B_deg in [-45, 45]; got {self.A_deg}, {self.B_deg}")
        if not all(math.isfinite(x) and abs(x) <= 5.0 for x in (self.v_dot_d_m_s2, self.v_x_m_s, self.omega_rad_s)):
            raise ValueError(f"v_dot_d_m_s2, v_x_m_s, omega_rad_s: finite, within 5; got {self.v_dot_d_m_s2}, "
                             f"{self.v_x_m_s}, {self.omega_rad_s}")
        if self.hold_line and self.mode == "cpg":
            raise ValueError('hold_line: an option of a motion command (mode = "acceleration" or "velocity")')


@dataclass(frozen=True)
class PivotControl(GroundControl):
    """The motion commands' control (thesis secs. 4.5.3, 4.6): the inverse models in
    ``model_folder`` (relative to the scenario; :mod:`.inverse` trains them), the speed hold
    ``v_dot_d = k_v_per_s (v_x - v)``, ``v_min_m_s``, the speed under which the curvature ``c =
    omega / v`` is taken at that speed, and what every ground robot's control has
    (:class:`~sitl.scenarios.ground.config.GroundControl`: the adaptation, the line holding; here
    the turn rate is limited to 0.1 rad/s by default). (The thesis gives none of these.)"""

    model_folder: str = ""
    k_v_per_s: float = 0.5
    v_min_m_s: float = 0.01
    omega_max_rad_s: float = 0.1

    def __post_init__(self) -> None:
        GroundControl.__post_init__(self)
        require_nonnegative(self, "k_v_per_s")
        require_positive(self, "v_min_m_s")


@dataclass(frozen=True)
class PivotScenario(GroundScenario):
    """A pivotboard run (:class:`~sitl.scenarios.ground.config.GroundScenario`: rates, settling,
    commands): its body, ground and CPG (``[cpg]``:
    :class:`~companion.motion.ground_cpgs.PivotCpgParams`), the motion commands' control
    (``[control]``: :class:`PivotControl`), ``[[commands]]`` (:class:`PivotCommand`)."""

    kind: Literal["pivotboard"] = "pivotboard"
    name: str = "pivotboard"
    #: eq. 4.1's map ``phi(A, B, v_dot_d)`` from a sweep (:mod:`.phase_map`): a file relative to
    #: the scenario's, whose ``[phase]`` table replaces ``[cpg] phase`` ("": the ``[cpg]`` one)
    phase_map_file: str = ""
    body: PivotBody = field(default_factory=PivotBody)
    ground: PivotGround = field(default_factory=PivotGround)
    cpg: PivotCpgParams = field(default_factory=PivotCpgParams)
    control: PivotControl = field(default_factory=PivotControl)
    commands: tuple[PivotCommand, ...] = (PivotCommand(0.0, 20.0, 0.0, 0.1),)

    def __post_init__(self) -> None:
        GroundScenario.__post_init__(self)
        if any(c.mode != "cpg" for c in self.commands) and not self.control.model_folder:
            raise ValueError("control.model_folder: motion commands need the inverse models")


def load_pivot_scenario(path: str | Path, settings=None, **overrides) -> PivotScenario:
    """Read a pivotboard scenario (:class:`~companion.configfile.ConfigError` naming the key);
    ``settings``, ``overrides``: as for :func:`~sitl.scenarios.ground.config.load_ground_scenario`."""
    sc = load_ground_scenario(PivotScenario, path, settings, **overrides)
    if sc.control.model_folder:
        folder = Path(path).resolve().parent / sc.control.model_folder
        sc = replace(sc, control=replace(sc.control, model_folder=str(folder)))
    return with_phase_map(sc, path, "phase")

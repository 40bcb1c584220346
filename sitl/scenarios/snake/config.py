"""The snake-like robot's scenario (``kind = "snake"``): its body, the ground, the CPG (thesis sec.
4.3.2) and the commanded CPG inputs over time. No MuJoCo here: the file loads and validates on any
install.

The thesis (sec. 4.2.2) gives the robot's structure only: 15 link modules in series on revolute
joints whose axes alternate between horizontal and vertical. Every dimension, mass, servo gain and
friction coefficient below is this project's choice, said so in the field's comment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from companion.configfile import require_nonnegative, require_positive
from companion.motion.ground_cpgs import SnakeCpgParams

from ..ground.config import GroundControl, GroundScenario, load_ground_scenario, with_phase_map

__all__ = ["SnakeBody", "SnakeGround", "CpgCommand", "SnakeControl", "SnakeScenario", "load_snake_scenario"]


@dataclass(frozen=True)
class SnakeBody:
    """The robot: ``modules`` capsules of ``module_length_m`` (joint to joint) and ``radius_m`` in
    series, module 1 the head; joint ``j`` (1-based, between modules ``j`` and ``j + 1``) turns about
    the vertical (yaw) axis for odd ``j`` when ``first_joint = "horizontal"`` and about the
    horizontal (pitch) axis for even ``j`` (the other way round with ``"vertical"``). Each joint is
    a position servo, the thesis's "simple PD control": ``servo_kp_nm_rad``, ``servo_kd_nms_rad``,
    its torque limited to ``servo_max_nm`` and its angle to ``joint_limit_deg``. (The thesis gives
    none of these values.)"""

    modules: int = 15
    module_length_m: float = 0.1
    radius_m: float = 0.025
    module_mass_kg: float = 0.2
    first_joint: Literal["horizontal", "vertical"] = "horizontal"
    servo_kp_nm_rad: float = 20.0
    servo_kd_nms_rad: float = 0.3
    servo_max_nm: float = 10.0
    joint_limit_deg: float = 90.0

    def __post_init__(self) -> None:
        if self.modules < 3 or self.modules % 2 == 0:
            raise ValueError(f"modules: an odd number >= 3 (as many horizontal as vertical joints), got {self.modules}")
        require_positive(self, "module_length_m", "radius_m", "module_mass_kg", "servo_kp_nm_rad", "servo_max_nm",
                         "joint_limit_deg")
        require_nonnegative(self, "servo_kd_nms_rad")
        if 2.0 * self.radius_m >= self.module_length_m:
            raise ValueError(f"radius_m: modules of {self.module_length_m} m need a radius under half of it")

    @property
    def joints(self) -> int:
        return self.modules - 1

    def is_horizontal(self, j: int) -> bool:
        """Whether 0-based joint ``j`` turns about the vertical axis (a horizontal-undulation joint)."""
        return (j % 2 == 0) == (self.first_joint == "horizontal")


@dataclass(frozen=True)
class SnakeGround:
    """The plane the snake lies on, tilted ``incline_deg`` about the world y axis (uphill along +x),
    and its friction: Coulomb, anisotropic as snake-robot models make it (scales and wheels slide
    more easily along the body than across it): ``friction_along`` along each module's axis,
    ``friction_across`` across it, smoothed below ``slip_speed_m_s`` (tanh)."""

    incline_deg: float = 0.0
    friction_along: float = 0.1
    friction_across: float = 1.0
    slip_speed_m_s: float = 0.005

    def __post_init__(self) -> None:
        if not -30.0 <= self.incline_deg <= 30.0:
            raise ValueError(f"incline_deg must be in [-30, 30], got {self.incline_deg}")
        require_nonnegative(self, "friction_along", "friction_across")
        require_positive(self, "slip_speed_m_s")


@dataclass(frozen=True)
class CpgCommand:
    """From ``t_s`` on, either (``mode = "cpg"``) the CPG's inputs themselves: the horizontal
    undulation's amplitude ``A_deg`` and bias ``B_deg`` (the bias turns the snake); or (``mode =
    "velocity"``, thesis sec. 4.6) a body velocity the inverse model and the adaptation turn into
    them once per CPG period (``[control]``): forward ``v_x_m_s`` and angular ``omega_rad_s``, or,
    with ``hold_line``, the angular velocity that brings the snake back onto the line ``y = 0``
    heading along +x (the thesis's "y (lateral) position is regulated to be zero")."""

    t_s: float
    A_deg: float = 0.0
    B_deg: float = 0.0
    mode: Literal["cpg", "velocity"] = "cpg"
    v_x_m_s: float = 0.0
    omega_rad_s: float = 0.0
    hold_line: bool = False

    def __post_init__(self) -> None:
        require_nonnegative(self, "t_s", "A_deg")
        if not (math.isfinite(self.B_deg) and abs(self.B_deg) <= 60.0 and self.A_deg <= 90.0):
            raise ValueError(f"A_deg in [0, 90] and B_deg in [-60, 60], got {self.A_deg}, {self.B_deg}")
        if not (math.isfinite(self.v_x_m_s) and math.isfinite(self.omega_rad_s) and abs(self.v_x_m_s) <= 5.0
                and abs(self.omega_rad_s) <= 5.0):
            raise ValueError(f"v_x_m_s and omega_rad_s: finite, within 5, got {self.v_x_m_s}, {self.omega_rad_s}")
        if self.hold_line and self.mode != "velocity":
            raise ValueError("hold_line: a velocity command's option (mode = \"velocity\")")


@dataclass(frozen=True)
class SnakeControl(GroundControl):
    """The velocity commands' control (thesis sec. 4.6): the inverse model ``model_file`` (relative
    to the scenario; :mod:`.inverse` trains it), and what every ground robot's control has
    (:class:`~sitl.scenarios.ground.config.GroundControl`: the adaptation, the line holding)."""

    model_file: str = ""


@dataclass(frozen=True)
class SnakeScenario(GroundScenario):
    """A snake run (:class:`~sitl.scenarios.ground.config.GroundScenario`: rates, settling,
    commands): its body, ground and CPG (``[cpg]``:
    :class:`~companion.motion.ground_cpgs.SnakeCpgParams`, its ``n`` the number of joints of each
    axis), ``[[commands]]`` (:class:`CpgCommand`)."""

    kind: Literal["snake"] = "snake"
    name: str = "snake"
    #: eq. 4.1's map ``phi_hv(A, B)`` from a sweep (:mod:`.phase_map`): a file relative to the
    #: scenario's, whose ``[phase_hv]`` table replaces ``[cpg] phase_hv`` ("": the ``[cpg]`` one)
    phase_map_file: str = ""
    body: SnakeBody = field(default_factory=SnakeBody)
    ground: SnakeGround = field(default_factory=SnakeGround)
    cpg: SnakeCpgParams = field(default_factory=SnakeCpgParams)
    control: SnakeControl = field(default_factory=SnakeControl)
    commands: tuple[CpgCommand, ...] = (CpgCommand(0.0, 30.0, 0.0),)

    def __post_init__(self) -> None:
        GroundScenario.__post_init__(self)
        if any(c.mode == "velocity" for c in self.commands) and not self.control.model_file:
            raise ValueError("control.model_file: velocity commands need the inverse model")
        if self.cpg.n != self.body.joints // 2:
            raise ValueError(f"cpg.n ({self.cpg.n}) must be the number of horizontal joints, "
                             f"{self.body.joints // 2} for {self.body.modules} modules")


def load_snake_scenario(path: str | Path, settings=None, **overrides) -> SnakeScenario:
    """Read a snake scenario (:class:`~companion.configfile.ConfigError` naming the key);
    ``settings``: dotted keys set in the file's tables; ``overrides``: top-level fields (e.g.
    ``duration_s``), checked as if the file held them."""
    sc = load_ground_scenario(SnakeScenario, path, settings, **overrides)
    folder = Path(path).resolve().parent
    if sc.control.model_file:
        sc = replace(sc, control=replace(sc.control, model_file=str(folder / sc.control.model_file)))
    return with_phase_map(sc, path, "phase_hv")

"""The pivotboard in MuJoCo: :func:`pivot_mjcf` and :class:`PivotModel`.

The deck has a free joint; each foot plate hangs under one of the deck's tips on a hinge about the
deck's normal, with a position servo; each plate carries two wheels (cylinders) on a free-rolling
hinge across the plate. Only the wheels touch the ground (``condim = 3``, the ground's friction):
they roll along the plate and resist sliding across it, the nonholonomic constraint the board
moves by. The board starts at rest, its wheels on the plane, pointing uphill.
"""

from __future__ import annotations

import mujoco
import numpy as np

from ..ground.plane import PlaneFrame
from .config import PivotScenario

__all__ = ["pivot_mjcf", "PivotModel"]

#: the deck's and the plates' thicknesses [m] (boxes; they never touch the ground)
DECK_THICKNESS_M = 0.02
PLATE_THICKNESS_M = 0.016


def _f(*v: float) -> str:
    return " ".join(f"{x:.9g}" for x in v)


def pivot_mjcf(sc: PivotScenario) -> str:
    """MJCF of the board and its ground (module docstring)."""
    b, plane = sc.body, PlaneFrame(sc.ground.incline_deg)
    mu = sc.ground.friction
    r, half_track = b.wheel_radius_m, 0.5 * b.wheel_track_m
    plate_drop = 0.5 * (DECK_THICKNESS_M + PLATE_THICKNESS_M)
    height = r + b.wheel_drop_m + plate_drop  # the deck's centre over the ground
    lim = b.joint_limit_deg
    friction = f'friction="{mu:.9g} 0.005 0.0001"'
    lines = ['<mujoco model="pivotboard">',
             '  <compiler angle="degree"/>',
             f'  <option timestep="{sc.physics_dt_s:.9g}" integrator="implicitfast"/>',
             '  <worldbody>',
             f'    <geom name="ground" type="plane" size="0 0 0.05" euler="{plane.mjcf_euler()}" {friction}/>',
             f'    <body name="deck" pos="{_f(*plane.above(height))}" euler="{plane.mjcf_euler()}">',
             '      <freejoint name="root"/>',
             f'      <geom name="deck" type="box" size="{_f(b.deck_half_length_m, 0.08, 0.5 * DECK_THICKNESS_M)}" '
             f'mass="{b.deck_mass_kg:.9g}" contype="0" conaffinity="0"/>']
    for side, x in (("r", b.plate_offset_m), ("l", -b.plate_offset_m)):
        lines += [f'      <body name="plate_{side}" pos="{_f(x, 0, -plate_drop)}">',
                  f'        <joint name="j{side}" type="hinge" axis="0 0 1" range="{-lim:.9g} {lim:.9g}"/>',
                  f'        <geom name="plate_{side}" type="box" size="{_f(0.06, half_track + 0.02, 0.5 * PLATE_THICKNESS_M)}" '
                  f'mass="{b.plate_mass_kg:.9g}" contype="0" conaffinity="0"/>']
        for k, y in enumerate((half_track, -half_track)):
            lines += [f'        <body name="wheel_{side}{k + 1}" pos="{_f(0, y, -b.wheel_drop_m)}">',
                      f'          <joint type="hinge" axis="0 1 0" damping="{b.wheel_damping_nms_rad:.9g}"/>',
                      f'          <geom name="wheel_{side}{k + 1}" type="cylinder" size="{_f(r, 0.01)}" euler="90 0 0" '
                      f'mass="{b.wheel_mass_kg:.9g}" condim="3" {friction}/>',
                      '        </body>']
        lines.append('      </body>')
    lines += ['    </body>', '  </worldbody>', '  <actuator>']
    for side in ("r", "l"):
        lines.append(f'    <position name="s{side}" joint="j{side}" kp="{b.servo_kp_nm_rad:.9g}" '
                     f'kv="{b.servo_kd_nms_rad:.9g}" forcelimited="true" '
                     f'forcerange="{-b.servo_max_nm:.9g} {b.servo_max_nm:.9g}"/>')
    lines += ['  </actuator>', '</mujoco>']
    return "\n".join(lines) + "\n"


class PivotModel:
    """The compiled board, its data at the start and its ground's frame; the interface
    :class:`~sitl.scenarios.ground.run.GroundRun` steps and logs (servos: right, left)."""

    def __init__(self, sc: PivotScenario):
        self.scenario = sc
        self.xml = pivot_mjcf(sc)
        self.model = mujoco.MjModel.from_xml_string(self.xml)
        self.data = mujoco.MjData(self.model)
        self.plane = PlaneFrame(sc.ground.incline_deg)
        m = self.model
        self.deck = m.body("deck").id
        self.plates = np.array([m.body("plate_r").id, m.body("plate_l").id])
        self.joint_qpos = np.array([m.jnt_qposadr[m.joint(f"j{s}").id] for s in ("r", "l")])
        mujoco.mj_forward(self.model, self.data)

    def step(self, n: int = 1) -> None:
        mujoco.mj_step(self.model, self.data, nstep=n)

    def centre_of_mass(self) -> np.ndarray:
        return self.data.subtree_com[self.deck].copy()

    def heading(self) -> float:
        """The deck's heading in the ground's plane [rad] (0: uphill, +x)."""
        return self.plane.heading(self.data.xmat[self.deck].reshape(3, 3)[:, 0])

    def in_plane(self, p_w: np.ndarray) -> np.ndarray:
        return self.plane.in_plane(p_w)

    def outline(self) -> np.ndarray:
        """The right plate, the deck's centre and the left plate (3, 3), world frame."""
        d = self.data
        return np.stack((d.xpos[self.plates[0]], d.xpos[self.deck], d.xpos[self.plates[1]]))

    def servo_angles(self) -> np.ndarray:
        """The plates' joint angles [rad]: right, left."""
        return self.data.qpos[self.joint_qpos].copy()

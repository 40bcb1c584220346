"""The snake-like robot in MuJoCo: its model from the scenario, and the ground's anisotropic friction.

:func:`snake_mjcf`: ``body.modules`` capsules in series, module 1 (the head) with a free joint,
each next module ``module_length_m`` behind the previous one (along its -x axis) on a hinge at the
joint between them, the hinges' axes alternating between the module's z axis (horizontal
undulation, a yaw joint) and its y axis (vertical, a pitch joint); a position servo on each
hinge (``kp``, ``kv``, torque and angle limits of ``[body]``); the ground plane tilted
``ground.incline_deg`` about the world y axis, uphill along +x. The robot starts lying straight on
the plane, pointing uphill.

The modules touch the ground through frictionless contacts (``condim = 1``: MuJoCo computes the
normal forces only). :class:`AnisotropicGround` adds the friction the way snake-robot models write
it: per module, Coulomb friction with the module's normal force, ``friction_along`` against the
sliding velocity along the module's axis and ``friction_across`` against the sliding across it
(both in the ground's plane), smoothed below ``slip_speed_m_s``; applied at the module's centre
(``xfrc_applied``) before every step.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from ..ground.plane import PlaneFrame
from .config import SnakeScenario

__all__ = ["snake_mjcf", "SnakeModel", "AnisotropicGround"]


def _f(*v: float) -> str:
    return " ".join(f"{x:.9g}" for x in v)


def snake_mjcf(sc: SnakeScenario) -> str:
    """MJCF of the robot and its ground (module docstring)."""
    b, plane = sc.body, PlaneFrame(sc.ground.incline_deg)
    L, r = b.module_length_m, b.radius_m
    half = 0.5 * L - r
    lim = b.joint_limit_deg
    lines = ['<mujoco model="snake">',
             '  <compiler angle="degree"/>',
             f'  <option timestep="{sc.physics_dt_s:.9g}" integrator="implicitfast"/>',
             '  <worldbody>',
             f'    <geom name="ground" type="plane" size="0 0 0.05" euler="{plane.mjcf_euler()}" condim="1"/>',
             f'    <body name="m1" pos="{_f(*plane.above(1.0001 * r))}" euler="{plane.mjcf_euler()}">',
             '      <freejoint name="root"/>']
    geom = (f'<geom type="capsule" fromto="{_f(-half, 0, 0, half, 0, 0)}" size="{r:.9g}" mass="{b.module_mass_kg:.9g}" '
            'condim="1"')
    lines.append(f'      {geom} name="m1"/>')
    for j in range(b.joints):
        indent = "  " * (j + 3)
        axis = "0 0 1" if b.is_horizontal(j) else "0 1 0"
        lines += [f'{indent}<body name="m{j + 2}" pos="{_f(-L, 0, 0)}">',
                  f'{indent}  <joint name="j{j + 1}" type="hinge" axis="{axis}" pos="{_f(0.5 * L, 0, 0)}" '
                  f'range="{-lim:.9g} {lim:.9g}"/>',
                  f'{indent}  {geom} name="m{j + 2}"/>']
    for j in reversed(range(b.joints)):
        lines.append(f'{"  " * (j + 3)}</body>')
    lines += ['    </body>', '  </worldbody>', '  <actuator>']
    for j in range(b.joints):
        lines.append(f'    <position name="s{j + 1}" joint="j{j + 1}" kp="{b.servo_kp_nm_rad:.9g}" '
                     f'kv="{b.servo_kd_nms_rad:.9g}" forcelimited="true" '
                     f'forcerange="{-b.servo_max_nm:.9g} {b.servo_max_nm:.9g}" ctrllimited="true" '
                     f'ctrlrange="{-math.radians(lim):.9g} {math.radians(lim):.9g}"/>')
    lines += ['  </actuator>', '</mujoco>']
    return "\n".join(lines) + "\n"


class AnisotropicGround:
    """The ground's friction on every module (module docstring): :meth:`apply` before each step."""

    def __init__(self, model: mujoco.MjModel, sc: SnakeScenario):
        g = sc.ground
        self.mu_along, self.mu_across, self.eps = g.friction_along, g.friction_across, g.slip_speed_m_s
        #: the ground's frame
        self.plane = PlaneFrame(g.incline_deg)
        self.normal = self.plane.normal
        self.ground = model.geom("ground").id
        self.bodies = np.array([model.body(f"m{k + 1}").id for k in range(sc.body.modules)])
        module_of = np.full(model.ngeom, -1)
        for k in range(sc.body.modules):
            module_of[model.geom(f"m{k + 1}").id] = k
        self.module_of = module_of
        self.normal_force = np.zeros(sc.body.modules)

    def apply(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Each module's friction force from the last step's contacts and its velocity now."""
        n = data.ncon
        N = self.normal_force
        N[:] = 0.0
        if n:
            geoms = data.contact.geom[:n]
            other = np.where(geoms[:, 0] == self.ground, geoms[:, 1], geoms[:, 0])
            on_ground = (geoms == self.ground).any(axis=1) & (self.module_of[other] >= 0)
            f = data.efc_force[data.contact.efc_address[:n]]
            np.add.at(N, self.module_of[other[on_ground]], f[on_ground])
        axes = data.xmat[self.bodies].reshape(-1, 3, 3)[:, :, 0]
        along = axes - np.outer(axes @ self.normal, self.normal)
        along /= np.maximum(np.linalg.norm(along, axis=1, keepdims=True), 1e-9)
        across = np.cross(self.normal, along)
        v = self._velocities(model, data)
        v_plane = v - np.outer(v @ self.normal, self.normal)
        va = np.sum(v_plane * along, axis=1)
        vc = np.sum(v_plane * across, axis=1)
        F = -N[:, None] * (self.mu_along * np.tanh(va / self.eps)[:, None] * along
                           + self.mu_across * np.tanh(vc / self.eps)[:, None] * across)
        data.xfrc_applied[self.bodies, :3] = F

    def _velocities(self, model, data) -> np.ndarray:
        """Each module's centre's linear velocity, world frame."""
        out = np.empty((len(self.bodies), 3))
        v6 = np.empty(6)
        for k, b in enumerate(self.bodies):
            mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, int(b), v6, 0)
            out[k] = v6[3:]
        return out


class SnakeModel:
    """The compiled model, its data at the start, the ground's friction and frame, the joints'
    servos by axis (``horizontal``, ``vertical``: 0-based actuator indices, head to tail); the
    interface :class:`~sitl.scenarios.ground.run.GroundRun` steps and logs."""

    def __init__(self, sc: SnakeScenario):
        self.scenario = sc
        self.xml = snake_mjcf(sc)
        self.model = mujoco.MjModel.from_xml_string(self.xml)
        self.data = mujoco.MjData(self.model)
        self.ground = AnisotropicGround(self.model, sc)
        self.plane = self.ground.plane
        b = sc.body
        self.horizontal = np.array([j for j in range(b.joints) if b.is_horizontal(j)])
        self.vertical = np.array([j for j in range(b.joints) if not b.is_horizontal(j)])
        self.root = self.model.body("m1").id
        self.joint_qpos = np.array([self.model.jnt_qposadr[self.model.joint(f"j{j + 1}").id] for j in range(b.joints)])
        mujoco.mj_forward(self.model, self.data)

    def step(self, n: int = 1) -> None:
        """``n`` physics steps, the ground's friction applied before each."""
        for _ in range(n):
            self.ground.apply(self.model, self.data)
            mujoco.mj_step(self.model, self.data)

    def module_positions(self) -> np.ndarray:
        """Every module's centre (modules, 3), world frame, head first."""
        return self.data.xpos[self.ground.bodies].copy()

    outline = module_positions

    def centre_of_mass(self) -> np.ndarray:
        return self.data.subtree_com[self.root].copy()

    def heading(self) -> float:
        """The body frame's heading in the ground's plane [rad] (0: uphill, +x): the direction of the
        modules' mean axis, head-wards."""
        return self.plane.heading(self.data.xmat[self.ground.bodies].reshape(-1, 3, 3)[:, :, 0].sum(axis=0))

    def in_plane(self, p_w: np.ndarray) -> np.ndarray:
        return self.plane.in_plane(p_w)

    def servo_angles(self) -> np.ndarray:
        """The joints' angles [rad], actuator order."""
        return self.data.qpos[self.joint_qpos].copy()

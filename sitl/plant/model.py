"""MuJoCo model of an n-link aerial skeleton, generated from its config (no hand-edited XML).

Each link is a body ``link{i}`` (1-based) whose frame is the link centre, x along the link
towards its right tip. Link 1 has a free joint (``link1_root``); link ``i+1`` is a child of
link ``i`` attached at the shared tip by a ball joint ``joint{i}_{i+1}`` with stiffness and
damping (the compliant cable, a 3-DOF joint: paper sec. II). Tips coincide by construction.

Each link carries the eight ODAR rotors of thesis Table 2.1 (sigma_1 = -1, sec. 2.4.1) as
sites ``link{i}_rotor{k}`` whose z axis is the thrust direction ``u_k`` and motor actuators of
the same name with ``gear = [0 0 1 0 0 gamma sigma_k]``: a thrust ``lambda`` pushes along
``u_k`` at ``r_k`` (hence the ``r_k x u_k`` moment) and adds the drag torque
``gamma sigma_k lambda u_k`` (eq. 2.1). Actuator controls are the rotor thrusts [N] produced
by :mod:`sitl.rotor`.

Sensors per link (site ``link{i}_imu`` at the centre): ``link{i}_acc`` (accelerometer: the
specific force an IMU measures, contacts included), ``link{i}_gyro``, and truth
``link{i}_pos``, ``link{i}_quat``, ``link{i}_linvel`` (world frame). The cable force at every
joint is MuJoCo's ``cfrc_int`` of the child link (the same tree as
:class:`companion.skeleton.dynamics.ChainModel`; ``tests/unit/test_chain_model.py`` checks both agree). Sites
``link{i}_tip_left`` / ``link{i}_tip_right`` mark the joints.

Links collide with the ground plane only. A physics step is split: :meth:`SkeletonModel.begin_step`
(``mj_step1``: kinematics and position/velocity sensors at the current time), then the caller
reads the truth and runs the firmware, then :meth:`SkeletonModel.end_step` (``mj_step2``:
thrusts and forces applied, accelerations and the accelerometer computed, state integrated).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import mujoco
import numpy as np

from companion.estimation.so3 import quat_from_euler_zyx, quat_to_rotmat
from companion.skeleton.body import GRAVITY_M_S2, SkeletonConfig, link_inertia
from companion.skeleton.rotors import RotorGeometry, RotorParams

from .start import StartPose

__all__ = ["build_mjcf", "rotor_controls", "SkeletonModel", "Truth"]


def _fmt(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(v))


def _unit(u: np.ndarray) -> np.ndarray:
    return u / np.linalg.norm(u)


def build_mjcf(cfg: SkeletonConfig, geometry: RotorGeometry, rotors: RotorParams, timestep_s: float = 0.001) -> str:
    """MJCF text of the skeleton (see the module docstring for names)."""
    inertia = link_inertia(cfg, geometry)
    L = cfg.link_length_m
    half = 0.5 * L
    gamma = rotors.drag_ratio_m
    limit = rotors.thrust_max_n
    lines = [
        '<mujoco model="aerial_skeleton">',
        f'  <option timestep="{timestep_s:.9g}" gravity="0 0 {-GRAVITY_M_S2:.9g}" integrator="implicitfast"/>',
        '  <visual><global offwidth="1280" offheight="720"/></visual>',
        "  <worldbody>",
        f'    <geom name="ground" type="plane" size="50 50 0.1" contype="0" conaffinity="1" '
        f'friction="{cfg.ground_friction:.9g} 0.005 0.0001" rgba="0.35 0.4 0.35 1"/>',
        '    <light name="sun" pos="0 0 20" dir="0 0 -1" directional="true"/>',
    ]
    indent = "    "
    for i in range(1, cfg.n_links + 1):
        pos = "0 0 0" if i == 1 else f"{L:.9g} 0 0"
        lines.append(f'{indent}<body name="link{i}" pos="{pos}">')
        inner = indent + "  "
        if i == 1:
            lines.append(f'{inner}<freejoint name="link1_root"/>')
        else:
            lines.append(
                f'{inner}<joint name="joint{i - 1}_{i}" type="ball" pos="{-half:.9g} 0 0" '
                f'stiffness="{cfg.joint_stiffness_nm_rad:.9g}" damping="{cfg.joint_damping_nms_rad:.9g}" '
                f'range="0 {cfg.joint_limit_deg:.9g}" limited="true"/>'
            )
        lines.append(
            f'{inner}<inertial pos="0 0 0" mass="{inertia.mass_kg:.9g}" diaginertia="{_fmt(inertia.inertia_kgm2)}"/>'
        )
        lines.append(
            f'{inner}<geom name="link{i}_bar" type="capsule" fromto="{-half + cfg.bar_radius_m:.9g} 0 0 '
            f'{half - cfg.bar_radius_m:.9g} 0 0" size="{cfg.bar_radius_m:.9g}" contype="1" conaffinity="0" '
            f'rgba="0.2 0.2 0.25 1"/>'
        )
        lines.append(f'{inner}<site name="link{i}_imu" pos="0 0 0" size="0.02"/>')
        lines.append(f'{inner}<site name="link{i}_tip_left" pos="{-half:.9g} 0 0" size="0.015"/>')
        lines.append(f'{inner}<site name="link{i}_tip_right" pos="{half:.9g} 0 0" size="0.015"/>')
        for k in range(geometry.positions_m.shape[0]):
            lines.append(
                f'{inner}<site name="link{i}_rotor{k + 1}" pos="{_fmt(geometry.positions_m[k])}" '
                f'zaxis="{_fmt(_unit(geometry.directions[k]))}" type="cylinder" size="0.06 0.005" '
                f'rgba="0.8 0.3 0.2 0.5"/>'
            )
        indent = inner
    for i in range(cfg.n_links, 0, -1):
        indent = indent[:-2]
        lines.append(f"{indent}</body>")
    lines.append("  </worldbody>")
    lines.append("  <actuator>")
    for i in range(1, cfg.n_links + 1):
        for k in range(geometry.positions_m.shape[0]):
            sigma = geometry.spin[k]
            lines.append(
                f'    <motor name="link{i}_rotor{k + 1}" site="link{i}_rotor{k + 1}" '
                f'gear="0 0 1 0 0 {gamma * sigma:.9g}" ctrllimited="true" ctrlrange="{-limit:.9g} {limit:.9g}"/>'
            )
    lines.append("  </actuator>")
    lines.append("  <sensor>")
    for i in range(1, cfg.n_links + 1):
        lines += [
            f'    <accelerometer name="link{i}_acc" site="link{i}_imu"/>',
            f'    <gyro name="link{i}_gyro" site="link{i}_imu"/>',
            f'    <framepos name="link{i}_pos" objtype="site" objname="link{i}_imu"/>',
            f'    <framequat name="link{i}_quat" objtype="site" objname="link{i}_imu"/>',
            f'    <framelinvel name="link{i}_linvel" objtype="site" objname="link{i}_imu"/>',
        ]
    lines.append("  </sensor>")
    lines.append("</mujoco>")
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class Truth:
    """Ground truth of every link: p/v world (n, 3), q (n, 4), body rate and specific force (n, 3),
    and the force on link ``j+1`` from link ``j`` at every joint (the cable), world (n-1, 3).

    The joint forces are computed when first read (the harness reads them at the log rate only,
    not at every physics tick): read them before the step ends (:meth:`SkeletonModel.end_step`)."""

    p_w_m: np.ndarray
    v_w_m_s: np.ndarray
    q_wxyz: np.ndarray
    omega_b_rad_s: np.ndarray
    specific_force_b_m_s2: np.ndarray
    _joint_forces: Callable[[], np.ndarray] = field(repr=False, compare=False)

    @cached_property
    def joint_force_w_n(self) -> np.ndarray:
        return self._joint_forces()


def rotor_controls(actuator_ids: np.ndarray) -> slice | np.ndarray:
    """Where the rotors' thrusts, flattened link by link, go in MuJoCo's ``ctrl``: one slice when
    the actuators lie in link and rotor order (written without a gather), else their ids."""
    flat = actuator_ids.reshape(-1)
    if np.array_equal(flat, np.arange(flat[0], flat[0] + flat.size)):
        return slice(int(flat[0]), int(flat[0]) + flat.size)
    return flat


class SkeletonModel:
    """A compiled skeleton with every element resolved by name."""

    def __init__(self, cfg: SkeletonConfig, geometry: RotorGeometry, rotors: RotorParams, timestep_s: float = 0.001,
                 cameras: tuple = (), markers: tuple = (), scene=None, seed: int = 0):
        self.cfg = cfg
        self.geometry = geometry
        self.xml = build_mjcf(cfg, geometry, rotors, timestep_s)
        assets: dict[str, bytes] = {}
        if cameras or markers or (scene is not None and scene.active):
            # cameras, ArUco markers and the [scene] (sitl.cameras.rig; OpenCV only then)
            from sitl.cameras.rig import vision_mjcf

            self.xml, assets = vision_mjcf(self.xml, tuple(cameras), tuple(markers), scene=scene, seed=seed)
        self.model = mujoco.MjModel.from_xml_string(self.xml, assets)
        self.data = mujoco.MjData(self.model)
        m = self.model
        n = cfg.n_links
        n_rot = geometry.positions_m.shape[0]
        self.n_links = n
        self.body_ids = np.array([m.body(f"link{i}").id for i in range(1, n + 1)])
        self.actuator_ids = np.array(
            [[m.actuator(f"link{i}_rotor{k}").id for k in range(1, n_rot + 1)] for i in range(1, n + 1)]
        )
        self._ctrl = rotor_controls(self.actuator_ids)
        self.tip_left_ids = np.array([m.site(f"link{i}_tip_left").id for i in range(1, n + 1)])
        self.tip_right_ids = np.array([m.site(f"link{i}_tip_right").id for i in range(1, n + 1)])

        def sensor_slice(name: str, dim: int) -> np.ndarray:
            s = m.sensor(name)
            assert s.dim[0] == dim, name
            return np.arange(s.adr[0], s.adr[0] + dim)

        def gather(kind: str, dim: int) -> np.ndarray:
            return np.stack([sensor_slice(f"link{i}_{kind}", dim) for i in range(1, n + 1)])

        self._acc = gather("acc", 3)
        self._gyro = gather("gyro", 3)
        self._pos = gather("pos", 3)
        self._quat = gather("quat", 4)
        self._linvel = gather("linvel", 3)
        root = m.joint("link1_root")
        self._root_qpos = int(root.qposadr[0])
        self._root_qvel = int(root.dofadr[0])
        self._thrust_dirs = geometry.directions / np.linalg.norm(geometry.directions, axis=1, keepdims=True)
        self.timestep_s = float(m.opt.timestep)

    def reset(self, start: StartPose) -> None:
        """Straight chain at ``start`` (at rest; on the ground if ``start.on_ground``)."""
        mujoco.mj_resetData(self.model, self.data)
        cfg = self.cfg
        q_root = quat_from_euler_zyx(math.radians(start.yaw_deg), math.radians(start.pitch_deg), 0.0)
        axis = quat_to_rotmat(q_root)[:, 0]
        center = np.array(start.center_w_m, dtype=float)
        if start.on_ground:
            lowest = 0.5 * (cfg.n_links * cfg.link_length_m) * abs(axis[2])
            center[2] = lowest + cfg.bar_radius_m + 1e-3
        p_root = center - axis * 0.5 * (cfg.n_links - 1) * cfg.link_length_m
        qpos = self.data.qpos
        qpos[self._root_qpos : self._root_qpos + 3] = p_root
        qpos[self._root_qpos + 3 : self._root_qpos + 7] = q_root
        mujoco.mj_forward(self.model, self.data)

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    def truth(self) -> Truth:
        s = self.data.sensordata
        return Truth(
            p_w_m=s[self._pos],
            v_w_m_s=s[self._linvel],
            q_wxyz=s[self._quat],
            omega_b_rad_s=s[self._gyro],
            specific_force_b_m_s2=s[self._acc],
            _joint_forces=self.joint_forces,
        )

    def joint_forces(self) -> np.ndarray:
        """(n-1, 3) force on link ``j+1`` from link ``j`` at their joint (the cable), world frame.

        MuJoCo's ``cfrc_int`` of a link (computed at every step for the accelerometers) is the
        force its parent must supply for its subtree's motion, less the external forces it knows
        as such (``xfrc_applied``, contacts); the rotors act through actuators (joint space), so
        their thrust along ``u_k`` is subtracted here, summed over the subtree."""
        d = self.data
        R = d.xmat[self.body_ids].reshape(-1, 3, 3)
        rotor_b = d.ctrl[self.actuator_ids] @ self._thrust_dirs  # (n, 3) body-frame rotor force per link
        rotor_w = np.einsum("nij,nj->ni", R, rotor_b)
        subtree = np.cumsum(rotor_w[::-1], axis=0)[::-1]  # links i..n
        return d.cfrc_int[self.body_ids[1:], 3:6] - subtree[1:]

    def link_velocities(self) -> np.ndarray:
        """(n, 3) world velocities of the link centres (valid after :meth:`begin_step`)."""
        return self.data.sensordata[self._linvel]

    def tips(self) -> tuple[np.ndarray, np.ndarray]:
        """World positions of the (left, right) tips of every link, each (n, 3)."""
        x = self.data.site_xpos
        return x[self.tip_left_ids].copy(), x[self.tip_right_ids].copy()

    def begin_step(self) -> None:
        """Kinematics at the current time (``mj_step1``): :meth:`truth` now has this instant's
        position, attitude, velocity and body rate, and the specific force of the last step."""
        mujoco.mj_step1(self.model, self.data)

    def end_step(self, thrust_n: np.ndarray, force_w_n: np.ndarray | None = None) -> None:
        """Apply rotor thrusts (n, 8) and forces at the link centres (n, 3); integrate (``mj_step2``)."""
        d = self.data
        d.ctrl[self._ctrl] = thrust_n.reshape(-1)
        if force_w_n is not None:
            d.xfrc_applied[self.body_ids, :3] = force_w_n
        mujoco.mj_step2(self.model, d)


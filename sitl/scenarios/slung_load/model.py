"""The slung-load model in MuJoCo: the vehicles, the load and the cables.

:func:`slung_load_mjcf`: ``n`` ODAR links of this stack, each with its own free joint (no joints
between them: ``link{i}_root``), each carrying its eight rotors, sensors and names exactly as in
:func:`sitl.plant.model.build_mjcf` (the one-link model replicated), so the rotor model, the
sensors and every link's firmware run unchanged; a box ``load`` (free joint, mass and inertia from
``[load]``); and one MuJoCo spatial tendon per cable, ``cable{i}`` from the vehicle's site
``link{i}_cable`` to the load's ``load_attach{i}``, limited to ``[0, L_i]``: an inextensible cable
that can go slack (its limit constraint's softness is ``load.cable_solref``). The load collides
with the ground; the cables with nothing. :class:`SlungLoadModel` compiles it.
"""

from __future__ import annotations

import re
from dataclasses import replace

import mujoco
import numpy as np

from companion.estimation.so3 import quat_from_euler_zyx
from companion.load.config import LoadConfig
from companion.load.formation import formation_state
from sitl.plant.model import SkeletonModel, build_mjcf, rotor_controls

from .config import SlungLoadScenario

__all__ = ["slung_load_mjcf", "SlungLoadModel", "put_in"]


def _fmt(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(v))


def slung_load_mjcf(sc: SlungLoadScenario, timestep_s: float) -> str:
    """MJCF of the vehicles, the load and the cables (module docstring)."""
    load: LoadConfig = sc.load
    n = load.n
    one = build_mjcf(replace(sc.skeleton, n_links=1), sc.geometry(), sc.rotors, timestep_s)
    lines = one.splitlines()
    start = next(i for i, s in enumerate(lines) if '<body name="link1"' in s)
    end = max(i for i, s in enumerate(lines) if s.strip() == "</body>")
    body = lines[start : end + 1]
    imu = next(j for j, s in enumerate(body) if 'name="link1_imu"' in s)
    indent = re.match(r"\s*", body[imu]).group(0)
    body.insert(imu + 1, f'{indent}<site name="link1_cable" pos="{_fmt(load.vehicle_attach_b_m)}" size="0.01"/>')
    actuators = [s for s in lines if "<motor " in s]
    s0, s1 = lines.index("  <sensor>"), lines.index("  </sensor>")
    sensors = lines[s0 + 1 : s1]

    def renamed(block: list[str], i: int) -> list[str]:
        return [re.sub(r"\blink1(?=[_\"])", f"link{i}", s) for s in block]

    P = load.params()
    half = 0.5 * np.asarray(load.size_m, dtype=float)
    load_body = [
        '    <body name="load" pos="0 0 0">',
        '      <freejoint name="load_root"/>',
        f'      <inertial pos="0 0 0" mass="{load.mass_kg:.9g}" diaginertia="{_fmt(np.diag(P.inertia_b_kg_m2))}"/>',
        f'      <geom name="load_box" type="box" size="{_fmt(half)}" contype="1" conaffinity="0" '
        f'rgba="0.85 0.6 0.3 1" mass="0"/>',
        '      <site name="load_center" pos="0 0 0" size="0.01"/>',
        *(f'      <site name="load_attach{i + 1}" pos="{_fmt(P.attach_b_m[i])}" size="0.01"/>' for i in range(n)),
        "    </body>",
    ]
    solref = _fmt(load.cable_solref)
    tendons = ["  <tendon>"]
    for i in range(1, n + 1):
        tendons += [
            f'    <spatial name="cable{i}" limited="true" range="0 {load.cable_length_m[i - 1]:.9g}" '
            f'width="{load.cable_width_m:.9g}" solreflimit="{solref}" rgba="0.1 0.1 0.1 1">',
            f'      <site site="link{i}_cable"/>',
            f'      <site site="load_attach{i}"/>',
            "    </spatial>",
        ]
    tendons.append("  </tendon>")
    out = lines[:start]
    for i in range(1, n + 1):
        out += renamed(body, i)
    out += load_body
    rest = lines[end + 1 :]
    wb = next(j for j, s in enumerate(rest) if "</worldbody>" in s)
    out += rest[: wb + 1] + tendons
    out.append("  <actuator>")
    for i in range(1, n + 1):
        out += renamed(actuators, i)
    out += ["  </actuator>", "  <sensor>"]
    for i in range(1, n + 1):
        out += renamed(sensors, i)
    out += ["  </sensor>", "</mujoco>"]
    return "\n".join(out) + "\n"


class SlungLoadModel(SkeletonModel):
    """The compiled slung-load model; the vehicles answer to :class:`~sitl.plant.model.SkeletonModel`'s
    interface (truth, thrusts, begin/end step), plus the load's truth and the cables' tensions."""

    def __init__(self, sc: SlungLoadScenario, timestep_s: float):
        self.cfg = sc.skeleton
        self.geometry = sc.geometry()
        self.scenario = sc
        self.xml = slung_load_mjcf(sc, timestep_s)
        assets: dict[str, bytes] = {}
        if sc.cameras or sc.markers or sc.scene.active:
            from sitl.cameras.rig import vision_mjcf

            self.xml, assets = vision_mjcf(self.xml, tuple(sc.cameras), tuple(sc.markers), scene=sc.scene,
                                           seed=sc.seed)
        self.model = mujoco.MjModel.from_xml_string(self.xml, assets)
        self.data = mujoco.MjData(self.model)
        m = self.model
        n = self.n_links = sc.skeleton.n_links
        n_rot = self.geometry.positions_m.shape[0]
        self.body_ids = np.array([m.body(f"link{i}").id for i in range(1, n + 1)])
        self.actuator_ids = np.array([[m.actuator(f"link{i}_rotor{k}").id for k in range(1, n_rot + 1)]
                                      for i in range(1, n + 1)])
        self._ctrl = rotor_controls(self.actuator_ids)
        self.tip_left_ids = np.array([m.site(f"link{i}_tip_left").id for i in range(1, n + 1)])
        self.tip_right_ids = np.array([m.site(f"link{i}_tip_right").id for i in range(1, n + 1)])

        def gather(kind: str, dim: int) -> np.ndarray:
            return np.stack([np.arange(m.sensor(f"link{i}_{kind}").adr[0], m.sensor(f"link{i}_{kind}").adr[0] + dim)
                             for i in range(1, n + 1)])

        self._acc, self._gyro, self._pos = gather("acc", 3), gather("gyro", 3), gather("pos", 3)
        self._quat, self._linvel = gather("quat", 4), gather("linvel", 3)
        self._roots = [(int(m.joint(f"link{i}_root").qposadr[0]), int(m.joint(f"link{i}_root").dofadr[0]))
                       for i in range(1, n + 1)]
        self._load_root = (int(m.joint("load_root").qposadr[0]), int(m.joint("load_root").dofadr[0]))
        self.load_body = m.body("load").id
        self.cable_ids = np.array([m.tendon(f"cable{i}").id for i in range(1, n + 1)])
        self._thrust_dirs = self.geometry.directions / np.linalg.norm(self.geometry.directions, axis=1, keepdims=True)
        self.timestep_s = float(m.opt.timestep)

    def reset(self, start=None) -> None:
        """Vehicles at the formation's start, at rest; the load hanging level below, cables taut."""
        mujoco.mj_resetData(self.model, self.data)
        f = formation_state(0.0, self.scenario.load.formation)
        q = quat_from_euler_zyx(f.yaw_rad, np.zeros(self.n_links), np.zeros(self.n_links))
        qpos = self.data.qpos
        for i, (a, _) in enumerate(self._roots):
            qpos[a : a + 3] = f.pos_w_m[i]
            qpos[a + 3 : a + 7] = q[i]
        pose = self.scenario.load.nominal_pose(f.center_w_m, f.phi_rad)
        a = self._load_root[0]
        qpos[a : a + 3] = pose.pos_m
        qpos[a + 3 : a + 7] = pose.q_wxyz
        mujoco.mj_forward(self.model, self.data)

    def joint_forces(self) -> np.ndarray:
        """No joints between the vehicles: zeros (n-1, 3) (the cables: :meth:`cable_tensions`)."""
        return np.zeros((self.n_links - 1, 3))

    def load_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The load's true ``(pos_w_m, q_wxyz)`` (valid after :meth:`begin_step`)."""
        d = self.data
        return d.xpos[self.load_body].copy(), d.xquat[self.load_body].copy()

    def cable_tensions(self) -> np.ndarray:
        """Each cable's tension [N] (its limit constraint's force; 0 when slack)."""
        d = self.data
        out = np.zeros(self.n_links)
        sel = d.efc_type[: d.nefc] == mujoco.mjtConstraint.mjCNSTR_LIMIT_TENDON
        for row in np.flatnonzero(sel):
            j = np.flatnonzero(self.cable_ids == d.efc_id[row])
            if j.size:
                out[j[0]] = d.efc_force[row]
        return out


def put_in(plant, sc: SlungLoadScenario) -> SlungLoadModel:
    """The slung-load model of ``sc`` at its start (:meth:`SlungLoadModel.reset`), flown by ``plant``
    from now on (:meth:`~sitl.plant.plant.Plant.use_model`; the plant's scenario becomes ``sc``)."""
    model = SlungLoadModel(sc, plant.dt)
    model.reset()
    plant.use_model(model)
    plant.scenario = sc
    return model

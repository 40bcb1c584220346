"""The wall push (thesis sec. 2.3.3): one ODAR pushes on a wall under hybrid pose/wrench control.

The flight (:class:`WallPushTask` on a :class:`~sitl.runner.BatchRunner`; the scenario:
:mod:`.config`):

1. take-off and hover under the hybrid controller without a contact (pose control);
2. from ``approach_start_s`` the pose target moves along ``normal_w`` (quintic, over
   ``approach_duration_s``) until the contact point ``contact_b_m`` is ``preload_m`` inside the
   wall;
3. at ``contact_start_s`` the contact is commanded (:meth:`LinkFirmware.set_contact`) and its
   force ramps (quintic, ``force_ramp_s``) to ``force_n`` from the observer's estimate of the
   preload (what the pose spring pushed with; from 0 the link would bounce off the wall); the
   pose target keeps holding the free directions (position along the wall, attitude).

Metrics from ``contact_start_s + force_ramp_s + settle_s`` to the end: the force tracking error
(MuJoCo's contact force, :func:`mujoco.mj_contactForce` summed over the bar-wall contacts and
projected on ``normal_w``, against the commanded force), RMS and relative to ``force_n``; the
observer's error (its ``lambda_c^`` against the same contact force, and its whole wrench estimate
against the contact wrench about the centre); the pose error in the free directions.

The task's hooks: the plant's model is rebuilt with the wall before the flight, the targets the
companion engine sends are shifted by the approach, and every physics step measures the contact.
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np

from companion.configfile import dump_toml
from companion.estimation.so3 import attitude_error, quat_to_rotmat
from companion.trajectory import planned_positions, smoothstep5
from link_firmware_sim.controllers.hybrid import ContactTarget
from sitl.plant.model import SkeletonModel
from sitl.runner import BatchRunner
from sitl.task import Task

from .config import ContactConfig, WallPushScenario

__all__ = ["wall_mjcf", "WallPushTask", "wall_push"]

log = logging.getLogger(__name__)


def wall_mjcf(cfg: ContactConfig, thickness_m: float = 0.1) -> str:
    """The wall: a box whose face contains ``wall_point_w_m``, its z axis along ``normal_w``."""
    n = np.asarray(cfg.normal_w, dtype=float)
    c = np.asarray(cfg.wall_point_w_m, dtype=float) + 0.5 * thickness_m * n
    fmt = lambda v: " ".join(f"{x:.9g}" for x in v)  # noqa: E731
    return (f'    <geom name="wall" type="box" pos="{fmt(c)}" zaxis="{fmt(n)}" size="3 3 {0.5 * thickness_m:.9g}" '
            f'contype="0" conaffinity="1" friction="{cfg.wall_friction:.9g} 0.005 0.0001" rgba="0.6 0.6 0.7 1"/>\n')


class WallPushTask(Task):
    """The wall, the approach and the contact command of a wall push (module docstring)."""

    def __init__(self, scenario: WallPushScenario):
        self.scenario = scenario
        self.normal_w = np.asarray(scenario.contact.normal_w, dtype=float)
        #: the contact force along the normal [N] and the contact wrench about the link's centre
        #: (force world, torque body), measured after every physics step
        self.contact_force_n = 0.0
        self.contact_wrench = np.zeros(6)
        self.contact_log: dict[str, list] = {k: [] for k in ("t", "force_true_n", "force_cmd_n", "force_hat_n",
                                                              "wrench_true", "wrench_hat", "engaged")}
        self._base_target = self._shifted_target = None
        self._f0: float | None = None

    def initialize(self, runner) -> None:
        """The plant's model with the wall (names and ids of bodies, sensors and actuators are
        unchanged); the approach's length from the contact point's start to ``preload_m`` inside the
        wall."""
        sc, plant = self.scenario, runner.plant
        wall = SkeletonModel(sc.skeleton, plant.geometry, sc.rotors, plant.dt)
        wall.model = mujoco.MjModel.from_xml_string(wall.xml.replace("  </worldbody>", wall_mjcf(sc.contact) + "  </worldbody>"))
        wall.data = mujoco.MjData(wall.model)
        wall.reset(sc.start)
        plant.use_model(wall)
        self._wall_geom = wall.model.geom("wall").id
        self._bar_geom = wall.model.geom("link1_bar").id
        truth = wall.truth()
        tip = truth.p_w_m[0] + quat_to_rotmat(truth.q_wxyz[0]) @ sc.contact_b_m
        self._approach_total_m = float(self.normal_w @ (np.asarray(sc.contact.wall_point_w_m) - tip)) + sc.contact.preload_m

    def after_step(self, runner, k: int, t: float) -> None:
        """Sum of the bar-wall contact forces on the link (world) and their wrench about its centre."""
        model = runner.model
        m, d = model.model, model.data
        force = np.zeros(6)
        f6 = np.zeros(6)
        center = d.xpos[model.body_ids[0]]
        R = d.xmat[model.body_ids[0]].reshape(3, 3)
        wrench = np.zeros(6)
        for i in range(d.ncon):
            con = d.contact[i]
            if {con.geom1, con.geom2} != {self._wall_geom, self._bar_geom}:
                continue
            mujoco.mj_contactForce(m, d, i, f6)
            frame = con.frame.reshape(3, 3)  # rows: normal, tangents (world)
            f_w = frame.T @ f6[:3]  # force on geom2 from geom1
            if con.geom2 != self._bar_geom:
                f_w = -f_w
            force[:3] += f_w
            wrench[:3] += f_w
            wrench[3:] += R.T @ np.cross(con.pos - center, f_w)
        self.contact_wrench = wrench
        self.contact_force_n = float(-self.normal_w @ force[:3])  # the wall pushes back along -n

    def schedule(self, runner, t: float) -> tuple[np.ndarray, ContactTarget | None, float]:
        """At ``t``: the approach's shift of the pose target (world), the contact to command
        (``None`` before ``contact_start_s``) and its force [N]."""
        c, n = self.scenario.contact, self.normal_w
        shift = self._approach_total_m * smoothstep5((t - c.approach_start_s) / max(c.approach_duration_s, 1e-9))
        if t < c.contact_start_s:
            return shift * n, None, 0.0
        if self._f0 is None:  # the ramp starts from the force the pose spring already applies
            est = runner.firmware[0].external_wrench()
            self._f0 = min(max(float(-n @ est[0][:3]), 0.0), c.force_n) if est is not None else 0.0
        f = self._f0 + (c.force_n - self._f0) * smoothstep5((t - c.contact_start_s) / max(c.force_ramp_s, 1e-9))
        return shift * n, ContactTarget(n, self.scenario.contact_b_m, f), f

    def after_outputs(self, runner, engine, outputs: list, t: float) -> None:
        """The engine's pose target shifted by the approach; the contact commanded."""
        shift, contact, _ = self.schedule(runner, t)
        fw = runner.firmware[0]
        if fw.target is not None:
            if fw.target is not self._shifted_target:  # a new target from the companion engine
                self._base_target = fw.target
            self._shifted_target = replace(self._base_target, p_w_m=self._base_target.p_w_m + shift)
            fw.target = self._shifted_target
        fw.set_contact(t, contact)

    def after_log(self, runner, t: float, truth) -> None:
        _, contact, f_cmd = self.schedule(runner, t)
        est = runner.firmware[0].external_wrench()
        w_hat, lam_hat = est if est is not None else (np.zeros(6), np.zeros(0))
        lg = self.contact_log
        lg["t"].append(t)
        lg["force_true_n"].append(self.contact_force_n)
        lg["force_cmd_n"].append(f_cmd)
        lg["force_hat_n"].append(float(lam_hat[0]) if lam_hat.size else float(-self.normal_w @ w_hat[:3]))
        lg["wrench_true"].append(self.contact_wrench.copy())
        lg["wrench_hat"].append(np.asarray(w_hat).copy())
        lg["engaged"].append(contact is not None)


def _rms(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def wall_push(scenario: WallPushScenario, out_dir: Path | None, *, progress=None, plots: bool = True) -> dict:
    """Fly the wall push; its metrics (and ``metrics.json``, ``log.npz`` with the contact log as
    ``contact_*``, ``scenario.toml`` and the plot ``wall_push.png`` in ``out_dir``)."""
    task = WallPushTask(scenario)
    runner = BatchRunner(scenario, task=task)
    sc = runner.scenario
    runner.run(sc.duration_s, progress=progress)
    arrays = runner.arrays()
    cl = {k: np.asarray(v) for k, v in task.contact_log.items()}
    steady = cl["t"] >= sc.contact.steady_start_s
    f_err = cl["force_true_n"][steady] - cl["force_cmd_n"][steady]
    obs_err = cl["force_hat_n"][steady] - cl["force_true_n"][steady]
    w_err = cl["wrench_hat"][steady] - cl["wrench_true"][steady]
    n = np.asarray(sc.contact.normal_w, dtype=float)
    w = arrays["t"] >= sc.contact.steady_start_s
    dp = arrays["p_true"][w, 0] - planned_positions(arrays)[w, 0]
    dp_free = dp - np.outer(dp @ n, n)
    att = np.degrees(np.linalg.norm(attitude_error(arrays["q_true"][w, 0], arrays["q_target"][w, 0]), axis=-1))
    metrics = {
        "scenario": sc.name, "seed": sc.seed, "force_cmd_n": sc.contact.force_n,
        "steady_window_s": [sc.contact.steady_start_s, float(cl["t"][-1])],
        "force_mean_true_n": float(cl["force_true_n"][steady].mean()),
        "force_error_rms_n": _rms(f_err),
        "force_error_rms_rel": _rms(f_err) / sc.contact.force_n if sc.contact.force_n > 0 else None,
        "contact_lost_fraction": float(np.mean(cl["force_true_n"][steady] <= 0.0)),
        "observer_force_error_rms_n": _rms(obs_err),
        "observer_force_error_mean_n": float(obs_err.mean()),
        "observer_wrench_error_rms": {"force_n": _rms(np.linalg.norm(w_err[:, :3], axis=1)),
                                      "torque_nm": _rms(np.linalg.norm(w_err[:, 3:], axis=1))},
        "free_pos_error_rms_m": _rms(np.linalg.norm(dp_free, axis=1)),
        "att_error_rms_deg": _rms(att),
        "crashed": runner.crashed, "crash_reason": runner.crash_reason,
        "realtime_factor": runner.sim_s / runner.wall_s if runner.wall_s > 0 else None,
    }
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        np.savez_compressed(out_dir / "log.npz", **arrays, **{f"contact_{k}": v for k, v in cl.items()})
        (out_dir / "scenario.toml").write_text(dump_toml(replace(sc, duration_s=runner.sim_s)))
        if plots:
            _plot(cl, sc, out_dir / "wall_push.png")
    return metrics


def _plot(cl: dict, sc: WallPushScenario, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(cl["t"], cl["force_cmd_n"], "k--", lw=1, label="commanded lambda_d")
    ax.plot(cl["t"], cl["force_true_n"], lw=0.8, label="MuJoCo contact force")
    ax.plot(cl["t"], cl["force_hat_n"], lw=0.8, label="observer lambda_c^")
    ax.axvline(sc.contact.steady_start_s, color="gray", lw=0.5)
    ax.set(xlabel="t [s]", ylabel="normal force [N]", title=f"{sc.name}: hybrid pose/wrench control")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

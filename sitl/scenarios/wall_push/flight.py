"""The contact scenario of issue 17: one ODAR pushes on a wall under hybrid pose/wrench control (thesis sec. 2.3.3).

A :class:`WallPushScenario` is a single-link :class:`~sitl.scenario.Scenario` with a ``[contact]``
section (:class:`ContactConfig`) and ``firmware.controller = "hybrid"``. The MuJoCo model gets a
wall (a box whose face passes through ``wall_point_w_m`` with the unit normal ``normal_w``
pointing into it; it collides with the link's bar). The flight:

1. take-off and hover under the hybrid controller without a contact (pose control);
2. from ``approach_start_s`` the pose target moves along ``normal_w`` (quintic, over
   ``approach_duration_s``) until the contact point ``contact_b_m`` (default: the right tip) is
   ``preload_m`` inside the wall;
3. at ``contact_start_s`` the contact is commanded (:meth:`LinkFirmware.set_contact`) and its
   force ramps (quintic, ``force_ramp_s``) to ``force_n`` from the observer's estimate of the
   preload (what the pose spring pushed with; from 0 the link would bounce off the wall); the pose target keeps holding
   the free directions (position along the wall, attitude).

Metrics from ``contact_start_s + force_ramp_s + settle_s`` to the end: the force tracking error
(MuJoCo's contact force, :func:`mujoco.mj_contactForce` summed over the bar-wall contacts and
projected on ``normal_w``, against the commanded force), RMS and relative to ``force_n``; the
observer's error (its ``lambda_c^`` against the same contact force, and its whole wrench estimate
against the contact wrench about the centre); the pose error in the free directions.

The batch runner is :class:`~sitl.runner.BatchRunner` with three hooks: the plant's model is
rebuilt with the wall before the flight, the targets the companion engine sends are shifted by the
approach, and every physics step records the contact force.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import mujoco
import numpy as np

from companion.config import load_setup
from companion.estimation.so3 import attitude_error, quat_to_rotmat
from companion.trajectory import smoothstep5
from link_firmware_sim.hybrid import ContactTarget

from .model import SkeletonModel
from .runner import BatchRunner
from .scenario import Scenario

__all__ = ["ContactConfig", "WallPushScenario", "load_wall_scenario", "WallPushRunner", "wall_push", "wall_mjcf"]

log = logging.getLogger(__name__)


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
    """A single-link scenario with a wall to push on (``[contact]``)."""

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
    return load_setup(WallPushScenario, path, **overrides)


def wall_mjcf(cfg: ContactConfig, thickness_m: float = 0.1) -> str:
    """The wall: a box whose face contains ``wall_point_w_m``, its z axis along ``normal_w``."""
    n = np.asarray(cfg.normal_w, dtype=float)
    c = np.asarray(cfg.wall_point_w_m, dtype=float) + 0.5 * thickness_m * n
    fmt = lambda v: " ".join(f"{x:.9g}" for x in v)  # noqa: E731
    return (f'    <geom name="wall" type="box" pos="{fmt(c)}" zaxis="{fmt(n)}" size="3 3 {0.5 * thickness_m:.9g}" '
            f'contype="0" conaffinity="1" friction="{cfg.wall_friction:.9g} 0.005 0.0001" rgba="0.6 0.6 0.7 1"/>\n')


class WallPushRunner(BatchRunner):
    """:class:`BatchRunner` with the wall, the approach and the contact command (module docstring)."""

    def __init__(self, scenario: WallPushScenario):
        super().__init__(scenario)
        sc = self.scenario
        plant = self.plant
        # The plant's model with the wall (names and ids of bodies, sensors and actuators are unchanged).
        wall = SkeletonModel(sc.skeleton, plant.geometry, sc.rotors, plant.dt)
        wall.model = mujoco.MjModel.from_xml_string(wall.xml.replace("  </worldbody>", wall_mjcf(sc.contact) + "  </worldbody>"))
        wall.data = mujoco.MjData(wall.model)
        wall.reset(sc.start)
        wall.begin_step()
        plant.model = self.model = wall
        self._wall_geom = wall.model.geom("wall").id
        self._bar_geom = wall.model.geom("link1_bar").id
        self._n = np.asarray(sc.contact.normal_w, dtype=float)
        self.contact_force_n = 0.0
        self.contact_wrench = np.zeros(6)
        self.contact_log: dict[str, list] = {k: [] for k in ("t", "force_true_n", "force_cmd_n", "force_hat_n",
                                                              "wrench_true", "wrench_hat", "engaged")}
        self._base_target = self._shifted_target = None
        self._f0: float | None = None
        end_tick = plant.end_tick

        def end_tick_and_measure() -> None:
            end_tick()
            self._measure_contact()

        plant.end_tick = end_tick_and_measure
        # the approach distance: from the contact point's start to preload_m inside the wall
        truth = wall.truth()
        tip = truth.p_w_m[0] + quat_to_rotmat(truth.q_wxyz[0]) @ sc.contact_b_m
        self._approach_total_m = float(self._n @ (np.asarray(sc.contact.wall_point_w_m) - tip)) + sc.contact.preload_m

    def _measure_contact(self) -> None:
        """Sum of the bar-wall contact forces on the link (world) and their wrench about its centre."""
        m, d = self.model.model, self.model.data
        force = np.zeros(6)
        f6 = np.zeros(6)
        center = d.xpos[self.model.body_ids[0]]
        R = d.xmat[self.model.body_ids[0]].reshape(3, 3)
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
        self.contact_force_n = float(-self._n @ force[:3])  # the wall pushes back along -n

    def _schedule(self, t: float) -> tuple[np.ndarray, ContactTarget | None, float]:
        c = self.scenario.contact
        shift = self._approach_total_m * smoothstep5((t - c.approach_start_s) / max(c.approach_duration_s, 1e-9))
        if t < c.contact_start_s:
            return shift * self._n, None, 0.0
        if self._f0 is None:  # the ramp starts from the force the pose spring already applies
            est = self.firmware[0].external_wrench()
            self._f0 = min(max(float(-self._n @ est[0][:3]), 0.0), c.force_n) if est is not None else 0.0
        f = self._f0 + (c.force_n - self._f0) * smoothstep5((t - c.contact_start_s) / max(c.force_ramp_s, 1e-9))
        return shift * self._n, ContactTarget(self._n, self.scenario.contact_b_m, f), f

    def _apply(self, engine, outputs, t: float) -> None:
        super()._apply(engine, outputs, t)
        shift, contact, _ = self._schedule(t)
        fw = self.firmware[0]
        if fw.target is not None:
            if fw.target is not self._shifted_target:  # a new target from the companion engine
                self._base_target = fw.target
            self._shifted_target = replace(self._base_target, p_w_m=self._base_target.p_w_m + shift)
            fw.target = self._shifted_target
        fw.set_contact(t, contact)

    def _log_tick(self, t: float, truth) -> None:
        super()._log_tick(t, truth)
        _, contact, f_cmd = self._schedule(t)
        est = self.firmware[0].external_wrench()
        w_hat, lam_hat = est if est is not None else (np.zeros(6), np.zeros(0))
        lg = self.contact_log
        lg["t"].append(t)
        lg["force_true_n"].append(self.contact_force_n)
        lg["force_cmd_n"].append(f_cmd)
        lg["force_hat_n"].append(float(lam_hat[0]) if lam_hat.size else float(-self._n @ w_hat[:3]))
        lg["wrench_true"].append(self.contact_wrench.copy())
        lg["wrench_hat"].append(np.asarray(w_hat).copy())
        lg["engaged"].append(contact is not None)


def _rms(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def wall_push(scenario: WallPushScenario, out_dir: Path | None, progress=None) -> dict:
    """Fly the wall push; its metrics (and ``metrics.json``, ``log.npz``, ``wall_push.png`` in ``out_dir``)."""
    runner = WallPushRunner(scenario)
    sc = runner.scenario
    runner.run(sc.duration_s, progress=progress)
    arrays = runner.arrays()
    cl = {k: np.asarray(v) for k, v in runner.contact_log.items()}
    steady = cl["t"] >= sc.contact.steady_start_s
    f_err = cl["force_true_n"][steady] - cl["force_cmd_n"][steady]
    obs_err = cl["force_hat_n"][steady] - cl["force_true_n"][steady]
    w_err = cl["wrench_hat"][steady] - cl["wrench_true"][steady]
    n = np.asarray(sc.contact.normal_w, dtype=float)
    w = arrays["t"] >= sc.contact.steady_start_s
    dp = arrays["p_true"][w, 0] - arrays["p_target"][w, 0]
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
        "real_time_factor": runner.sim_s / runner.wall_s if runner.wall_s > 0 else None,
    }
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        np.savez_compressed(out_dir / "log.npz", **arrays, **{f"contact_{k}": v for k, v in cl.items()})
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

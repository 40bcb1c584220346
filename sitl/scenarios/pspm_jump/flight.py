"""PSPM teleoperation of one ODAR in MuJoCo (thesis sec. 2.3.4): scripted operator jumps, with and without PSPM.

A :class:`~.config.PspmJumpScenario` is a single-link :class:`~sitl.scenario.Scenario` with a
``[teleop]`` section (:class:`~.config.TeleopConfig`). Each flight runs the full SITL loop (MuJoCo, rotors and ESCs,
seeded sensors, the link's EKF and firmware); the companion engine arms the link and gives the
hover pose. A scripted master device replaces every pose target the engine sends (at its target
rate, 50 Hz) by an operator set pose: the hover pose, moved by ``jump_m`` along ``jump_axis_w``
from ``jump_s`` on and turned by ``yaw_jump_deg`` about the vertical from ``yaw_jump_s`` on (two
abrupt jumps). The set poses go through :meth:`LinkFirmware.set_target
<link_firmware_sim.firmware.LinkFirmware.set_target>`, the same entry as SET_POSITION_TARGET_LOCAL_NED
and SET_ATTITUDE_TARGET on a vehicle, so the firmware's ``pspm_mode`` decides what the link flies:

* ``"on"`` (SKL_PSPM_EN = 1): PSPM modulates every set pose with its energy reservoirs, the
  slave law of sec. 2.3.4 tracks the modulated pose;
* ``"bypass"`` (SKL_PSPM_EN = 2): the same slave law on the raw set poses (without PSPM).

The master side's haptic force ``f_h = -K_ht (p_d - p_bar)`` (:func:`~link_firmware_sim.controllers.pspm.haptic_feedback`;
the scripted device does not move between its jumps, and no observer runs under the slave law, so
the ``B_ht`` and ``K_hf f_e^`` terms are zero) is computed and logged with the reservoirs.

The scripted operator is a :class:`PspmJumpTask`: its set poses replace the engine's targets
(:meth:`~sitl.task.Task.before_outputs`), its log rows follow the run's (:meth:`~sitl.task.Task.after_log`).
:func:`pspm_jump` flies the scenario once per mode. Metrics per mode: the position overshoot along the jump (truth; from ``jump_s`` until
``yaw_jump_s``), its 5 % settling time and final error, the yaw overshoot after ``yaw_jump_s``, the
reservoirs' minimum, the largest speed, and whether the flight crashed.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.configfile import dump_toml
from companion.engine import TargetOut
from companion.estimation.so3 import quat_from_euler_zyx, quat_mul, quat_to_rotmat
from companion.messages import PoseTarget
from link_firmware_sim.controllers.pspm import haptic_feedback
from sitl.runner import BatchRunner
from sitl.task import Task

from .config import PspmJumpScenario

__all__ = ["PspmJumpTask", "jump_runner", "jump_metrics", "pspm_jump", "plot_jump", "heading_deg", "MODES"]

log = logging.getLogger(__name__)

#: firmware pspm_mode per run name
MODES = {"unmodulated": "bypass", "pspm": "on"}


def heading_deg(q_wxyz: np.ndarray, q_ref_wxyz: np.ndarray) -> float:
    """Heading of ``q`` relative to ``q_ref`` about the world vertical [deg]."""
    R = quat_to_rotmat(q_wxyz) @ quat_to_rotmat(q_ref_wxyz).T
    return math.degrees(math.atan2(R[1, 0], R[0, 0]))


class PspmJumpTask(Task):
    """The scripted operator in place of the engine's targets (module docstring)."""

    def __init__(self, scenario: PspmJumpScenario):
        self.scenario = scenario
        self.axis = np.asarray(scenario.teleop.jump_axis_w, dtype=float)
        self.base: PoseTarget | None = None  # the engine's (hover) pose the operator moves from
        self.teleop_log: dict[str, list] = {k: [] for k in (
            "t", "along_true_m", "along_d_m", "along_bar_m", "yaw_true_deg", "yaw_d_deg", "yaw_bar_deg",
            "energy_t_j", "energy_r_j", "f_h_n", "speed_m_s")}

    def operator_pose(self, base: PoseTarget, t: float) -> PoseTarget:
        """The scripted master's set pose at ``t``: ``base`` jumped (position, then yaw)."""
        tc = self.scenario.teleop
        p = base.p_w_m + (tc.jump_m * self.axis if t >= tc.jump_s else 0.0)
        yaw = math.radians(tc.yaw_jump_deg) if t >= tc.yaw_jump_s else 0.0
        return PoseTarget.hold(p, quat_mul(quat_from_euler_zyx(yaw, 0.0, 0.0), base.q_wxyz))

    def before_outputs(self, runner, engine, outputs: list, t: float) -> list:
        """Every pose target of the engine replaced by the operator's set pose (as
        SET_POSITION_TARGET_LOCAL_NED / SET_ATTITUDE_TARGET would set it); the rest to the runner."""
        rest = []
        for out in outputs:
            if isinstance(out, TargetOut):
                fw = runner.firmware[engine.links[out.row].index]
                if self.base is None or t < self.scenario.teleop.jump_s:
                    self.base = out.target
                fw.set_target(t, self.operator_pose(self.base, t))
            else:
                rest.append(out)
        return rest

    def after_log(self, runner, t: float, truth) -> None:
        if self.base is None:
            return
        fw = runner.firmware[0]
        op = self.operator_pose(self.base, t)
        mod = fw.active_target(t)
        report = fw.pspm_report()
        f_h, _ = haptic_feedback(np.zeros(3), np.zeros(3), op.p_w_m, op.q_wxyz, mod.p_w_m, mod.q_wxyz, np.zeros(3),
                                 np.zeros(3), self.scenario.teleop.haptic)
        p0, q0, a = self.base.p_w_m, self.base.q_wxyz, self.axis
        lg = self.teleop_log
        lg["t"].append(t)
        lg["along_true_m"].append(float(a @ (truth.p_w_m[0] - p0)))
        lg["along_d_m"].append(float(a @ (op.p_w_m - p0)))
        lg["along_bar_m"].append(float(a @ (mod.p_w_m - p0)))
        lg["yaw_true_deg"].append(heading_deg(truth.q_wxyz[0], q0))
        lg["yaw_d_deg"].append(heading_deg(op.q_wxyz, q0))
        lg["yaw_bar_deg"].append(heading_deg(mod.q_wxyz, q0))
        lg["energy_t_j"].append(report[0] if report is not None else math.nan)
        lg["energy_r_j"].append(report[1] if report is not None else math.nan)
        lg["f_h_n"].append(f_h)
        lg["speed_m_s"].append(float(np.linalg.norm(truth.v_w_m_s[0])))


def jump_runner(scenario: PspmJumpScenario, pspm_mode: str) -> BatchRunner:
    """A runner of ``scenario`` with the firmware's ``pspm_mode`` (``"on"``, ``"bypass"``) and the
    scripted operator (``runner.task``: its ``teleop_log``)."""
    sc = replace(scenario, firmware=replace(scenario.firmware, pspm_mode=pspm_mode))
    return BatchRunner(sc, task=PspmJumpTask(sc))


def jump_metrics(t, along_m, yaw_deg, energy_t_j, energy_r_j, speed_m_s, jump_m: float, jump_s: float,
                 yaw_jump_deg: float, yaw_jump_s: float) -> dict:
    """Overshoot and 5 % settling of the position jump (``jump_s`` to ``yaw_jump_s``), the yaw
    overshoot after ``yaw_jump_s``, the reservoirs' minimum (``None`` when not logged: no PSPM)."""
    t, along, yaw = np.asarray(t), np.asarray(along_m), np.asarray(yaw_deg)
    win = (t >= jump_s) & (t < yaw_jump_s)
    err = np.abs(along[win] - jump_m)
    out_of_band = np.nonzero(err > 0.05 * jump_m)[0]
    settled = float(t[win][out_of_band[-1]] - jump_s) if out_of_band.size else 0.0
    after_yaw = t >= yaw_jump_s
    yaw_sign = 1.0 if yaw_jump_deg >= 0 else -1.0
    e_t, e_r = np.asarray(energy_t_j, dtype=float), np.asarray(energy_r_j, dtype=float)
    overshoot = float(max(along[win].max() - jump_m, 0.0))
    return {
        "overshoot_m": overshoot,
        "overshoot_pct": 100.0 * overshoot / jump_m if jump_m > 0 else None,
        "settling_time_5pct_s": settled,
        "settled_in_window": bool(not out_of_band.size or out_of_band[-1] < err.size - 1),
        "final_error_m": float(err[-1]),
        "yaw_overshoot_deg": float(max((yaw_sign * yaw[after_yaw]).max() - abs(yaw_jump_deg), 0.0)),
        "yaw_final_error_deg": float(abs(yaw[after_yaw][-1] - yaw_jump_deg)),
        "reservoir_min_j": {"E_t": float(np.nanmin(e_t)) if np.isfinite(e_t).any() else None,
                            "E_r": float(np.nanmin(e_r)) if np.isfinite(e_r).any() else None},
        "max_speed_m_s": float(np.max(speed_m_s)),
    }


def pspm_jump(scenario: PspmJumpScenario, out_dir: Path | None, *, runs=tuple(MODES), progress=None,
              plots: bool = True) -> dict:
    """Fly the operator jumps once per run (``"unmodulated"``, ``"pspm"``); returns the metrics (and
    writes ``metrics.json``, ``log.npz`` with each run's series as ``<run>_<key>``,
    ``scenario.toml`` and the plot ``pspm_jump.png`` in ``out_dir``)."""
    tc = scenario.teleop
    out: dict = {"scenario": scenario.name, "seed": scenario.seed, "jump_m": tc.jump_m, "yaw_jump_deg": tc.yaw_jump_deg,
                 "operator_hz": scenario.companion.target_rate_hz, "runs": {}}
    series = {}
    for name in runs:
        runner = jump_runner(scenario, MODES[name])
        runner.run(scenario.duration_s, progress=progress)
        lg = {k: np.asarray(v) for k, v in runner.task.teleop_log.items()}
        lg["axis"] = runner.task.axis
        m = jump_metrics(lg["t"], lg["along_true_m"], lg["yaw_true_deg"], lg["energy_t_j"], lg["energy_r_j"],
                         lg["speed_m_s"], tc.jump_m, tc.jump_s, tc.yaw_jump_deg, tc.yaw_jump_s)
        m.update(crashed=runner.crashed, crash_reason=runner.crash_reason,
                 realtime_factor=runner.sim_s / runner.wall_s if runner.wall_s > 0 else None)
        out["runs"][name] = m
        log.info("%s: %s", name, m)
        series[name] = lg
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(out, indent=2) + "\n")
        np.savez_compressed(out_dir / "log.npz", **{f"{n}_{k}": v for n, r in series.items() for k, v in r.items()})
        (out_dir / "scenario.toml").write_text(dump_toml(scenario))
        if plots:
            plot_jump(series, out_dir / "pspm_jump.png", tc.jump_m, tc.yaw_jump_deg, "MuJoCo SITL")
    return out


def plot_jump(series: dict, path: Path, jump_m: float, yaw_jump_deg: float, title: str) -> None:
    """Position along the jump and yaw (operator, modulated, flown), reservoirs, haptic force."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    for name, r in series.items():
        axes[0].plot(r["t"], r["along_true_m"], lw=1, label=f"flown ({name})")
        axes[1].plot(r["t"], r["yaw_true_deg"], lw=1, label=f"flown ({name})")
        axes[3].plot(r["t"], r["f_h_n"] @ r["axis"], lw=0.8, label=f"haptic force along the jump ({name})")
    r = series.get("pspm", next(iter(series.values())))
    axes[0].plot(r["t"], r["along_d_m"], "k--", lw=0.8, label="operator set position")
    axes[0].plot(r["t"], r["along_bar_m"], ":", lw=1.4, label="modulated set position (PSPM)")
    axes[1].plot(r["t"], r["yaw_d_deg"], "k--", lw=0.8, label="operator set yaw")
    axes[1].plot(r["t"], r["yaw_bar_deg"], ":", lw=1.4, label="modulated set yaw (PSPM)")
    axes[2].plot(r["t"], r["energy_t_j"], label="E_t (translation)")
    axes[2].plot(r["t"], r["energy_r_j"], label="E_r (rotation)")
    for ax, ylab in zip(axes, ("along the jump [m]", "yaw [deg]", "reservoir [J]", "f_h [N]")):
        ax.set_ylabel(ylab)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t [s]")
    axes[0].set_title(f"{title}: operator jumps of {jump_m:g} m and {yaw_jump_deg:g} deg yaw, with and without PSPM")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

"""A ground robot's run: MuJoCo, the CPG and the servos on one clock, the body frame's velocities
and the metrics.

:class:`GroundRun` steps the robot (``physics_dt_s``; the robot applies what it adds to MuJoCo
itself, e.g. the snake's ground friction), and at ``cpg_rate_hz`` sets the servos' targets from the
CPG and integrates the CPG over the next period with the command in force; it logs the body at
``log_rate_hz``. The robot and its CPG come from the kind: ``robot`` answers ``step()``,
``centre_of_mass()``, ``heading()``, ``in_plane(p)``, ``outline()`` (its shape's points, for the
plot), ``servo_angles()``; ``cpg`` answers ``targets()`` (the servos' targets now, actuator order),
``advance(command, dt_s)`` and ``axes`` (names of actuator groups, for the tracking metrics), and
``control``: ``None``, or the motion commands' control, whose ``series()`` (``t``, the desired
``v_x_d``, ``omega_d`` and, for the pivotboard, ``v_dot_d``, the inputs ``A``, ``B``) joins the log
as ``control_*``.

**The body frame {B}** (thesis Fig. 4-1): at the robot's centre of mass, its x axis the robot's
heading in the ground's plane. The thesis's velocities are averages over one CPG period (sec.
4.5.3: "during time [t - dt, t]"): :func:`period_velocities` gives, a period after the start, the
centre of mass's displacement over the last period in {B} (at the period's mean heading) over the
period, ``v_x`` (forward) and ``v_y``, and the heading's change over it, ``omega``.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from companion.configfile import dump_toml

__all__ = ["GroundRun", "body_velocity", "period_velocities", "period_acceleration", "run_metrics", "speed_error",
           "command_tracking", "fly_ground", "write_run"]


class GroundRun:
    """The run's loop and log (module docstring)."""

    def __init__(self, sc, robot, cpg):
        self.sc, self.robot, self.cpg = sc, robot, cpg
        self.cpg_every = int(round(1.0 / (sc.cpg_rate_hz * sc.physics_dt_s)))
        self.log_every = int(round(1.0 / (sc.log_rate_hz * sc.physics_dt_s)))
        self.rows: dict[str, list] = {k: [] for k in ("t", "com_w", "com_plane", "heading", "target", "angle",
                                                     "outline_plane")}
        self.target = np.zeros(robot.model.nu)
        self.wall_s = 0.0

    def run(self, progress=None) -> None:
        sc, robot = self.sc, self.robot
        dt = sc.physics_dt_s
        n = int(round(sc.duration_s / dt))
        wall0 = time.perf_counter()
        for k in range(n + 1):
            t = k * dt
            if k % self.cpg_every == 0:
                self.target = self.cpg.targets()
                robot.data.ctrl[:] = self.target
                self.cpg.advance(sc.command_at(t), self.cpg_every * dt)
            if k % self.log_every == 0:
                self._log(t)
            if k == n:
                break
            robot.step()
            if progress is not None and k % 500 == 499:
                progress(500 * dt)
        self.wall_s = time.perf_counter() - wall0

    def _log(self, t: float) -> None:
        robot, r = self.robot, self.rows
        com = robot.centre_of_mass()
        r["t"].append(t)
        r["com_w"].append(com)
        r["com_plane"].append(robot.in_plane(com))
        r["heading"].append(robot.heading())
        r["target"].append(np.array(self.target, dtype=float))
        r["angle"].append(robot.servo_angles())
        r["outline_plane"].append(robot.in_plane(robot.outline()))

    def arrays(self) -> dict[str, np.ndarray]:
        out = {k: np.asarray(v) for k, v in self.rows.items()}
        out["heading"] = np.unwrap(out["heading"])
        out.update(zip(("period_t", "v_x", "v_y", "omega"), period_velocities(
            out["t"], out["com_plane"], out["heading"], self.cpg.period_s)))
        control = getattr(self.cpg, "control", None)
        if control is not None:  # motion commands: what the control asked for, once per period
            out.update({f"control_{k}": v for k, v in control.series().items()})
        return out


def body_velocity(d_plane, mid_heading, d_heading, period_s: float):
    """``(v_x, v_y, omega)`` in {B} of a displacement ``d_plane`` (..., 2) in the ground's plane and a
    heading change ``d_heading`` over ``period_s``, {B} at the heading ``mid_heading`` (the period's
    middle)."""
    d = np.asarray(d_plane, dtype=float)
    c, s = np.cos(mid_heading), np.sin(mid_heading)
    return ((c * d[..., 0] + s * d[..., 1]) / period_s, (-s * d[..., 0] + c * d[..., 1]) / period_s,
            np.asarray(d_heading) / period_s)


def period_velocities(t: np.ndarray, p_plane: np.ndarray, heading: np.ndarray, period_s: float):
    """``(t, v_x, v_y, omega)`` at every sample a whole period after the first: the centre of mass's
    displacement over the last ``period_s`` in {B} (rotated by the mean of the (unwrapped) heading
    over the period's samples: a body that undulates turns its heading to and fro within a
    period) over the period, and the heading's change over it."""
    dt = float(t[1] - t[0])
    m = int(round(period_s / dt))
    if len(t) <= m:
        return (np.zeros(0),) * 4
    d = p_plane[m:] - p_plane[:-m]
    c = np.concatenate(([0.0], np.cumsum(heading)))
    mean = (c[m + 1:] - c[:-m - 1]) / (m + 1)  # samples k - m .. k
    return (t[m:], *body_velocity(d, mean, heading[m:] - heading[:-m], period_s))


def period_acceleration(a: dict, period_s: float, log_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """``(t, v_dot)``: the forward acceleration of the period velocities, ``v_x``'s change over a
    period, over the period (the pivotboard's eq. 4.2 is written in these velocities)."""
    m = int(round(period_s * log_rate_hz))
    if len(a["v_x"]) <= m:
        return np.zeros(0), np.zeros(0)
    return a["period_t"][m:], (a["v_x"][m:] - a["v_x"][:-m]) / period_s


def _summary(x: np.ndarray) -> dict:
    return {"mean": float(np.mean(x)), "std": float(np.std(x)), "n": int(x.size)}


def run_metrics(sc, a: dict, wall_s: float, axes: dict[str, list[int]]) -> dict:
    """Per command (its window from ``settle_s`` after it starts) the mean and standard deviation of
    ``v_x``, ``v_y``, ``omega``; the distance, path length and heading change over the run; the
    servos' RMS tracking error per group of ``axes``."""
    out: dict = {"scenario": sc.name, "kind": sc.kind, "seed": sc.seed, "duration_s": float(a["t"][-1]),
                 "realtime_factor": float(a["t"][-1] / wall_s) if wall_s > 0 else None}
    per = []
    for k, t0, t1 in sc.windows():
        w = (a["period_t"] >= t0) & (a["period_t"] <= t1)
        row = {"command": asdict(sc.commands[k]), "window_s": [t0, t1]}
        if w.any():
            row.update(v_x_m_s=_summary(a["v_x"][w]), v_y_m_s=_summary(a["v_y"][w]), omega_rad_s=_summary(a["omega"][w]))
        per.append(row)
    out["commands"] = per
    out["distance_m"] = float(np.linalg.norm(a["com_plane"][-1] - a["com_plane"][0]))
    out["path_length_m"] = float(np.sum(np.linalg.norm(np.diff(a["com_plane"], axis=0), axis=1)))
    out["heading_change_deg"] = float(np.degrees(a["heading"][-1] - a["heading"][0]))
    err = a["target"] - a["angle"]
    out["servo_rms_deg"] = {name: float(np.degrees(np.sqrt(np.mean(err[:, idx] ** 2)))) for name, idx in axes.items()}
    return out


def speed_error(a: dict, row: dict, cmd, w: np.ndarray, t0: float, t1: float) -> None:
    """A velocity command's forward tracking: the RMS of ``v_x - v_x_m_s`` over the period
    velocities ``w`` selects (``row["v_x_rms_err_m_s"]``)."""
    row["v_x_rms_err_m_s"] = float(np.sqrt(np.mean((a["v_x"][w] - cmd.v_x_m_s) ** 2)))


def command_tracking(sc, a: dict, metrics: dict, forward=speed_error) -> None:
    """Each motion command's tracking over its window (``metrics["commands"]``' rows), as the thesis
    reports it (sec. 4.7.2): ``forward(a, row, command, period_window, t0, t1)`` adds the forward
    motion's error (default :func:`speed_error`); then, holding the line, the RMS of the lateral
    offset ``y`` (at the log rate), else of ``omega - omega_rad_s`` (the period velocities).
    Commands of ``mode = "cpg"`` and empty windows are left as they are."""
    for (k, t0, t1), row in zip(sc.windows(), metrics["commands"]):
        cmd = sc.commands[k]
        w = (a["period_t"] >= t0) & (a["period_t"] <= t1)
        if cmd.mode == "cpg" or not w.any():
            continue
        forward(a, row, cmd, w, t0, t1)
        if cmd.hold_line:
            wy = (a["t"] >= t0) & (a["t"] <= t1)
            row["y_rms_m"] = float(np.sqrt(np.mean(a["com_plane"][wy, 1] ** 2)))
        else:
            row["omega_rms_err_rad_s"] = float(np.sqrt(np.mean((a["omega"][w] - cmd.omega_rad_s) ** 2)))


def fly_ground(sc, run: GroundRun, out_dir: Path | None, stem: str, *, progress=None, plots: bool = True,
               forward=speed_error, more=None) -> dict:
    """Fly ``run`` (of the scenario ``sc``); returns the metrics (:func:`run_metrics`, ``more(a,
    metrics)``'s additions, the motion commands' tracking with ``forward``: :func:`command_tracking`)
    and writes the run folder when ``out_dir`` is given (:func:`write_run`, files named ``stem``)."""
    run.run(progress)
    a = run.arrays()
    metrics = run_metrics(sc, a, run.wall_s, run.cpg.axes)
    if more is not None:
        more(a, metrics)
    command_tracking(sc, a, metrics, forward)
    if out_dir is not None:
        write_run(sc, run, metrics, out_dir, stem, plots)
    return metrics


def write_run(sc, run: GroundRun, metrics: dict, out_dir: Path, stem: str, plots: bool) -> None:
    """The run folder: ``metrics.json``, ``<stem>.npz`` (the log), ``scenario.toml`` and, with
    ``plots``, ``<stem>.png`` (the path with the robot's outline every 2 s, and the velocities;
    with motion commands also the desired motion, the acceleration and the CPG's inputs)."""
    a = run.arrays()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    np.savez_compressed(out_dir / f"{stem}.npz", **a)
    (out_dir / "scenario.toml").write_text(dump_toml(sc))
    if not plots:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    control = "control_t" in a
    fig, axes = plt.subplots(2 if control else 1, 2, figsize=(11, 9.0 if control else 4.5), squeeze=False)
    ax0, ax1 = axes[0]
    ax0.plot(a["com_plane"][:, 0], a["com_plane"][:, 1], lw=1.0, label="centre of mass")
    step = max(1, int(round(2.0 * sc.log_rate_hz)))
    for shape in a["outline_plane"][::step]:
        ax0.plot(shape[:, 0], shape[:, 1], "-", color="gray", lw=0.8, alpha=0.6)
        ax0.plot(shape[0, 0], shape[0, 1], "o", color="tab:red", ms=2)
    ax0.set(xlabel="uphill x [m]", ylabel="y [m]", title=f"{sc.name}: path (outline every 2 s)")
    ax0.set_aspect("equal", adjustable="datalim")
    ax0.grid(alpha=0.3)
    ax1.plot(a["period_t"], a["v_x"], color="C0", label="v_x [m/s]")
    ax1.plot(a["period_t"], a["v_y"], color="C1", label="v_y [m/s]")
    ax1.plot(a["period_t"], a["omega"], color="C2", label="omega [rad/s]")
    ax1.set(xlabel="t [s]", title="velocities in {B}, averaged over a CPG period")
    if control:
        _plot_control(a, sc, ax1, *axes[1])
    ax1.grid(alpha=0.3)
    ax1.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / f"{stem}.png", dpi=110)
    plt.close(fig)


def _plot_control(a: dict, sc, ax_velocity, ax_acceleration, ax_inputs) -> None:
    """The motion commands' panels (as the thesis's Figs. 4-15, 4-16, 4-18): the desired velocities
    beside the measured ones, the desired and the measured acceleration (the period velocity's
    change over a period), and the CPG's inputs."""
    t = a["control_t"]
    ax_velocity.step(t, a["control_v_x_d"], where="post", color="C0", ls="--", lw=1.0, label="v_x desired")
    ax_velocity.step(t, a["control_omega_d"], where="post", color="C2", ls="--", lw=1.0, label="omega desired")
    ax_acceleration.plot(*period_acceleration(a, 1.0 / sc.cpg.frequency_hz, sc.log_rate_hz), color="C0",
                         label="measured")
    if "control_v_dot_d" in a:
        ax_acceleration.step(t, a["control_v_dot_d"], where="post", color="C0", ls="--", lw=1.0, label="desired")
    ax_acceleration.set(xlabel="t [s]", ylabel="[m/s^2]", title="forward acceleration")
    ax_acceleration.grid(alpha=0.3)
    ax_acceleration.legend(fontsize=8)
    ax_inputs.step(t, np.degrees(a["control_A"]), where="post", label="A [deg]")
    ax_inputs.step(t, np.degrees(a["control_B"]), where="post", label="B [deg]")
    ax_inputs.set(xlabel="t [s]", title="the CPG's inputs, once per period")
    ax_inputs.grid(alpha=0.3)
    ax_inputs.legend(fontsize=8)

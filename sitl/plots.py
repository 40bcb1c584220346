"""PNG plots of a run (matplotlib, Agg backend; no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from companion.estimation.so3 import quat_to_rotmat  # noqa: E402
from companion.trajectory import in_truth_frame, planned_positions  # noqa: E402

from .metrics import NEES_BLOCKS, nees_series  # noqa: E402

__all__ = ["plot_constraint_error", "plot_tracking", "plot_thrust", "plot_cable_tension", "plot_body_motion",
           "plot_attitude_tracking", "plot_nees", "write_plots"]


def _save(fig, title: str, path: Path) -> None:
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_constraint_error(log: dict[str, np.ndarray], path: Path) -> None:
    """Tip position and velocity error per joint, before and after SCKF (thesis Figs. 3-6, 3-7)."""
    if "con_pos_before" not in log:
        return
    t = log["t_sckf"]
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for ax, key, unit in ((axes[0], "pos", "m"), (axes[1], "vel", "m/s")):
        before = log[f"con_{key}_before"]
        for j in range(before.shape[1]):
            ax.plot(t, before[:, j], lw=0.8, alpha=0.6, label=f"joint {j + 1}-{j + 2} before")
        if f"con_{key}_after" in log:
            after = log[f"con_{key}_after"]
            for j in range(after.shape[1]):
                ax.plot(t, after[:, j], lw=1.4, label=f"joint {j + 1}-{j + 2} after SCKF")
        ax.set_yscale("log")
        ax.set_ylabel(f"tip {key} error [{unit}]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7, ncol=2)
    axes[1].set_xlabel("time [s]")
    _save(fig, "Constraint error between neighbouring link tips (eq. 3)", path)


def plot_tracking(log: dict[str, np.ndarray], path: Path) -> None:
    """Per link and axis: target, estimate used by control, and truth, all in the truth's frame
    (the target and the estimate less the home offset the companion flew from: the estimate
    tracks the target in the links' frame, shifted together)."""
    t = log["t"]
    n = log["p_true"].shape[1]
    target, estimate = planned_positions(log), in_truth_frame(log, log["p_ctrl"])
    fig, axes = plt.subplots(n, 3, figsize=(12, 2.2 * n + 1), sharex=True, squeeze=False)
    for i in range(n):
        for a, name in enumerate("xyz"):
            ax = axes[i, a]
            ax.plot(t, target[:, i, a], "k--", lw=1.0, label="target")
            ax.plot(t, estimate[:, i, a], lw=1.0, label="estimate")
            ax.plot(t, log["p_true"][:, i, a], lw=1.0, alpha=0.8, label="true")
            ax.set_ylabel(f"link {i + 1} {name} [m]")
            ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    for a in range(3):
        axes[-1, a].set_xlabel("time [s]")
    _save(fig, "Position tracking per link (truth's frame: target and estimate less the home offset)", path)


def plot_thrust(log: dict[str, np.ndarray], path: Path) -> None:
    """Rotor thrusts of every link (zero crossings show the ESC singularity)."""
    t = log["t"]
    thrust = log["thrust"]
    n = thrust.shape[1]
    fig, axes = plt.subplots(n, 1, figsize=(10, 2.0 * n + 1), sharex=True, squeeze=False)
    for i in range(n):
        ax = axes[i, 0]
        for k in range(thrust.shape[2]):
            ax.plot(t, thrust[:, i, k], lw=0.8, label=f"rotor {k + 1}")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_ylabel(f"link {i + 1} [N]")
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=6, ncol=4)
    axes[-1, 0].set_xlabel("time [s]")
    _save(fig, "Rotor thrust", path)


def _moving_mean(t: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """Centred moving mean over ``window_s`` (one undulation period) along the first axis."""
    k = max(1, int(round(window_s / max(np.median(np.diff(t)), 1e-9))))
    kernel = np.ones(k) / k
    return np.stack([np.convolve(x[:, j], kernel, mode="same") for j in range(x.shape[1])], axis=1)


def plot_body_motion(log: dict[str, np.ndarray], motion, path: Path, period_s: float) -> None:
    """Commanded vs expected (targets' centroid) vs achieved (true centroid) forward speed and
    direction of travel, averaged over one undulation period (thesis Figs. 5-4 to 5-6, bottom)."""
    t = log["t"]
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    cmd_t, cmd_v, cmd_yaw = [], [], []
    for c in motion.commands:
        cmd_t.append(motion.start_s + c.at_s)
        cmd_v.append(c.speed_m_s)
        cmd_yaw.append(np.nan if c.yaw_deg is None else c.yaw_deg)
    cmd_t.append(t[-1])
    for name, positions, style in (("expected (targets)", planned_positions(log), "--"),
                                   ("achieved (true)", log["p_true"], "-")):
        c = positions.mean(axis=1)
        v = _moving_mean(t, np.gradient(c, t, axis=0), period_s)
        axes[0].plot(t, np.linalg.norm(v[:, :2], axis=1), style, lw=1.2, label=name)
        axes[1].plot(t, np.degrees(np.unwrap(np.arctan2(-v[:, 1], -v[:, 0]))), style, lw=1.2, label=name)
        axes[2].plot(t, c[:, 2], style, lw=1.2, label=name)
    axes[0].step(cmd_t, cmd_v + cmd_v[-1:], where="post", color="k", lw=1.0, label="commanded")
    axes[1].step(cmd_t, cmd_yaw + cmd_yaw[-1:], where="post", color="k", lw=1.0, label="commanded heading")
    axes[0].set_ylabel("forward speed [m/s]")
    axes[1].set_ylabel("direction of travel [deg]")
    axes[2].set_ylabel("centroid altitude [m]")
    axes[2].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.axvline(motion.start_s, color="grey", lw=0.8)
        ax.legend(fontsize=7)
    _save(fig, f"CPG body motion (period-averaged, {period_s:g} s)", path)


def plot_attitude_tracking(log: dict[str, np.ndarray], path: Path) -> None:
    """Per link: target vs true yaw and pitch (thesis Figs. 5-4 to 5-6, top)."""
    t = log["t"]
    n = log["q_true"].shape[1]
    fig, axes = plt.subplots(n, 2, figsize=(12, 1.8 * n + 1), sharex=True, squeeze=False)
    for key, style, label in (("q_target", "k--", "target"), ("q_true", "-", "true")):
        R = quat_to_rotmat(log[key])
        yaw = np.degrees(np.unwrap(np.arctan2(R[..., 1, 0], R[..., 0, 0]), axis=0))
        pitch = np.degrees(np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0)))
        for i in range(n):
            axes[i, 0].plot(t, yaw[:, i], style, lw=0.9, label=label)
            axes[i, 1].plot(t, pitch[:, i], style, lw=0.9, label=label)
    for i in range(n):
        axes[i, 0].set_ylabel(f"link {i + 1} yaw [deg]")
        axes[i, 1].set_ylabel("pitch [deg]")
        for ax in axes[i]:
            ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel("time [s]")
    _save(fig, "Attitude tracking per link", path)


def plot_cable_tension(log: dict[str, np.ndarray], path: Path) -> None:
    """Cable tension per joint over the flight (the simulator's truth; the model's prediction when the
    targets carry the whole-chain feed-forward). Below zero a cable would have to push."""
    if "tension_true" not in log or log["tension_true"].shape[1] == 0:
        return
    t = log["t"]
    fig, ax = plt.subplots(figsize=(10, 4))
    for j in range(log["tension_true"].shape[1]):
        line, = ax.plot(t, log["tension_true"][:, j], lw=0.9, label=f"joint {j + 1}-{j + 2}")
        if "tension_model" in log:
            ax.plot(t, log["tension_model"][:, j], "--", lw=0.9, color=line.get_color(), alpha=0.8,
                    label=f"joint {j + 1}-{j + 2} model")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("cable tension [N]")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    _save(fig, "Cable tension at every joint (positive: the cable pulls)", path)


def plot_nees(log: dict[str, np.ndarray], path: Path) -> None:
    """NEES over time per 3-dof block: each link's EKF estimate and corrected estimate (1 s moving
    mean), with the expected value 3 and the 95 % band of a single chi2(3) sample."""
    ekf, corr = nees_series(log, "ekf"), nees_series(log, "corr")
    if ekf is None or corr is None:
        return
    t = log["t_sckf"]
    window = max(int(round(1.0 / max(np.median(np.diff(t)), 1e-3))), 1) if t.size > 1 else 1
    kernel = np.ones(window) / window

    def smooth(x):
        return np.convolve(x, kernel, mode="same")  # NaN (a link out) leaves a gap

    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for j, (ax, block) in enumerate(zip(axes, NEES_BLOCKS)):
        for i in range(ekf.shape[1]):
            ax.plot(t, smooth(ekf[:, i, j]), lw=0.8, alpha=0.7, label=f"link {i + 1} EKF")
            ax.plot(t, smooth(corr[:, i, j]), lw=1.2, ls="--", label=f"link {i + 1} corrected")
        ax.axhline(3.0, color="k", lw=1.0)
        ax.axhspan(0.216, 9.348, color="0.85", alpha=0.5, zorder=0)
        ax.set_yscale("log")
        ax.set_ylabel(f"NEES {block}")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=6, ncol=4)
    axes[-1].set_xlabel("time [s]")
    _save(fig, "NEES per 3-dof block (1 s mean; 3 expected, band: 95 % of one chi2(3) sample)", path)


def write_plots(log: dict[str, np.ndarray], out_dir: Path, motion=None, period_s: float = 4.0) -> list[Path]:
    """The run's PNGs; with ``motion`` (a CPG run) also the body motion and attitude tracking."""
    paths = [out_dir / "constraint_error.png", out_dir / "tracking.png", out_dir / "thrust.png",
             out_dir / "cable_tension.png", out_dir / "nees.png"]
    plot_constraint_error(log, paths[0])
    plot_tracking(log, paths[1])
    plot_thrust(log, paths[2])
    plot_cable_tension(log, paths[3])
    plot_nees(log, paths[4])
    if motion is not None:
        paths += [out_dir / "body_motion.png", out_dir / "attitude_tracking.png"]
        plot_body_motion(log, motion, paths[-2], period_s)
        plot_attitude_tracking(log, paths[-1])
    return [p for p in paths if p.exists()]

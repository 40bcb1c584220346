"""PNG plots of a run (matplotlib, Agg backend; no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["plot_constraint_error", "plot_tracking", "plot_thrust", "write_plots"]


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
    """Per link and axis: target, estimate used by control, and truth."""
    t = log["t"]
    n = log["p_true"].shape[1]
    fig, axes = plt.subplots(n, 3, figsize=(12, 2.2 * n + 1), sharex=True, squeeze=False)
    for i in range(n):
        for a, name in enumerate("xyz"):
            ax = axes[i, a]
            ax.plot(t, log["p_target"][:, i, a], "k--", lw=1.0, label="target")
            ax.plot(t, log["p_ctrl"][:, i, a], lw=1.0, label="estimate")
            ax.plot(t, log["p_true"][:, i, a], lw=1.0, alpha=0.8, label="true")
            ax.set_ylabel(f"link {i + 1} {name} [m]")
            ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    for a in range(3):
        axes[-1, a].set_xlabel("time [s]")
    _save(fig, "Position tracking per link", path)


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


def write_plots(log: dict[str, np.ndarray], out_dir: Path) -> list[Path]:
    paths = [out_dir / "constraint_error.png", out_dir / "tracking.png", out_dir / "thrust.png"]
    plot_constraint_error(log, paths[0])
    plot_tracking(log, paths[1])
    plot_thrust(log, paths[2])
    return [p for p in paths if p.exists()]

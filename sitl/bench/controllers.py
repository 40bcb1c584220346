"""One link's pose controllers compared on one scenario (``python -m sitl.bench controllers``).

The scenario (by default ``configs/sitl/odar/single_odar_figure8.toml``: one ODAR on a figure
eight at 45 deg pitch) is flown once per controller (``[firmware] controller``: ``impedance``,
eq. 1; ``se3_pid``, thesis sec. 2.3.2), everything else equal (the seed too). Each flight's
tracking of link 1 is measured from the end of the figure eight's amplitude ramp (or from the
take-off's end for another trajectory): RMS position error against the truth and against the
estimate the controller uses, RMS attitude error, the largest position error.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.estimation.so3 import attitude_error
from companion.trajectory import planned_positions

__all__ = ["CONTROLLERS", "tracking_metrics", "compare_controllers", "format_controllers", "markdown_controllers",
           "plot_controllers"]

log = logging.getLogger(__name__)

#: the controllers compared by default (``[firmware] controller``)
CONTROLLERS = ("impedance", "se3_pid")


def tracking_metrics(arrays: dict[str, np.ndarray], start_s: float) -> dict:
    """RMS tracking of link 1 from ``start_s``: position [m] against the truth and the control
    estimate, attitude [deg] against the truth; max position error [m]."""
    w = arrays["t"] >= start_s
    tgt_p, tgt_q = arrays["p_target"][w, 0], arrays["q_target"][w, 0]
    pos_true = np.linalg.norm(arrays["p_true"][w, 0] - planned_positions(arrays)[w, 0], axis=-1)
    pos_est = np.linalg.norm(arrays["p_ctrl"][w, 0] - tgt_p, axis=-1)
    att = np.degrees(np.linalg.norm(attitude_error(arrays["q_true"][w, 0], tgt_q), axis=-1))
    rms = lambda x: float(np.sqrt(np.mean(x * x)))  # noqa: E731
    return {"rms_pos_true_m": rms(pos_true), "rms_pos_est_m": rms(pos_est), "rms_att_true_deg": rms(att),
            "max_pos_true_m": float(pos_true.max()), "window_s": [float(start_s), float(arrays["t"][-1])]}


def compare_controllers(scenario, out_dir: Path | None, controllers=CONTROLLERS, progress=None) -> dict:
    """Fly ``scenario`` once per controller; their tracking metrics (and ``<controller>/log.npz``
    and ``compare_tracking.png`` in ``out_dir``)."""
    from sitl.runner import BatchRunner  # MuJoCo: when a comparison runs

    tr = scenario.trajectory
    start = tr.figure8_start_s + tr.figure8_period_s if tr.kind == "figure8" else scenario.flight_start_s
    out: dict = {"scenario": scenario.name, "seed": scenario.seed, "duration_s": scenario.duration_s,
                 "controllers": {}}
    for name in controllers:
        sc = replace(scenario, firmware=replace(scenario.firmware, controller=name))
        runner = BatchRunner(sc)
        runner.run(sc.duration_s, progress=progress)
        arrays = runner.arrays()
        m = tracking_metrics(arrays, start)
        m.update(took_off=runner.plant.took_off, crashed=runner.crashed, crash_reason=runner.crash_reason,
                 realtime_factor=runner.sim_s / runner.wall_s if runner.wall_s > 0 else None)
        out["controllers"][name] = m
        log.info("%s: %s", name, m)
        if out_dir is not None:
            (out_dir / name).mkdir(parents=True, exist_ok=True)
            np.savez_compressed(out_dir / name / "log.npz", **arrays)
    if out_dir is not None:
        plot_controllers(out_dir, controllers, start, out_dir / "compare_tracking.png")
    return out


def plot_controllers(run_dir: Path, controllers, start_s: float, path: Path) -> None:
    """The path flown in the horizontal plane and the position error over time, per controller
    (from each controller's ``log.npz`` in ``run_dir``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_xy, ax_e) = plt.subplots(1, 2, figsize=(11, 4.5))
    for name in controllers:
        a = np.load(run_dir / name / "log.npz")
        w = a["t"] >= start_s
        ax_xy.plot(a["p_true"][w, 0, 0], a["p_true"][w, 0, 1], label=f"{name} (true)", lw=0.8)
        ax_e.plot(a["t"][w], 100 * np.linalg.norm(a["p_true"][w, 0] - planned_positions(a)[w, 0], axis=-1), label=name,
                  lw=0.8)
    target = planned_positions(a)[w, 0]  # (in the truth's frame)
    ax_xy.plot(target[:, 0], target[:, 1], "k--", lw=0.8, label="target")
    ax_xy.set(xlabel="x [m]", ylabel="y [m]", aspect="equal", title="link 1's path (horizontal plane)")
    ax_e.set(xlabel="t [s]", ylabel="|p - p_d| [cm] (true)")
    for ax in (ax_xy, ax_e):
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


_COLUMNS = (("rms_pos_true_m", "RMS position, truth [cm]", 100.0), ("rms_pos_est_m", "RMS position, estimate [cm]", 100.0),
            ("rms_att_true_deg", "RMS attitude [deg]", 1.0), ("max_pos_true_m", "max position [cm]", 100.0))


#: the last columns: whether the flight crashed, and its real-time factor (what a controller costs per tick,
#: compared within one run)
_TAIL = ("crashed", "real-time factor")


def _rows(result: dict) -> list[tuple]:
    return [(name, *(f"{scale * m[key]:.2f}" for key, _, scale in _COLUMNS), "yes" if m["crashed"] else "no",
             "-" if m.get("realtime_factor") is None else f"{m['realtime_factor']:.1f}")
            for name, m in result["controllers"].items()]


def format_controllers(result: dict) -> str:
    """The comparison as console text."""
    head = ("controller", *(label for _, label, _ in _COLUMNS), *_TAIL)
    rows = [head, *_rows(result)]
    widths = [max(len(str(r[i])) for r in rows) for i in range(len(head))]
    window = next(iter(result["controllers"].values()))["window_s"]
    lines = [f"{result['scenario']} (seed {result['seed']}), tracking of link 1 from {window[0]:g} s to {window[1]:g} s"]
    lines += ["  ".join(str(c).rjust(w) for c, w in zip(r, widths)) for r in rows]
    return "\n".join(lines)


def markdown_controllers(result: dict) -> str:
    """The Markdown table of a :func:`compare_controllers` result (``controllers.json``)."""
    from .report import md_table

    window = next(iter(result["controllers"].values()))["window_s"]
    intro = (f"Scenario `{result['scenario']}` (seed {result['seed']}, {result['duration_s']:g} s), flown once per "
             f"controller; tracking of link 1 from {window[0]:g} s to {window[1]:g} s.")
    return "\n".join([intro, "", md_table(("controller", *(label for _, label, _ in _COLUMNS), *_TAIL),
                                          _rows(result))])

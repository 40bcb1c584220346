"""Benchmark of the slung load's pose filters on the synthetic scenario (``sitl/scenarios/slung_load/synthetic.py``).

    python -m sitl.bench load_filter [--seeds N] [--seed S] [--duration S] [--latency S] [--out DIR]

Per seed: EKF, UKF, the unfiltered per-image solve and the report's open-loop trajectory, with
the images delivered late (capture + latency + jitter) and the filters' real-time output scored
at every vehicle sample; ``load_pose_err`` as in ``metrics.json``, mean pose NEES, filter counters
and the time per image. Writes ``load_filter.json`` and, for the first seed, ``load_pose_error.png``
(the report's Figs. 4 and 9: error magnitude with the filters' 3-sigma bound) into the run folder.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from companion.load.estimate import LoadFilterConfig
from companion.load.metrics import pose_error_series
from sitl.scenarios.slung_load.synthetic import SlungLoadSim, run_estimators, simulate_truth, summarize, synthesize

ESTIMATORS = ("ekf", "ukf", "unfiltered", "open_loop")


def run_load_filter_bench(seeds, sim: SlungLoadSim, cfg: LoadFilterConfig, progress=None):
    """Truth once (it has no random draw), then per seed: measurements, estimators, summary.
    Returns ``(result dict, run of the first seed)``."""
    t0 = time.perf_counter()
    truth = simulate_truth(sim)
    truth_s = time.perf_counter() - t0
    per_seed, first = [], None
    for seed in seeds:
        meas = synthesize(truth, sim, seed)
        t0 = time.perf_counter()
        run = run_estimators(truth, meas, sim, cfg, seed)
        wall = time.perf_counter() - t0
        s = summarize(run)
        s["seed"] = seed
        s["estimators_wall_s"] = wall
        s["images"] = len(meas.images)
        s["frames"] = meas.frames
        per_seed.append(s)
        first = first or run
        if progress:
            progress(1)
    agg = {}
    for name in ESTIMATORS:
        rows = [s["load_pose_err"][name] for s in per_seed if name in s["load_pose_err"]]
        agg[name] = {k: float(np.mean([r[k] for r in rows])) for k in ("pos_rms_m", "att_rms_deg")}
        agg[name].update({k.replace("rms", "rms_std"): float(np.std([r[k] for r in rows]))
                          for k in ("pos_rms_m", "att_rms_deg")})
    result = {
        "scenario": dataclasses.asdict(sim),
        "filter": dataclasses.asdict(cfg),
        "load_pose_err": agg,
        "pose_nees_mean": {k: float(np.mean([s["pose_nees_mean"][k] for s in per_seed])) for k in ("ekf", "ukf")},
        "truth_sim_s": truth_s,
        "per_seed": per_seed,
    }
    return result, first


def format_load_filter(result: dict) -> str:
    sim = result["scenario"]
    lines = [f"slung load, synthetic: {sim['duration_s']:g} s, circle {sim['circle_radius_m']:g} m at "
             f"{sim['speed_m_s']:g} m/s, 3 cameras at {sim['camera_rate_hz']:g} Hz, latency "
             f"{sim['latency_s'] * 1e3:.0f}-{(sim['latency_s'] + sim['latency_jitter_s']) * 1e3:.0f} ms, "
             f"{len(result['per_seed'])} seed(s); RMS after 1 s (mean +- std over seeds)",
             f"{'estimator':<12} {'pos RMS [cm]':>16} {'att RMS [deg]':>16}"]
    for name, r in result["load_pose_err"].items():
        lines.append(f"{name:<12} {100 * r['pos_rms_m']:>9.2f} +- {100 * r['pos_rms_std_m']:<4.2f} "
                     f"{r['att_rms_deg']:>9.2f} +- {r['att_rms_std_deg']:<4.2f}")
    nees = result["pose_nees_mean"]
    lines.append(f"mean pose NEES (6 dof, 6 if consistent): EKF {nees['ekf']:.2f}, UKF {nees['ukf']:.2f}")
    per = result["per_seed"][0]
    lines.append(f"seed {per['seed']}: {per['images']} images of {per['frames']} frames, estimators "
                 f"{per['estimators_wall_s']:.1f} s wall for all four (EKF+UKF with late-image replays)")
    return "\n".join(lines)


def plot_load_errors(run, path) -> None:
    """Error magnitude over time per estimator, the filters' 3-sigma bound dashed (Figs. 4, 9)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for name in ("ekf", "ukf", "open_loop"):
        pe, ae = pose_error_series(run.pos_w_m[name], run.q_wxyz[name], run.pos_gt_w_m, run.q_gt_wxyz)
        line, = axes[0].plot(run.t_s, 100 * pe, label=name, lw=1)
        axes[1].plot(run.t_s, ae, lw=1, color=line.get_color())
        if name != "open_loop":
            P = run.P_pose[name]
            axes[0].plot(run.t_s, 300 * np.sqrt(np.trace(P[:, :3, :3], axis1=1, axis2=2)), "--", lw=0.7,
                         color=line.get_color())
            axes[1].plot(run.t_s, 3 * np.degrees(np.sqrt(np.trace(P[:, 3:, 3:], axis1=1, axis2=2))), "--", lw=0.7,
                         color=line.get_color())
    if run.unfiltered is not None:
        t, p, q, p_gt, q_gt = run.unfiltered
        pe, ae = pose_error_series(p, q, p_gt, q_gt)
        axes[0].plot(t, 100 * pe, ".", ms=2, label="unfiltered", color="grey")
        axes[1].plot(t, ae, ".", ms=2, color="grey")
    axes[0].set_ylabel("position error [cm]")
    axes[1].set_ylabel("attitude error [deg]")
    axes[1].set_xlabel("time [s]")
    axes[0].set_ylim(0, 30)
    axes[1].set_ylim(0, 20)
    axes[0].legend(loc="upper right", ncol=4)
    axes[0].set_title("load pose error (dashed: 3-sigma of the filter)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown_load_filter(result: dict) -> str:
    """The Markdown tables of a :func:`run_load_filter_bench` result (``load_filter.json``):
    :func:`format_load_filter`'s figures, every seed's counters beside them."""
    from .report import md_table

    sim = result["scenario"]
    intro = (f"Synthetic slung load: {sim['duration_s']:g} s, circle {sim['circle_radius_m']:g} m at "
             f"{sim['speed_m_s']:g} m/s, 3 cameras at {sim['camera_rate_hz']:g} Hz, image latency "
             f"{sim['latency_s'] * 1e3:.0f}-{(sim['latency_s'] + sim['latency_jitter_s']) * 1e3:.0f} ms, "
             f"{len(result['per_seed'])} seed(s); RMS error after the first second, mean ± std over the seeds.")
    rows = [(name, f"{100 * r['pos_rms_m']:.2f} ± {100 * r['pos_rms_std_m']:.2f}",
             f"{r['att_rms_deg']:.2f} ± {r['att_rms_std_deg']:.2f}") for name, r in result["load_pose_err"].items()]
    nees = result["pose_nees_mean"]
    seeds = [(s["seed"], s["images"], s["frames"], f"{s['estimators_wall_s']:.1f}") for s in result["per_seed"]]
    return "\n".join([
        intro, "", md_table(("estimator", "position RMS [cm]", "attitude RMS [deg]"), rows), "",
        f"Mean pose NEES (6 dof, 6 if consistent): EKF {nees['ekf']:.2f}, UKF {nees['ukf']:.2f}.", "",
        "## Per seed", "",
        md_table(("seed", "images", "frames", "estimators' wall time [s] (all four)"), seeds),
    ])

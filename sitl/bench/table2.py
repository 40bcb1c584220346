"""The paper's Table II protocol (sec. IV): accuracy and compute time vs. group size.

12 links of 1 m, 20 s, Table I noise, slow drifts (0.5 m position, 5 deg attitude), per-link
EKF at 100 Hz, then the semi-distributed constraint application at 20 Hz (400 steps) with
group sizes 2, 3, 4, 6, 12 (12 = one group = the full SCKF of Alg. 1). All group sizes see
the same EKF stream (the SCKF never feeds back into the EKF, paper sec. III-A).

Reported per group size: estimator compute time (wall time inside the local constraint
applications and the global step only, summed over the 400 steps), mean position error and
mean quaternion error (2-norm of the error vs. truth, averaged over links and steps; the
quaternion error is sign-aligned), plus the same errors for the EKF alone.

Consistency (:func:`nees_summary`): the NEES of every link per 3-dof block (position,
velocity, attitude; ``e^T P_bb^-1 e`` with ``e`` the truth minus the estimate, the attitude error
world-frame as the EKF's error state), averaged over the steps and links, for the EKF alone and
for the corrected estimate of every group size (its covariance: the local constraint
application's per-link blocks, which the global step leaves as they are, paper eq. 6, although
it moves the estimate: with several groups the corrected NEES is low by construction). A
consistent filter averages 3. Its 95 % bounds are those of the average of ``K_eff`` independent
3-dof NEES values (``K_eff mean ~ chi2(3 K_eff)``): ``K_eff`` sums, over links and seeds, the
steps divided by the NEES' integrated correlation time, estimated from the whitened errors' own
autocorrelation (``1 + 2 sum_j rho(j)^2``, :func:`sitl.metrics.correlation_time`). Over seeds
this is the Monte Carlo NEES test (Bar-Shalom, Li & Kirubarajan, sec. 5.4.2). The links count
as independent: true of the EKFs (each link has its own sensors), not of the corrected
estimates (the constraints couple neighbours), whose bounds are therefore too narrow.

Two EKF tunings run on the same seeded sensor data (:data:`ekf_chain.EKF_CONFIGS`): ``paper``
(Table I, drifts unmodelled) and ``consistent`` (:func:`ekf_chain.consistent_ekf_config`).
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from companion.estimation.chain import ERR_P, ERR_TH, ERR_V
from companion.estimation.constraints import constraint_residual
from companion.estimation.sckf import CAParams
from companion.estimation.semi import make_groups, semi_distributed_apply
from companion.estimation.so3 import quat_distance
from sitl.metrics import NEES_BLOCKS, correlation_time, nees_bounds95, nees_whitened

from .ekf_chain import EKF_CONFIGS, ChainRun, EkfStream, ekf_config, simulate_ekf_chain

__all__ = [
    "PAPER_TABLE2",
    "GROUP_SIZES",
    "nees_summary",
    "evaluate_group_size",
    "run_table2",
    "run_table2_configs",
    "table2_seed",
    "aggregate_seeds",
    "combine_configs",
    "format_table2",
    "format_nees_table",
    "format_table2_configs",
    "markdown_table2",
]

#: The paper's Table II: group size -> (computing time s, position error m, quaternion error).
PAPER_TABLE2 = {
    2: (13.753, 0.0377, 0.0026),
    3: (15.496, 0.0370, 0.0025),
    4: (16.356, 0.0369, 0.0025),
    6: (20.900, 0.0360, 0.0023),
    12: (29.041, 0.0322, 0.0023),
}
GROUP_SIZES = (2, 3, 4, 6, 12)

EKF_CONFIG_TITLES = {
    "paper": "paper (Table I: white measurement noise only, the drifts unmodelled)",
    "consistent": "consistent (the drifts carried in the measurement and process noise: consistent_ekf_config)",
}


def _errors(stream: EkfStream, p: np.ndarray, q: np.ndarray) -> tuple[float, float]:
    pos = float(np.mean(np.linalg.norm(p - stream.p_true, axis=-1)))
    quat = float(np.mean(quat_distance(q, stream.q_true)))
    return pos, quat


def nees_summary(stream: EkfStream, p: np.ndarray, v: np.ndarray, q: np.ndarray, P: np.ndarray) -> dict:
    """NEES per 3-dof block of the estimate ``(p, v, q)`` with per-link covariances ``P`` (K, n, 9, 9).

    ``nees``: the average over steps and links; ``nees_effective_samples``: how many independent
    3-dof NEES values that average is worth (the steps over the correlation time, summed over the
    links); ``nees_bounds95``: the two-sided 95 % bounds of such an average for a consistent
    filter (see the module docstring).
    """
    cov = np.stack([P[..., b, b] for b in (ERR_P, ERR_V, ERR_TH)], axis=2)  # (K, n, 3, 3, 3)
    w = nees_whitened(stream.p_true, stream.v_true, stream.q_true, p, v, q, cov)  # (K, n, 3, 3)
    nees = np.sum(w * w, axis=-1)  # (K, n, 3)
    k_eff = np.sum(nees.shape[0] / correlation_time(w), axis=0)  # (3,)
    bounds = nees_bounds95(k_eff)
    return {
        "nees": {b: float(nees[..., j].mean()) for j, b in enumerate(NEES_BLOCKS)},
        "nees_effective_samples": {b: float(k_eff[j]) for j, b in enumerate(NEES_BLOCKS)},
        "nees_bounds95": {b: bounds[j].tolist() for j, b in enumerate(NEES_BLOCKS)},
    }


def evaluate_group_size(stream: EkfStream, size: int, params: CAParams = CAParams()) -> dict:
    """Run Alg. 2 + eq. 6 on every tick of ``stream`` with groups of ``size`` links."""
    K, n = stream.p.shape[:2]
    groups = make_groups(n, size)
    p_out = np.empty_like(stream.p)
    v_out = np.empty_like(stream.v)
    q_out = np.empty_like(stream.q)
    P_out = np.empty_like(stream.P)
    iterations = np.empty((K, len(groups)), dtype=int)
    residual_after = np.empty(K)
    elapsed = 0.0
    for k in range(K):
        args = (stream.p[k], stream.v[k], stream.q[k], stream.w[k], stream.d, stream.P[k])
        t0 = time.perf_counter()
        res = semi_distributed_apply(*args, groups, params)
        elapsed += time.perf_counter() - t0
        p_out[k], v_out[k], q_out[k], P_out[k] = res.p, res.v, res.q, res.P
        iterations[k] = res.iterations
        residual_after[k] = np.linalg.norm(constraint_residual(res.p, res.v, res.q, stream.w[k], stream.d))
    pos_err, quat_err = _errors(stream, p_out, q_out)
    return {
        "time_s": elapsed,
        "pos_err_m": pos_err,
        "quat_err": quat_err,
        "groups": len(groups),
        "mean_iterations_per_group": float(iterations.mean()),
        "max_iterations": int(iterations.max()),
        "residual_after_mean": float(residual_after.mean()),
        "residual_after_max": float(residual_after.max()),
        **nees_summary(stream, p_out, v_out, q_out, P_out),
    }


def run_table2(
    seed: int = 0,
    run: ChainRun = ChainRun(),
    group_sizes=GROUP_SIZES,
    params: CAParams = CAParams(),
    progress=None,
) -> tuple[dict, EkfStream]:
    """Simulate the EKF stream once (with ``run.ekf``), then evaluate every group size on it."""
    stream = simulate_ekf_chain(run, seed, progress)
    n = run.motion.n_links
    residual_before = np.array(
        [np.linalg.norm(constraint_residual(stream.p[k], stream.v[k], stream.q[k], stream.w[k], stream.d))
         for k in range(stream.t.size)]
    )
    ekf_pos, ekf_quat = _errors(stream, stream.p, stream.q)
    result = {
        "ekf_only": {"pos_err_m": ekf_pos, "quat_err": ekf_quat, "residual_mean": float(residual_before.mean()),
                     **nees_summary(stream, stream.p, stream.v, stream.q, stream.P)},
        "groups": {},
        "protocol": {
            "seed": seed,
            "n_links": n,
            "link_length_m": run.motion.link_length_m,
            "duration_s": run.duration_s,
            "ekf_rate_hz": run.ekf_rate_hz,
            "gps_rate_hz": run.gps_rate_hz,
            "attitude_rate_hz": run.att_rate_hz,
            "sckf_rate_hz": run.sckf_rate_hz,
            "sckf_steps": int(stream.t.size),
            "alpha": params.alpha,
            "eps": params.eps,
            "max_iter": params.max_iter,
            "ekf": asdict(run.ekf),
        },
        "paper": {str(g): dict(zip(("time_s", "pos_err_m", "quat_err"), v)) for g, v in PAPER_TABLE2.items()},
    }
    for size in group_sizes:
        if size > n:
            raise ValueError(f"group size {size} exceeds the number of links ({n})")
        result["groups"][str(size)] = evaluate_group_size(stream, size, params)
    return result, stream


def run_table2_configs(
    seed: int = 0,
    run: ChainRun = ChainRun(),
    configs=EKF_CONFIGS,
    group_sizes=GROUP_SIZES,
    params: CAParams = CAParams(),
    progress=None,
) -> dict[str, tuple[dict, EkfStream]]:
    """:func:`run_table2` once per EKF tuning in ``configs`` (names of :data:`EKF_CONFIGS`), all on
    the same seeded truth and sensor data (the tuning draws no random numbers)."""
    out = {}
    for name in configs:
        result, stream = run_table2(seed, replace(run, ekf=ekf_config(name, run)), group_sizes, params, progress)
        result["protocol"]["ekf_config"] = name
        out[name] = (result, stream)
    return out


def table2_seed(out_dir, seed: int, run: ChainRun, configs, params: CAParams, streams_to: str | None = None) -> dict:
    """One seed of the protocol as a campaign job (:mod:`sitl.campaign.engine`): the result per
    EKF tuning in ``configs``; with ``streams_to``, that folder gets the replay inputs of this
    seed (``ekf_stream[_<tuning>].npz``, ``truth.npz``) for ``python -m companion replay``."""
    runs = run_table2_configs(seed, run, configs, GROUP_SIZES, params)
    if streams_to is not None:
        folder = Path(streams_to)
        for name, (_, stream) in runs.items():
            suffix = "" if name == "paper" else f"_{name}"
            np.savez_compressed(folder / f"ekf_stream{suffix}.npz", **stream.replay_arrays())
        stream = next(iter(runs.values()))[1]
        np.savez_compressed(folder / "truth.npz", t=stream.t, p=stream.p_true, v=stream.v_true, q=stream.q_true)
    return {name: result for name, (result, _) in runs.items()}


_NEES_KEYS = ("nees", "nees_effective_samples", "nees_bounds95")


def _aggregate_nees(rows: list[dict]) -> dict:
    """Monte Carlo NEES over seeds: the mean of the per-seed averages (equal weights: every seed has
    the same steps and links), their spread, the effective samples summed and the bounds for them."""
    out: dict = {"nees": {}, "nees_std": {}, "nees_effective_samples": {}, "nees_bounds95": {}, "nees_inside95": {}}
    for b in NEES_BLOCKS:
        vals = np.array([r["nees"][b] for r in rows])
        k_eff = float(sum(r["nees_effective_samples"][b] for r in rows))
        lo, hi = nees_bounds95(k_eff).tolist()
        mean = float(vals.mean())
        out["nees"][b] = mean
        out["nees_std"][b] = float(vals.std(ddof=1)) if len(vals) > 1 else 0.0
        out["nees_effective_samples"][b] = k_eff
        out["nees_bounds95"][b] = [lo, hi]
        out["nees_inside95"][b] = bool(lo <= mean <= hi)
    return out


def aggregate_seeds(results: list[dict]) -> dict:
    """Mean over seeds in the single-run layout, with spreads and the protocol checks.

    Every number of the single-run layout becomes its mean over the seeds; ``*_std`` fields
    give the spread. ``checks`` holds the two accuracy claims of the protocol:
    ``sckf_beats_ekf`` (every group size has a lower mean position error than the EKF
    alone, in every seed) and ``larger_groups_not_worse`` (for each pair of consecutive group
    sizes, the paired per-seed difference of position error is not positive beyond two
    standard errors; needs >= 2 seeds).
    """
    first = results[0]
    out = {"ekf_only": {}, "groups": {}, "protocol": dict(first["protocol"]), "paper": first["paper"]}
    out["protocol"]["seeds"] = [r["protocol"]["seed"] for r in results]
    for key in first["ekf_only"]:
        if key in _NEES_KEYS:
            continue
        vals = np.array([r["ekf_only"][key] for r in results])
        out["ekf_only"][key] = float(vals.mean())
        out["ekf_only"][f"{key}_std"] = float(vals.std(ddof=1)) if len(vals) > 1 else 0.0
    if "nees" in first["ekf_only"]:
        out["ekf_only"].update(_aggregate_nees([r["ekf_only"] for r in results]))
    sizes = list(first["groups"])
    for size in sizes:
        row = {}
        for key in first["groups"][size]:
            if key in _NEES_KEYS:
                continue
            vals = np.array([r["groups"][size][key] for r in results], dtype=float)
            row[key] = float(vals.mean())
            if key in ("time_s", "pos_err_m", "quat_err"):
                row[f"{key}_std"] = float(vals.std(ddof=1)) if len(vals) > 1 else 0.0
        if "nees" in first["groups"][size]:
            row.update(_aggregate_nees([r["groups"][size] for r in results]))
        out["groups"][size] = row
    beats = all(r["groups"][g]["pos_err_m"] < r["ekf_only"]["pos_err_m"] for r in results for g in sizes)
    pairs = {}
    not_worse = None
    if len(results) > 1:
        not_worse = True
        for small, large in zip(sizes[:-1], sizes[1:]):
            diff = np.array([r["groups"][large]["pos_err_m"] - r["groups"][small]["pos_err_m"] for r in results])
            se = float(diff.std(ddof=1) / np.sqrt(len(diff)))
            worse = bool(diff.mean() > 2.0 * se)
            pairs[f"{small}->{large}"] = {"mean_diff_m": float(diff.mean()), "std_err_m": se, "worse": worse}
            not_worse = not_worse and not worse
    out["checks"] = {"sckf_beats_ekf": beats, "larger_groups_not_worse": not_worse, "pairs": pairs}
    out["per_seed"] = results
    return out


def format_table2(result: dict) -> str:
    proto = result["protocol"]
    seeds = proto.get("seeds", [proto["seed"]])
    spread = len(seeds) > 1

    def val(row, key, fmt):
        text = format(row[key], fmt)
        return f"{text}+-{format(row[key + '_std'], fmt)}" if spread and key + "_std" in row else text

    width = 17 if spread else 11
    lines = [
        f"Table II protocol: {proto['n_links']} links x {proto['link_length_m']:g} m, {proto['duration_s']:g} s, "
        f"EKF {proto['ekf_rate_hz']:g} Hz, SCKF {proto['sckf_rate_hz']:g} Hz ({proto['sckf_steps']} steps), "
        f"eps {proto['eps']:g}, alpha {proto['alpha']:g}, seed(s) {', '.join(str(s) for s in seeds)}"
        + (" (mean +- std over seeds)" if spread else ""),
    ]
    if "ekf_config" in proto:
        lines.append(f"EKF tuning: {EKF_CONFIG_TITLES.get(proto['ekf_config'], proto['ekf_config'])}")
    lines += [
        "",
        f"{'group size':>10} | {'CA time [s]':>{width}} | {'pos err [m]':>{width}} | {'quat err':>{width}} | "
        f"{'iters':>5} | {'|c| after':>9} || {'paper time':>10} | {'paper pos':>9} | {'paper quat':>10}",
        "-" * (88 + 3 * width),
    ]
    ekf = result["ekf_only"]
    lines.append(
        f"{'EKF only':>10} | {'-':>{width}} | {val(ekf, 'pos_err_m', '.4f'):>{width}} | "
        f"{val(ekf, 'quat_err', '.4f'):>{width}} | {'-':>5} | {ekf['residual_mean']:9.4f} || "
        f"{'-':>10} | {'-':>9} | {'-':>10}"
    )
    for size, row in result["groups"].items():
        paper = result["paper"].get(size)
        ptxt = (
            f"{paper['time_s']:10.3f} | {paper['pos_err_m']:9.4f} | {paper['quat_err']:10.4f}"
            if paper
            else f"{'-':>10} | {'-':>9} | {'-':>10}"
        )
        lines.append(
            f"{size:>10} | {val(row, 'time_s', '.4f'):>{width}} | {val(row, 'pos_err_m', '.4f'):>{width}} | "
            f"{val(row, 'quat_err', '.4f'):>{width}} | {row['mean_iterations_per_group']:5.2f} | "
            f"{row['residual_after_mean']:9.4f} || {ptxt}"
        )
    checks = result.get("checks")
    if checks:
        lines.append("")
        lines.append(f"SCKF cuts the EKF-only position error at every group size: {'yes' if checks['sckf_beats_ekf'] else 'NO'}")
        if checks["larger_groups_not_worse"] is None:
            lines.append("Larger groups not less accurate beyond noise: run with --seeds N (N >= 2) to check")
        else:
            detail = ", ".join(
                f"{k}: {v['mean_diff_m']:+.4f}+-{v['std_err_m']:.4f} m" for k, v in checks["pairs"].items()
            )
            verdict = "yes" if checks["larger_groups_not_worse"] else "NO"
            lines.append(f"Larger groups not less accurate beyond noise (paired, 2 s.e.): {verdict} ({detail})")
    return "\n".join(lines)


def combine_configs(aggregates: dict[str, dict]) -> dict:
    """One result for several EKF tunings: ``by_ekf`` maps each tuning's name to its
    :func:`aggregate_seeds` result; ``protocol`` (without the tuning) and ``paper`` are shared."""
    first = next(iter(aggregates.values()))
    protocol = {k: v for k, v in first["protocol"].items() if k not in ("ekf", "ekf_config")}
    return {"protocol": protocol, "paper": first["paper"], "ekf_configs": list(aggregates), "by_ekf": aggregates}


def _nees_cell(row: dict, block: str) -> str:
    lo, hi = row["nees_bounds95"][block]
    val = row["nees"][block]
    inside = row.get("nees_inside95", {}).get(block, lo <= val <= hi)
    return f"{val:6.2f} [{lo:.2f}-{hi:.2f}]{' ' if inside else '!'}"


def format_nees_table(combined: dict) -> str:
    """The NEES per block for the EKF alone and each group size, one column group per tuning."""
    names = combined["ekf_configs"]
    runs = [combined["by_ekf"][n] for n in names]
    cell_w = 19
    head1 = f"{'':>10} |" + " |".join(f" {n:<{3 * cell_w + 2}}" for n in names)
    head2 = f"{'':>10} |" + " |".join(" " + " ".join(f"{b:<{cell_w}}" for b in NEES_BLOCKS) for _ in names)
    lines = [
        "NEES per 3-dof block, mean over steps, links and seeds (3: consistent; above: the covariance claims less "
        "error than there is, below: more)",
        "[95 % bounds of that mean for its effective samples, links taken as independent: too narrow for the "
        "corrected rows]; !: outside.",
        "Groups < all links: the covariance is the local step's, which the global step (eq. 6) leaves as it is "
        "although it corrects the estimate.",
        "",
        head1,
        head2,
        "-" * len(head2),
    ]
    labels = [("EKF only", lambda r: r["ekf_only"])] + [
        (size, lambda r, size=size: r["groups"][size]) for size in runs[0]["groups"]
    ]
    for label, get in labels:
        cells = [" ".join(_nees_cell(get(r), b) for b in NEES_BLOCKS) for r in runs]
        lines.append(f"{label:>10} | " + " | ".join(cells))
    proto = combined["protocol"]
    steps = len(proto.get("seeds", [proto.get("seed")])) * proto["sckf_steps"] * proto["n_links"]
    lines.append("")
    for n, r in zip(names, runs):
        k = r["ekf_only"]["nees_effective_samples"]
        lines.append(f"effective samples, EKF only ({n}): " + " / ".join(f"{b} {k[b]:.0f}" for b in NEES_BLOCKS)
                     + f" of {steps} link-steps")
    return "\n".join(lines)


def format_table2_configs(combined: dict) -> str:
    """Every tuning's Table II, then the NEES side by side."""
    parts = [format_table2(combined["by_ekf"][n]) for n in combined["ekf_configs"]]
    return "\n\n".join(parts + [format_nees_table(combined)])


def _md_val(row: dict, key: str, spec: str, spread: bool) -> str:
    text = format(row[key], spec)
    return f"{text} ± {format(row[key + '_std'], spec)}" if spread and key + "_std" in row else text


def _md_nees(row: dict, block: str) -> str:
    lo, hi = row["nees_bounds95"][block]
    val = row["nees"][block]
    inside = row.get("nees_inside95", {}).get(block, lo <= val <= hi)
    return f"{val:.2f} [{lo:.2f}-{hi:.2f}]" + ("" if inside else " **out**")


def markdown_table2(combined: dict) -> str:
    """The Markdown tables of a :func:`combine_configs` result (``table2.json``): per EKF tuning, Table II
    beside the paper's and the protocol's checks, then the NEES per block (the figures of
    :func:`format_table2_configs`)."""
    from .report import md_table

    proto = combined["protocol"]
    seeds = proto.get("seeds", [proto.get("seed")])
    spread = len(seeds) > 1
    parts = [
        f"{proto['n_links']} links x {proto['link_length_m']:g} m, {proto['duration_s']:g} s, EKF "
        f"{proto['ekf_rate_hz']:g} Hz, SCKF {proto['sckf_rate_hz']:g} Hz ({proto['sckf_steps']} steps), eps "
        f"{proto['eps']:g}, alpha {proto['alpha']:g}, seed(s) {', '.join(str(s) for s in seeds)}"
        + ("; figures: mean ± std over the seeds." if spread else "."),
    ]
    for name in combined["ekf_configs"]:
        result = combined["by_ekf"][name]
        ekf = result["ekf_only"]
        rows = [("EKF only", "-", _md_val(ekf, "pos_err_m", ".4f", spread), _md_val(ekf, "quat_err", ".4f", spread),
                 "-", f"{ekf['residual_mean']:.4f}", "-", "-", "-")]
        for size, row in result["groups"].items():
            paper = result["paper"].get(size)
            rows.append((size, _md_val(row, "time_s", ".4f", spread), _md_val(row, "pos_err_m", ".4f", spread),
                         _md_val(row, "quat_err", ".4f", spread), f"{row['mean_iterations_per_group']:.2f}",
                         f"{row['residual_after_mean']:.4f}",
                         *((f"{paper['time_s']:.3f}", f"{paper['pos_err_m']:.4f}", f"{paper['quat_err']:.4f}")
                           if paper else ("-", "-", "-"))))
        parts += ["", f"## EKF tuning: {EKF_CONFIG_TITLES.get(name, name)}", "",
                  md_table(("group size", "CA time [s]", "pos err [m]", "quat err", "iterations", "|c| after",
                            "paper time [s]", "paper pos err [m]", "paper quat err"), rows)]
        checks = result.get("checks")
        if checks:
            parts += ["", f"- SCKF cuts the EKF-only position error at every group size: "
                          f"{'yes' if checks['sckf_beats_ekf'] else 'NO'}"]
            if checks["larger_groups_not_worse"] is None:
                parts.append("- Larger groups not less accurate beyond noise: not checked (one seed)")
            else:
                detail = ", ".join(f"{k}: {v['mean_diff_m']:+.4f} ± {v['std_err_m']:.4f} m"
                                   for k, v in checks["pairs"].items())
                parts.append(f"- Larger groups not less accurate beyond noise (paired, 2 s.e.): "
                             f"{'yes' if checks['larger_groups_not_worse'] else 'NO'} ({detail})")
    parts += ["", "## NEES per 3-dof block", "",
              "Mean over steps, links and seeds (3: consistent) with the 95 % bounds of that mean for its effective "
              "samples, links taken as independent (too narrow for the corrected rows); **out**: outside. Groups "
              "smaller than the chain: the covariance is the local step's, which the global step (eq. 6) leaves "
              "as it is."]
    for name in combined["ekf_configs"]:
        result = combined["by_ekf"][name]
        rows = [("EKF only", *(_md_nees(result["ekf_only"], b) for b in NEES_BLOCKS))]
        rows += [(size, *(_md_nees(row, b) for b in NEES_BLOCKS)) for size, row in result["groups"].items()]
        k = result["ekf_only"]["nees_effective_samples"]
        steps = len(seeds) * proto["sckf_steps"] * proto["n_links"]
        parts += ["", f"### EKF tuning: {name}", "", md_table(("group size", *NEES_BLOCKS), rows), "",
                  "Effective samples, EKF only: " + " / ".join(f"{b} {k[b]:.0f}" for b in NEES_BLOCKS)
                  + f" of {steps} link-steps."]
    return "\n".join(parts)

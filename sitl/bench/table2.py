"""The paper's Table II protocol (sec. IV): accuracy and compute time vs. group size.

12 links of 1 m, 20 s, Table I noise, slow drifts (0.5 m position, 5 deg attitude), per-link
EKF at 100 Hz, then the semi-distributed constraint application at 20 Hz (400 steps) with
group sizes 2, 3, 4, 6, 12 (12 = one group = the full SCKF of Alg. 1). All group sizes see
the same EKF stream (the SCKF never feeds back into the EKF, paper sec. III-A).

Reported per group size: estimator compute time (wall time inside the local constraint
applications and the global step only, summed over the 400 steps), mean position error and
mean quaternion error (2-norm of the error vs. truth, averaged over links and steps; the
quaternion error is sign-aligned), plus the same errors for the EKF alone.
"""

from __future__ import annotations

import time

import numpy as np

from companion.estimation.constraints import constraint_residual
from companion.estimation.sckf import CAParams
from companion.estimation.semi import make_groups, semi_distributed_apply
from companion.estimation.so3 import quat_distance

from .ekf_chain import ChainRun, EkfStream, simulate_ekf_chain

__all__ = ["PAPER_TABLE2", "GROUP_SIZES", "evaluate_group_size", "run_table2", "aggregate_seeds", "format_table2"]

#: The paper's Table II: group size -> (computing time s, position error m, quaternion error).
PAPER_TABLE2 = {
    2: (13.753, 0.0377, 0.0026),
    3: (15.496, 0.0370, 0.0025),
    4: (16.356, 0.0369, 0.0025),
    6: (20.900, 0.0360, 0.0023),
    12: (29.041, 0.0322, 0.0023),
}
GROUP_SIZES = (2, 3, 4, 6, 12)


def _errors(stream: EkfStream, p: np.ndarray, q: np.ndarray) -> tuple[float, float]:
    pos = float(np.mean(np.linalg.norm(p - stream.p_true, axis=-1)))
    quat = float(np.mean(quat_distance(q, stream.q_true)))
    return pos, quat


def evaluate_group_size(stream: EkfStream, size: int, params: CAParams = CAParams()) -> dict:
    """Run Alg. 2 + eq. 6 on every tick of ``stream`` with groups of ``size`` links."""
    K, n = stream.p.shape[:2]
    groups = make_groups(n, size)
    p_out = np.empty_like(stream.p)
    q_out = np.empty_like(stream.q)
    iterations = np.empty((K, len(groups)), dtype=int)
    residual_after = np.empty(K)
    elapsed = 0.0
    for k in range(K):
        args = (stream.p[k], stream.v[k], stream.q[k], stream.w[k], stream.d, stream.P[k])
        t0 = time.perf_counter()
        res = semi_distributed_apply(*args, groups, params)
        elapsed += time.perf_counter() - t0
        p_out[k], q_out[k] = res.p, res.q
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
    }


def run_table2(
    seed: int = 0,
    run: ChainRun = ChainRun(),
    group_sizes=GROUP_SIZES,
    params: CAParams = CAParams(),
    progress=None,
) -> tuple[dict, EkfStream]:
    """Simulate the EKF stream once, then evaluate every group size on it."""
    stream = simulate_ekf_chain(run, seed, progress)
    n = run.motion.n_links
    residual_before = np.array(
        [np.linalg.norm(constraint_residual(stream.p[k], stream.v[k], stream.q[k], stream.w[k], stream.d))
         for k in range(stream.t.size)]
    )
    ekf_pos, ekf_quat = _errors(stream, stream.p, stream.q)
    result = {
        "ekf_only": {"pos_err_m": ekf_pos, "quat_err": ekf_quat, "residual_mean": float(residual_before.mean())},
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
        },
        "paper": {str(g): dict(zip(("time_s", "pos_err_m", "quat_err"), v)) for g, v in PAPER_TABLE2.items()},
    }
    for size in group_sizes:
        if size > n:
            raise ValueError(f"group size {size} exceeds the number of links ({n})")
        result["groups"][str(size)] = evaluate_group_size(stream, size, params)
    return result, stream


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
        vals = np.array([r["ekf_only"][key] for r in results])
        out["ekf_only"][key] = float(vals.mean())
        out["ekf_only"][f"{key}_std"] = float(vals.std(ddof=1)) if len(vals) > 1 else 0.0
    sizes = list(first["groups"])
    for size in sizes:
        row = {}
        for key in first["groups"][size]:
            vals = np.array([r["groups"][size][key] for r in results], dtype=float)
            row[key] = float(vals.mean())
            if key in ("time_s", "pos_err_m", "quat_err"):
                row[f"{key}_std"] = float(vals.std(ddof=1)) if len(vals) > 1 else 0.0
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

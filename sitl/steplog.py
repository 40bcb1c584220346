"""The companions' step logs joined over the whole chain and matched to the simulator's truth.

Batch and fleet mode both end here: each companion engine (one, or one per group in
distributed mode) logs its steps (:data:`companion.engine.STEP_LOG_KEYS`); :func:`merge_step_logs`
joins the groups' logs on their common cycles and computes the eq. 3 joint errors over the whole
chain before and after the constraint application; :func:`attach_truth` adds the true link
positions at every step time (linear interpolation of the truth log).
"""

from __future__ import annotations

import numpy as np

from companion.estimation.constraints import joint_error_norms

__all__ = ["merge_step_logs", "attach_truth"]

_CHAIN_KEYS = ("p_ekf_sckf", "v_ekf_sckf", "q_ekf_sckf", "w_sckf", "p_local_sckf", "p_corr_sckf", "v_corr_sckf",
               "q_corr_sckf", "corrected_sckf", "P_ekf_sckf", "P_corr_sckf")


def _unique_cycles(log: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    _, first = np.unique(log["cycle_us"], return_index=True)
    return {k: v[first] for k, v in log.items()}


def _at_cycles(log: dict[str, np.ndarray], cycles: np.ndarray) -> dict[str, np.ndarray]:
    """``log``'s rows at ``cycles``; where it has none: NaN (floats), false (flags), -1 (integers)."""
    rows = np.clip(np.searchsorted(log["cycle_us"], cycles), 0, len(log["cycle_us"]) - 1)
    have = log["cycle_us"][rows] == cycles
    out = {}
    for key in (*_CHAIN_KEYS, "global_applied", "leader", "iterations", "nis_max_sckf", "home_offset_sckf"):
        if key not in log:  # (a log written before the key existed)
            continue
        v = log[key][rows]
        if v.dtype.kind == "f":
            fill = np.nan
        elif v.dtype.kind == "b":
            fill = False
        else:
            fill = -1 if key == "leader" else 0
        v = v.copy()
        v[~have] = fill
        out[key] = v
    return out


def _with_skipped(cycles: np.ndarray, period_us: int | None) -> np.ndarray:
    """``cycles`` (sorted) and the cycles of the ``period_us`` grid inside every longer gap."""
    if period_us is None or cycles.size < 2:
        return cycles
    gaps = np.flatnonzero(np.diff(cycles) > 1.5 * period_us)
    if gaps.size == 0:
        return cycles
    filled = [np.arange(cycles[k] + period_us, cycles[k + 1] - period_us // 2, period_us) for k in gaps]
    return np.unique(np.concatenate([cycles, *filled]))


def merge_step_logs(logs: list[list[dict[str, np.ndarray]]], d: np.ndarray, distributed: bool,
                    period_us: int | None = None) -> dict | None:
    """One step log of the whole chain, or ``None`` when a companion has logged no step.

    ``logs``: per companion (per group in distributed mode, in group order) the parts of its log
    in time order (a companion restarted after a fault continues its log in a second part).
    Distributed logs are joined on the cycles any group logged and, given the step period
    ``period_us``, the cycles no group logged between them (every companion down, or every one
    skipped the cycle on a host too busy to run it): a group that logged no step in a
    cycle has NaN states there, ``corrected_sckf`` and ``global_applied`` false and ``leader``
    -1, so the window stays in the log as the outage it was;
    ``global_applied`` and ``home_offset_sckf`` become (steps, groups[, 3]) in either mode. Adds
    ``con_pos_before`` / ``con_vel_before`` / ``con_pos_after`` /
    ``con_vel_after`` (steps, n - 1): the eq. 3 tip position and velocity errors per joint.
    """
    per = []
    for parts in logs:
        parts = [p for p in parts if p and "t_sckf" in p and len(p["t_sckf"])]
        if not parts:
            return None
        joined = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        per.append(_unique_cycles(joined) if distributed else joined)
    if not distributed:
        merged = dict(per[0])
        merged["global_applied"] = merged["global_applied"][:, None]
        if "home_offset_sckf" in merged:  # (steps, groups, 3), as in distributed mode
            merged["home_offset_sckf"] = merged["home_offset_sckf"][:, None]
    else:
        # from the first cycle every group logged (the start-up), every cycle any group logged
        first = max(lg["cycle_us"][0] for lg in per)
        cycles = np.unique(np.concatenate([lg["cycle_us"] for lg in per]))
        cycles = _with_skipped(cycles[cycles >= first], period_us)
        merged = {"t_sckf": cycles * 1e-6, "cycle_us": cycles}
        taken = [_at_cycles(lg, cycles) for lg in per]
        for key in _CHAIN_KEYS:
            merged[key] = np.concatenate([tk[key] for tk in taken], axis=1)
        merged["global_applied"] = np.stack([tk["global_applied"] for tk in taken], axis=1)
        merged["leader"] = np.stack([tk["leader"] for tk in taken], axis=1)
        if all("home_offset_sckf" in tk for tk in taken):
            merged["home_offset_sckf"] = np.stack([tk["home_offset_sckf"] for tk in taken], axis=1)
        merged["iterations"] = np.max(np.stack([tk["iterations"] for tk in taken]), axis=0)
        merged["nis_max_sckf"] = np.fmax.reduce(np.stack([tk["nis_max_sckf"] for tk in taken]), axis=0)
    n = merged["p_ekf_sckf"].shape[1] if merged["t_sckf"].size else 0
    if n > 1:
        for tag, (p, v, q) in (("before", ("p_ekf_sckf", "v_ekf_sckf", "q_ekf_sckf")),
                               ("after", ("p_corr_sckf", "v_corr_sckf", "q_corr_sckf"))):
            pos, vel = joint_error_norms(merged[p], merged[v], merged[q], merged["w_sckf"], d)
            merged[f"con_pos_{tag}"] = pos
            merged[f"con_vel_{tag}"] = vel
    return merged


def attach_truth(step_log: dict[str, np.ndarray], t_truth: np.ndarray, p_truth: np.ndarray,
                 v_truth: np.ndarray | None = None, q_truth: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """``step_log`` restricted to the truth log's time span, with ``p_true_sckf`` (steps, n, 3):
    the true link positions at the step times, linearly interpolated between truth samples, and
    likewise ``v_true_sckf`` and ``q_true_sckf`` (normalised linear interpolation of the
    quaternions, sign-aligned) when the truth's velocities and attitudes are given."""
    t = step_log["t_sckf"]
    keep = (t >= t_truth[0]) & (t <= t_truth[-1])
    out = {k: v[keep] for k, v in step_log.items()}
    ts = out["t_sckf"]
    k = np.clip(np.searchsorted(t_truth, ts, side="right") - 1, 0, max(len(t_truth) - 2, 0))
    if len(t_truth) > 1:
        w = ((ts - t_truth[k]) / (t_truth[k + 1] - t_truth[k]))[:, None, None]
    else:
        w = np.zeros((len(ts), 1, 1))
    k1 = np.minimum(k + 1, len(t_truth) - 1)
    out["p_true_sckf"] = (1.0 - w) * p_truth[k] + w * p_truth[k1]
    if v_truth is not None:
        out["v_true_sckf"] = (1.0 - w) * v_truth[k] + w * v_truth[k1]
    if q_truth is not None:
        q0, q1 = q_truth[k], q_truth[k1]
        q1 = np.where(np.sum(q0 * q1, axis=-1, keepdims=True) < 0, -q1, q1)
        q = (1.0 - w) * q0 + w * q1
        out["q_true_sckf"] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return out

"""What the view shows at one instant (:class:`ViewFrame`), made from one row of a run's log.

A run's log (``log.npz``, :class:`~sitl.runner.RunLog` as it grows, a fleet's merged logs) has
rows at the log rate (``t``: truth, EKF, targets, state words) and rows at the companion's steps
(``t_sckf``: the states a step used and what it made of them). :func:`frame` takes one row of
each, as mappings of key -> that row's array, so that a replay (rows picked by time from the
whole log) and a live run (the newest rows) make their frames the same way. :func:`figures`
computes the panel's figures from rows with or without a leading time axis.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from companion.trajectory import planned_positions

__all__ = ["Poses", "ViewFrame", "FIGURES", "frame", "figures"]

#: the panel's figures: key -> (title, unit)
FIGURES = {
    "constraint_before_mm": ("constraint error before the step (largest joint)", "mm"),
    "constraint_after_mm": ("constraint error after the step (largest joint)", "mm"),
    "tracking_cm": ("tracking error, truth to target (largest link)", "cm"),
    "latency_ms": ("correction latency (largest link)", "ms"),
    "global_step": ("groups whose step took the global shift", "fraction"),
}


@dataclass(frozen=True)
class Poses:
    """Poses of the links (or one body) in the world frame (ENU, z up): positions (n, 3) [m] and
    unit quaternions (n, 4) (w, x, y, z); a row of NaN where nothing is known."""

    p_w_m: np.ndarray
    q_wxyz: np.ndarray

    @property
    def known(self) -> np.ndarray:
        """(n,) whether each row holds a finite pose."""
        return np.isfinite(self.p_w_m).all(axis=-1) & np.isfinite(self.q_wxyz).all(axis=-1)


@dataclass(frozen=True)
class ViewFrame:
    """The run at ``t_s`` (simulated seconds): the truth, the link EKF estimates, the companion's
    corrected estimates at its newest step (``step_t_s``), the targets (in the truth's frame),
    each correction as the move from the estimate the step used to the corrected one, each link's
    state word (:mod:`companion.linkstate`), the load's pose and the panel's figures
    (:data:`FIGURES`). What the log does not hold is ``None``."""

    t_s: float
    truth: Poses
    ekf: Poses | None = None
    corrected: Poses | None = None
    target: Poses | None = None
    step_t_s: float | None = None
    correction_from_w_m: np.ndarray | None = None
    correction_to_w_m: np.ndarray | None = None
    link_state: np.ndarray | None = None
    load: Poses | None = None
    figures: Mapping[str, float] | None = None


def _poses(row: Mapping, p_key: str, q_key: str) -> Poses | None:
    if p_key not in row or q_key not in row:
        return None
    return Poses(np.asarray(row[p_key], dtype=float), np.asarray(row[q_key], dtype=float))


def _targets(row: Mapping) -> Poses | None:
    """The targets of ``row`` in the truth's frame (:func:`companion.trajectory.planned_positions`:
    the companion flies them from its home, in the links' frame)."""
    if "p_target" not in row or "q_target" not in row:
        return None
    return Poses(np.asarray(planned_positions(row), dtype=float), np.asarray(row["q_target"], dtype=float))


def _nanmax(a: np.ndarray, axis: int = -1) -> np.ndarray:
    """The largest finite value along ``axis`` (NaN where there is none), without numpy's warning."""
    a = np.asarray(a, dtype=float)
    if a.shape[axis] == 0:
        return np.full(np.delete(a.shape, axis if axis >= 0 else a.ndim + axis), np.nan)[()]
    finite = np.isfinite(a)
    out = np.max(np.where(finite, a, -np.inf), axis=axis)
    return np.where(finite.any(axis=axis), out, np.nan)[()]


def figures(row: Mapping, step: Mapping | None = None) -> dict[str, np.ndarray]:
    """The panel's figures (:data:`FIGURES`) of log row(s) ``row`` and step row(s) ``step``: each
    a number, or an array over a leading time axis when the rows have one. A figure whose keys
    the rows lack is left out."""
    out: dict[str, np.ndarray] = {}
    if "p_true" in row and "p_target" in row:  # (the targets in the truth's frame: less the home offset)
        err = np.linalg.norm(np.asarray(row["p_true"], float) - planned_positions(row), axis=-1)
        out["tracking_cm"] = 100.0 * _nanmax(err)
    if "correction_latency_ms" in row:
        out["latency_ms"] = _nanmax(row["correction_latency_ms"])
    if step:
        if "con_pos_before" in step:
            out["constraint_before_mm"] = 1e3 * _nanmax(step["con_pos_before"])
        if "con_pos_after" in step:
            out["constraint_after_mm"] = 1e3 * _nanmax(step["con_pos_after"])
        if "global_applied" in step:
            g = np.asarray(step["global_applied"], dtype=float)
            out["global_step"] = g.mean(axis=-1) if g.ndim and g.shape[-1] else np.full(g.shape[:-1], np.nan)[()]
    return out


def frame(t_s: float, row: Mapping, step: Mapping | None = None, load: Mapping | None = None) -> ViewFrame:
    """The frame at ``t_s`` of log row ``row`` (``p_true``, ``q_true`` and what else the log holds),
    the newest step row ``step`` at or before it and the load's row ``load``."""
    truth = _poses(row, "p_true", "q_true")
    if truth is None:
        raise KeyError("a log row needs p_true and q_true")
    corrected = src = dst = step_t = None
    if step:
        corrected = _poses(step, "p_corr_sckf", "q_corr_sckf")
        if "p_ekf_sckf" in step and "p_corr_sckf" in step:
            src, dst = np.asarray(step["p_ekf_sckf"], float), np.asarray(step["p_corr_sckf"], float)
        if "t_sckf" in step:
            step_t = float(step["t_sckf"])
    state = row.get("link_state")
    return ViewFrame(
        t_s=float(t_s), truth=truth, ekf=_poses(row, "p_ekf", "q_ekf"), corrected=corrected,
        target=_targets(row), step_t_s=step_t, correction_from_w_m=src, correction_to_w_m=dst,
        link_state=None if state is None else np.asarray(state), load=_poses(load or {}, "load_p_true", "load_q_true"),
        figures={k: float(v) for k, v in figures(row, step).items()})

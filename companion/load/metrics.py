"""Metrics of the vision measurement and the load's pose.

Errors in the report's definitions, from :mod:`companion.vision.geometry`: eq. 2, the
translation error ``t_est - t_gt`` (its norm here), and eq. 3, the geodesic angle
``|arccos((tr(R_est^T R_gt) - 1) / 2)|``. On top of them:

* :func:`pose_error_series` -- per-sample position error [m] and angle [deg] (the report's
  Figs. 3, 7, 8 for PnP; Figs. 4, 9 for the filters);
* :func:`load_pose_err` -- the ``metrics.json`` entry
  ``{"ekf": {"pos_rms_m", "att_rms_deg", ...}, "ukf": {...}, "unfiltered": {...}}``;
* :func:`pnp_error_table` -- per PnP method: RMS, max, spike count, detection rate, time;
* :func:`detection_rate`, :func:`timing_summary_ms`, :func:`pose_nees`.

numpy only; samples without an estimate (NaN rows) are left out of the RMS and counted.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from companion.estimation.so3 import attitude_error, quat_to_rotmat
from companion.estimation.whiten import whitened

from companion.vision.geometry import geodesic_angle_rad, translation_error_m

__all__ = [
    "rms",
    "pose_error_series",
    "error_summary",
    "load_pose_err",
    "pnp_error_table",
    "detection_rate",
    "timing_summary_ms",
    "pose_nees",
    "pose_error_whitened",
]


def rms(values: np.ndarray) -> float:
    """Root mean square of the finite entries (NaN if there are none)."""
    v = np.asarray(values, dtype=float).ravel()
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v * v))) if v.size else float("nan")


def _as_rotmats(att: np.ndarray) -> np.ndarray:
    att = np.asarray(att, dtype=float)
    if att.shape[-1] == 4:
        return quat_to_rotmat(att)
    if att.shape[-2:] != (3, 3):
        raise ValueError(f"attitudes must be (..., 4) quaternions [w, x, y, z] or (..., 3, 3) matrices, got {att.shape}")
    return att


def pose_error_series(pos_est_m, att_est, pos_gt_m, att_gt) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: ``|t_est - t_gt|`` [m] (eq. 2) and the geodesic angle [deg] (eq. 3).

    Attitudes as quaternions ``(k, 4)`` or rotation matrices ``(k, 3, 3)``; rows with NaN in the
    estimate give NaN."""
    pos_est = np.asarray(pos_est_m, dtype=float)
    pos_gt = np.asarray(pos_gt_m, dtype=float)
    if pos_est.shape != pos_gt.shape or pos_est.shape[-1] != 3:
        raise ValueError(f"positions must both be (k, 3), got {pos_est.shape}, {pos_gt.shape}")
    att = np.array(att_est, dtype=float)
    missing = ~(np.all(np.isfinite(att.reshape(len(pos_est), -1)), axis=1) & np.all(np.isfinite(pos_est), axis=1))
    att[missing] = [1.0, 0.0, 0.0, 0.0] if att.shape[-1] == 4 else np.eye(3)
    R_est = _as_rotmats(att)
    R_gt = _as_rotmats(att_gt)
    if R_gt.shape != R_est.shape:
        raise ValueError(f"attitudes must have matching shapes, got {R_est.shape}, {R_gt.shape}")
    pos_err = np.linalg.norm(translation_error_m(pos_est, pos_gt), axis=-1)
    att_err = np.degrees(geodesic_angle_rad(R_est, R_gt))
    pos_err[missing] = np.nan
    att_err[missing] = np.nan
    return pos_err, att_err


def error_summary(pos_err_m: np.ndarray, att_err_deg: np.ndarray) -> dict:
    """RMS and max of error series, with how many samples had an estimate."""
    pos_err_m = np.asarray(pos_err_m, dtype=float)
    att_err_deg = np.asarray(att_err_deg, dtype=float)
    ok = np.isfinite(pos_err_m) & np.isfinite(att_err_deg)
    return {
        "pos_rms_m": rms(pos_err_m[ok]),
        "att_rms_deg": rms(att_err_deg[ok]),
        "pos_max_m": float(np.max(pos_err_m[ok])) if ok.any() else float("nan"),
        "att_max_deg": float(np.max(att_err_deg[ok])) if ok.any() else float("nan"),
        "n_samples": int(ok.sum()),
        "coverage": float(ok.mean()) if ok.size else float("nan"),
    }


def load_pose_err(estimates: Mapping[str, tuple[np.ndarray, np.ndarray]], pos_gt_m: np.ndarray,
                  q_gt_wxyz: np.ndarray) -> dict:
    """``metrics.json``'s ``load_pose_err``: for every estimator (``"ekf"``, ``"ukf"``,
    ``"unfiltered"``, ...) its ``(pos_w_m (k, 3), q_wxyz (k, 4))`` at the truth's sample times
    against the truth -> ``{name: {"pos_rms_m", "att_rms_deg", "pos_max_m", "att_max_deg",
    "n_samples", "coverage"}}``."""
    return {name: error_summary(*pose_error_series(p, q, pos_gt_m, q_gt_wxyz)) for name, (p, q) in estimates.items()}


def detection_rate(detected) -> float:
    """Fraction of frames with a detection (NaN for no frames)."""
    d = np.asarray(detected, dtype=bool).ravel()
    return float(d.mean()) if d.size else float("nan")


def timing_summary_ms(times_s) -> dict:
    """Mean, median, 95th percentile and max of per-frame times, in milliseconds."""
    t = np.asarray(times_s, dtype=float).ravel() * 1e3
    if not t.size:
        return {"mean_ms": float("nan"), "p50_ms": float("nan"), "p95_ms": float("nan"), "max_ms": float("nan"), "n": 0}
    return {"mean_ms": float(t.mean()), "p50_ms": float(np.median(t)), "p95_ms": float(np.percentile(t, 95)),
            "max_ms": float(t.max()), "n": int(t.size)}


def pnp_error_table(per_method: Mapping[str, Mapping[str, np.ndarray]], spike_m: float = 0.5) -> dict:
    """Per PnP method, errors of the marker's pose in the camera frame (the report's Figs. 3, 7, 8).

    Each method maps to arrays: ``t_est_m`` (k, 3), ``R_est`` (k, 3, 3), ``t_gt_m``, ``R_gt``
    for the frames with a detection, and optionally ``detected`` (frames,) bool and
    ``time_s`` (per-frame detection + PnP time). Returns ``{method: {"pos_rms_m",
    "att_rms_deg", "pos_max_m", "att_max_deg", "n_samples", "coverage", "spikes",
    "detection_rate", "time_ms"}}`` with ``spikes`` the count of position errors above
    ``spike_m`` (P3P's ~2 m spikes in the report)."""
    out = {}
    for method, d in per_method.items():
        pos_err, att_err = pose_error_series(d["t_est_m"], d["R_est"], d["t_gt_m"], d["R_gt"])
        row = error_summary(pos_err, att_err)
        row["spikes"] = int(np.sum(pos_err > spike_m))
        row["detection_rate"] = detection_rate(d["detected"]) if "detected" in d else float("nan")
        row["time_ms"] = timing_summary_ms(d["time_s"]) if "time_s" in d else None
        out[method] = row
    return out


def pose_error_whitened(pos_est_m, q_est_wxyz, P_pose, pos_gt_m, q_gt_wxyz) -> np.ndarray:
    """The pose error (6 dof) per sample, ``[p_gt - p; log(q_gt q^-1)]`` (world-frame attitude
    error, the filters' convention), whitened by ``P_pose`` (k, 6, 6), the covariance of
    ``[dp; dtheta]``: ``L^-1 e`` with ``P = L L^T`` (k, 6). Its squared norm is the NEES; for a
    consistent filter its components are independent unit normals. NaN for a sample whose error is
    not finite or whose covariance is not finite and positive definite (a diverged estimate):
    :func:`~companion.estimation.whiten.whitened`."""
    e = np.concatenate((np.asarray(pos_gt_m, float) - np.asarray(pos_est_m, float),
                        attitude_error(np.asarray(q_gt_wxyz, float), np.asarray(q_est_wxyz, float))), axis=-1)
    return whitened(e, P_pose)


def pose_nees(pos_est_m, q_est_wxyz, P_pose, pos_gt_m, q_gt_wxyz) -> np.ndarray:
    """Normalised estimation error squared of the pose (6 dof) per sample
    (:func:`pose_error_whitened` squared). Mean 6 for a consistent filter."""
    w = pose_error_whitened(pos_est_m, q_est_wxyz, P_pose, pos_gt_m, q_gt_wxyz)
    return np.einsum("ki,ki->k", w, w)
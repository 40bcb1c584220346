"""The companion's load estimation on a slung-load flight, with the truth beside it.

Every delivered camera frame goes through :class:`~companion.load.pipeline.LoadVisionPipeline`
(ArUco, PnP with ``load.pnp_method``, covariance, eq. 4's observation: the marker pipeline of
:func:`load_pipeline_config`), into the companion's load tracker
(:class:`~companion.load.tracker.LoadTracker`) with an EKF and a UKF (frames arrive ``latency_s``
after capture: the filters roll back and replay) and the unfiltered solve
(:class:`~companion.load.unfiltered.UnfilteredLoadPose`); the vehicles' own EKF states (GNSS-aided
position and attitude with their covariances) are the filters' vehicle samples at
``load.vehicle_rate_hz``. The filters start from the rigging's prior below the vehicles' own
estimated positions (the camera-free pose, 0.1 m and 0.1 rad), not from the truth or the
formation's targets.

Each filter is scored twice (:func:`load_pose_metrics`, also the fleet run's): in real time (its
estimate at every vehicle sample, what a controller would get, predicted past the images still on
their way) and at a fixed lag (its estimate of the instant the cameras' longest delivery delay
ago, :func:`fixed_lag_s`, with every image of that instant in: comparable with the camera-only
solve, which refers to its images' capture times).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from companion.load.metrics import error_summary, load_pose_err, pose_error_series, pose_error_whitened, timing_summary_ms
from companion.load.model import VehicleStates
from companion.load.pipeline import LoadVisionPipeline
from companion.load.tracker import LoadTracker
from companion.load.unfiltered import UnfilteredLoadPose
from companion.vision.config import PipelineConfig
from link_firmware_sim.estimators.ekf import E_P, E_TH
from sitl.cameras.rig import CapturedFrame
from sitl.cameras.video import pipeline_config
from sitl.metrics import correlation_time, nees_bounds95

from .config import SlungLoadScenario
from .model import SlungLoadModel

__all__ = ["LoadEstimation", "load_pipeline_config", "fixed_lag_s", "load_pose_metrics"]

#: the filters a batch flight runs side by side (a fleet's companion runs the EKF)
KINDS = ("ekf", "ukf")


def load_pipeline_config(sc: SlungLoadScenario) -> PipelineConfig:
    """The marker pipeline the load's cameras run: the scenario's markers, ``load.pnp_method``, the
    load's marker only, ``load.sigma_floor_px``, ``load.corner_refinement``, and the calibration's
    stated accuracy (the spread the cameras' true intrinsics were drawn with)."""
    cfg = pipeline_config(sc.markers)
    focal, principal, dist = (max(getattr(c, k) for c in sc.cameras) for k in (
        "calib_focal_std_frac", "calib_principal_std_px", "calib_dist_std_frac"))
    return replace(cfg, method=sc.load.pnp_method, ids=(sc.load.marker_id,), sigma_floor_px=sc.load.sigma_floor_px,
                   detector=replace(cfg.detector, corner_refinement=sc.load.corner_refinement),
                   calib_focal_std_frac=focal, calib_principal_std_px=principal, calib_dist_std_frac=dist)


def fixed_lag_s(sc: SlungLoadScenario, dt_s: float) -> float:
    """The fixed-lag estimates' delay: the cameras' longest delivery delay, rounded up to the vehicle
    samples' period (``ValueError`` unless it is shorter than the filters' history)."""
    period = max(1, int(round(1.0 / (sc.load.vehicle_rate_hz * dt_s)))) * dt_s
    lag = period * math.ceil(max(c.max_latency_s for c in sc.cameras) / period - 1e-9)
    if lag >= sc.load.filter.lag_s:
        raise ValueError(f"the cameras' latency ({lag} s) must be shorter than load.filter.lag_s")
    return lag


class LoadEstimation:
    """The companion's load estimation on a slung-load flight, with the truth beside it
    (module docstring). ``on_tick`` at every physics tick (after the kinematics), ``on_frame``
    for every delivered camera frame."""

    def __init__(self, runner, duration_s: float):
        sc: SlungLoadScenario = runner.scenario
        self.runner, self.sc, self.load = runner, sc, sc.load
        self.pipeline = LoadVisionPipeline(load_pipeline_config(sc), sc.cameras_in_body(), sc.load.marker_id,
                                           sc.marker_in_load())
        self.dt = runner.dt
        self.v_div = max(1, int(round(1.0 / (sc.load.vehicle_rate_hz * runner.dt))))
        n_ticks = int(round(duration_s / runner.dt)) + 2
        self.truth_p = np.full((n_ticks, 3), np.nan)
        self.truth_q = np.full((n_ticks, 4), np.nan)
        self.tension = []  # (t, tensions)
        self.lag_s = fixed_lag_s(sc, runner.dt)
        self.tracker = LoadTracker(sc.load, KINDS, fixed_lag_s=self.lag_s)
        self.unfiltered = UnfilteredLoadPose(sc.load.n, window_s=0.5 / max(c.rate_hz for c in sc.cameras))
        self.vehicles: list[VehicleStates] = []
        self.truth_rows: dict[str, list] = {k: [] for k in ("p_true", "q_true", "lag_p_true", "lag_q_true")}
        self.solves: list[tuple] = []  # (t, p, q, p_true, q_true)
        self.frames: dict[str, int] = {}
        self.detected: dict[str, int] = {}
        self.frame_s: list[float] = []
        self.pnp_rows: list[tuple] = []  # (t_capture, vehicle, pos err, att err, range, side px)
        self.filter_s = 0.0

    # -- ticks -------------------------------------------------------------------------------
    def on_tick(self, k: int, t: float) -> None:
        model: SlungLoadModel = self.runner.model
        if k < len(self.truth_p):
            self.truth_p[k], self.truth_q[k] = model.load_pose()
        if k % self.v_div:
            return
        fws = self.runner.firmware
        veh = VehicleStates(t, np.stack([fw.ekf.p_w_m for fw in fws]), np.stack([fw.ekf.v_w_m_s for fw in fws]),
                            np.stack([fw.ekf.P[E_P, E_P] for fw in fws]), np.stack([fw.ekf.q_wxyz for fw in fws]),
                            np.stack([fw.ekf.P[E_TH, E_TH] for fw in fws]),
                            np.stack([fw.ekf.sckf_view()[3] for fw in fws]))
        self.vehicles.append(veh)
        del self.vehicles[:-200]
        w0 = time.perf_counter()
        lagged = len(self.tracker.rows["lag_t"])
        self.tracker.push_vehicles(veh)
        r = self.truth_rows
        r["p_true"].append(self.truth_p[k])
        r["q_true"].append(self.truth_q[k])
        if len(self.tracker.rows["lag_t"]) > lagged:
            p_true, q_true = self._truth_at(t - self.lag_s)
            r["lag_p_true"].append(p_true)
            r["lag_q_true"].append(q_true)
        self.filter_s += time.perf_counter() - w0
        if k % (5 * self.v_div) == 0:
            self.tension.append(np.concatenate(([t], model.cable_tensions())))

    def _vehicles_at(self, t_s: float) -> VehicleStates | None:
        for v in reversed(self.vehicles):
            if v.stamp_s <= t_s + 1e-12:
                return v
        return None

    def _truth_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        k = min(max(int(round(t_s / self.dt)), 0), len(self.truth_p) - 1)
        return self.truth_p[k], self.truth_q[k]

    def on_frame(self, f: CapturedFrame) -> None:
        h = f.frame.header
        self.frames[h.camera] = self.frames.get(h.camera, 0) + 1
        w0 = time.perf_counter()
        res = self.pipeline.on_frame(f.frame)
        self.frame_s.append(time.perf_counter() - w0)
        if res.pose is None:
            return
        self.detected[h.camera] = self.detected.get(h.camera, 0) + 1
        R_true, t_true = f.truth.marker_in_camera(self.load.marker_id)
        pe, ae = pose_error_series(res.pose.t_cm_m[None], res.pose.R_cm[None], t_true[None], R_true[None])
        self.pnp_rows.append((h.t_capture_s, h.vehicle, float(pe[0]), float(ae[0]), float(np.linalg.norm(t_true)),
                              res.pose.side_px))
        obs = res.observation
        w0 = time.perf_counter()
        self.tracker.push_observation(obs)
        veh = self._vehicles_at(obs.stamp_s)
        if veh is not None and self.unfiltered.push(obs, veh):
            p_true, q_true = self._truth_at(self.unfiltered.stamp_s)
            self.solves.append((self.unfiltered.stamp_s, self.unfiltered.pos_w_m, self.unfiltered.q_wxyz, p_true,
                                q_true))
        self.filter_s += time.perf_counter() - w0

    # -- results -------------------------------------------------------------------------------
    def arrays(self) -> dict[str, np.ndarray]:
        out = self.tracker.arrays()
        out.update({f"load_{k}": np.asarray(v) for k, v in self.truth_rows.items() if v})
        if self.solves:
            t, p, q, pt, qt = (np.asarray(a) for a in zip(*self.solves))
            out.update(load_unf_t=t, load_unf_p=p, load_unf_q=q, load_unf_p_true=pt, load_unf_q_true=qt)
        if self.tension:
            out["load_cable_tension"] = np.asarray(self.tension)
        if self.pnp_rows:
            a = np.asarray(self.pnp_rows)
            out.update(load_pnp_t=a[:, 0], load_pnp_vehicle=a[:, 1].astype(int), load_pnp_pos_err_m=a[:, 2],
                       load_pnp_att_err_deg=a[:, 3], load_pnp_range_m=a[:, 4], load_pnp_side_px=a[:, 5])
        return out

    def metrics(self) -> dict:
        a = self.arrays()
        settle = self.load.settle_s
        out = load_pose_metrics(a, settle, KINDS)
        if any(k.endswith("_fixed_lag") for k in out.get("load_pose_err", {})):
            out["load_fixed_lag_s"] = self.lag_s
        if "load_unf_t" in a and np.any(a["load_unf_t"] >= settle):
            k = a["load_unf_t"] >= settle
            out.setdefault("load_pose_err", {})["unfiltered"] = error_summary(*pose_error_series(
                a["load_unf_p"][k], a["load_unf_q"][k], a["load_unf_p_true"][k], a["load_unf_q_true"][k]))
        else:
            out.setdefault("load_pose_err", {})["unfiltered"] = None
        out["load_filter_stats"] = self.tracker.stats()["filters"]
        n_frames = sum(self.frames.values())
        out["load_vision"] = {
            "pnp_method": self.load.pnp_method,
            "frames": dict(self.frames),
            "detection_rate": {c: self.detected.get(c, 0) / n for c, n in self.frames.items()},
            "detection_rate_total": sum(self.detected.values()) / n_frames if n_frames else None,
            "detect_pnp_ms_per_frame": timing_summary_ms(self.frame_s),
            "filters_ms_per_sim_s": 1e3 * self.filter_s / max(self.runner.sim_s, 1e-9),
        }
        if "load_pnp_t" in a:
            out["load_vision"]["pnp_error"] = error_summary(a["load_pnp_pos_err_m"], a["load_pnp_att_err_deg"])
        return out


def load_pose_metrics(a: dict, settle_s: float, kinds) -> dict:
    """``load_pose_err`` (position and attitude error summaries) and ``load_pose_nees`` of the
    filters ``kinds`` and the camera-free pose, in real time (``load_t``) and at the fixed lag
    (``load_lag_t``, when logged), from ``settle_s`` on; ``a``: the tracker's log
    (:func:`companion.load.tracker.log_keys`, prefixed ``load_``) with the truth at its rows
    (``load_p_true``, ``load_q_true``; ``load_lag_p_true``, ``load_lag_q_true``)."""
    out: dict = {}
    if "load_t" in a and np.any(a["load_t"] >= settle_s):
        keep = a["load_t"] >= settle_s
        est = {k: (a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep]) for k in (*kinds, "camera_free")}
        out["load_pose_err"] = load_pose_err(est, a["load_p_true"][keep], a["load_q_true"][keep])
        out["load_pose_nees"] = {k: _nees_check(pose_error_whitened(
            a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep], a[f"load_{k}_P"][keep], a["load_p_true"][keep],
            a["load_q_true"][keep])) for k in kinds}
    if "load_lag_t" in a and np.any(a["load_lag_t"] >= settle_s):
        keep = a["load_lag_t"] >= settle_s
        names = [f"{k}_fixed_lag" for k in kinds]
        est = {k: (a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep]) for k in names}
        out.setdefault("load_pose_err", {}).update(load_pose_err(est, a["load_lag_p_true"][keep],
                                                                 a["load_lag_q_true"][keep]))
        out.setdefault("load_pose_nees", {}).update({k: _nees_check(pose_error_whitened(
            a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep], a[f"load_{k}_P"][keep], a["load_lag_p_true"][keep],
            a["load_lag_q_true"][keep])) for k in names})
    return out


def _nees_check(w: np.ndarray) -> dict:
    """The filter's pose NEES over the window from its whitened errors ``w`` (k, 6): the mean
    (6 for a consistent filter), the effective samples (``k`` over the NEES' correlation time,
    :func:`sitl.metrics.correlation_time`) and the 95 % bounds of such a mean
    (:func:`sitl.metrics.nees_bounds95`, 6 dof); ``inside95`` whether the mean lies within them."""
    nees = np.sum(w * w, axis=-1)
    k_eff = float(len(w) / correlation_time(w))
    lo, hi = (float(b) for b in nees_bounds95(k_eff, dof=6))
    mean = float(np.nanmean(nees))
    return {"mean": mean, "effective_samples": round(k_eff, 1), "bounds95": [lo, hi], "inside95": lo <= mean <= hi}

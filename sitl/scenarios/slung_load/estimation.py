"""The companion's load estimation on a slung-load flight, with the truth beside it.

Every delivered camera frame goes through :class:`~companion.load.pipeline.LoadVisionPipeline`
(ArUco, PnP with ``load.pnp_method``, covariance, eq. 4's observation), into an EKF and a UKF
(:class:`~companion.load.filter.LoadPoseFilter`; frames arrive ``latency_s`` after capture: the
filters roll back and replay) and the unfiltered solve
(:class:`~companion.load.unfiltered.UnfilteredLoadPose`); the vehicles' own EKF states (GNSS-aided
position and attitude with their covariances) are the filters' vehicle samples at
``load.vehicle_rate_hz``. The filters
start from the rigging's prior below the vehicles' own estimated positions (the camera-free
pose, 0.1 m and 0.1 rad), not from the truth or the formation's targets.

Each filter is scored twice: in real time (its estimate at every vehicle sample, what a
controller would get, predicted past the images still on their way) and at a fixed lag (its
estimate of the instant the cameras' longest delivery delay ago, ``load_fixed_lag_s``, with every
image of that instant in: comparable with the camera-only solve, which refers to its images'
capture times).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from companion.load.estimate import initial_estimate
from companion.load.filter import LoadPoseFilter
from companion.load.metrics import (error_summary, load_pose_err, pose_error_series, pose_error_whitened,
                                    timing_summary_ms)
from companion.load.model import ERR_ATT, ERR_POS, VehicleStates
from companion.load.pipeline import LoadVisionPipeline
from companion.load.unfiltered import UnfilteredLoadPose
from link_firmware_sim.estimators.ekf import E_P, E_TH
from sitl.cameras.rig import CapturedFrame
from sitl.cameras.video import pipeline_config
from sitl.metrics import correlation_time, nees_bounds95

from .config import SlungLoadScenario
from .model import SlungLoadModel

__all__ = ["LoadEstimation"]


class LoadEstimation:
    """The companion's load estimation on a slung-load flight, with the truth beside it
    (module docstring). ``on_tick`` at every physics tick (after the kinematics), ``on_frame``
    for every delivered camera frame."""

    def __init__(self, runner, duration_s: float):
        sc: SlungLoadScenario = runner.scenario
        self.runner, self.sc, self.load = runner, sc, sc.load
        self.params = sc.load.params()
        cfg = pipeline_config(sc.markers)
        # the calibration's stated accuracy: the spread the cameras' true intrinsics were drawn with
        focal, principal, dist = (max(getattr(c, k) for c in sc.cameras) for k in (
            "calib_focal_std_frac", "calib_principal_std_px", "calib_dist_std_frac"))
        cfg = replace(cfg, method=sc.load.pnp_method, ids=(sc.load.marker_id,), sigma_floor_px=sc.load.sigma_floor_px,
                      detector=replace(cfg.detector, corner_refinement=sc.load.corner_refinement),
                      calib_focal_std_frac=focal, calib_principal_std_px=principal, calib_dist_std_frac=dist)
        self.pipeline = LoadVisionPipeline(cfg, sc.cameras_in_body(), sc.load.marker_id, sc.marker_in_load())
        self.dt = runner.dt
        self.v_div = max(1, int(round(1.0 / (sc.load.vehicle_rate_hz * runner.dt))))
        n_ticks = int(round(duration_s / runner.dt)) + 2
        self.truth_p = np.full((n_ticks, 3), np.nan)
        self.truth_q = np.full((n_ticks, 4), np.nan)
        self.tension = []  # (t, tensions)
        self.filters: dict[str, LoadPoseFilter] = {}
        self.unfiltered = UnfilteredLoadPose(sc.load.n, window_s=0.5 / max(c.rate_hz for c in sc.cameras))
        self.vehicles: list[VehicleStates] = []
        period = self.v_div * runner.dt
        # the fixed-lag estimates: every image captured before t - lag has arrived by t
        self.lag_s = period * math.ceil(max(c.max_latency_s for c in sc.cameras) / period - 1e-9)
        if self.lag_s >= sc.load.filter.lag_s:
            raise ValueError(f"the cameras' latency ({self.lag_s} s) must be shorter than load.filter.lag_s")
        self.rows: dict[str, list] = {k: [] for k in (
            "t", "p_true", "q_true", "ekf_p", "ekf_q", "ekf_P", "ukf_p", "ukf_q", "ukf_P", "camera_free_p",
            "camera_free_q", "lag_t", "lag_p_true", "lag_q_true", "ekf_fixed_lag_p", "ekf_fixed_lag_q",
            "ekf_fixed_lag_P", "ukf_fixed_lag_p", "ukf_fixed_lag_q", "ukf_fixed_lag_P")}
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
        if not self.filters:
            prior = self.load.camera_free_pose(veh.pos_w_m)  # the rigging below the vehicles' own estimates
            init = initial_estimate(t, prior.pos_m, prior.q_wxyz, veh, self.params, pos_sigma_m=0.1, att_sigma_rad=0.1)
            self.filters = {kind: LoadPoseFilter(kind, self.params, self.load.filter, init) for kind in ("ekf", "ukf")}
        r = self.rows
        r["t"].append(t)
        r["p_true"].append(self.truth_p[k])
        r["q_true"].append(self.truth_q[k])
        sl = np.r_[ERR_POS, ERR_ATT]
        for kind, filt in self.filters.items():
            est = filt.push_vehicles(veh)
            r[f"{kind}_p"].append(est.pos_w_m.copy())
            r[f"{kind}_q"].append(est.q_wxyz.copy())
            r[f"{kind}_P"].append(est.P[np.ix_(sl, sl)])
        t_lag = t - self.lag_s
        if t_lag >= self.rows["t"][0] - 1e-9:
            r["lag_t"].append(t_lag)
            p_true, q_true = self._truth_at(t_lag)
            r["lag_p_true"].append(p_true)
            r["lag_q_true"].append(q_true)
            for kind, filt in self.filters.items():
                est = filt.estimate_at(t_lag)
                r[f"{kind}_fixed_lag_p"].append(est.pos_w_m.copy())
                r[f"{kind}_fixed_lag_q"].append(est.q_wxyz.copy())
                r[f"{kind}_fixed_lag_P"].append(est.P[np.ix_(sl, sl)])
        free = self.load.camera_free_pose(veh.pos_w_m)  # the baseline without cameras
        r["camera_free_p"].append(free.pos_m)
        r["camera_free_q"].append(free.q_wxyz)
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
        for filt in self.filters.values():
            filt.push_observation(obs)
        veh = self._vehicles_at(obs.stamp_s)
        if veh is not None and self.unfiltered.push(obs, veh):
            p_true, q_true = self._truth_at(self.unfiltered.stamp_s)
            self.solves.append((self.unfiltered.stamp_s, self.unfiltered.pos_w_m, self.unfiltered.q_wxyz, p_true,
                                q_true))
        self.filter_s += time.perf_counter() - w0

    # -- results -------------------------------------------------------------------------------
    def arrays(self) -> dict[str, np.ndarray]:
        out = {f"load_{k}": np.asarray(v) for k, v in self.rows.items() if v}
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
        out: dict = {}
        if "load_t" in a and np.any(a["load_t"] >= settle):
            keep = a["load_t"] >= settle
            est = {k: (a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep]) for k in (*self.filters, "camera_free")}
            out["load_pose_err"] = load_pose_err(est, a["load_p_true"][keep], a["load_q_true"][keep])
            out["load_pose_nees"] = {k: _nees_check(pose_error_whitened(
                a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep], a[f"load_{k}_P"][keep], a["load_p_true"][keep],
                a["load_q_true"][keep])) for k in self.filters}
        if "load_lag_t" in a and np.any(a["load_lag_t"] >= settle):
            keep = a["load_lag_t"] >= settle
            names = [f"{k}_fixed_lag" for k in self.filters]
            est = {k: (a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep]) for k in names}
            out.setdefault("load_pose_err", {}).update(load_pose_err(est, a["load_lag_p_true"][keep],
                                                                     a["load_lag_q_true"][keep]))
            out.setdefault("load_pose_nees", {}).update({k: _nees_check(pose_error_whitened(
                a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep], a[f"load_{k}_P"][keep], a["load_lag_p_true"][keep],
                a["load_lag_q_true"][keep])) for k in names})
            out["load_fixed_lag_s"] = self.lag_s
        if "load_unf_t" in a and np.any(a["load_unf_t"] >= settle):
            k = a["load_unf_t"] >= settle
            out.setdefault("load_pose_err", {})["unfiltered"] = error_summary(*pose_error_series(
                a["load_unf_p"][k], a["load_unf_q"][k], a["load_unf_p_true"][k], a["load_unf_q_true"][k]))
        else:
            out.setdefault("load_pose_err", {})["unfiltered"] = None
        out["load_filter_stats"] = {k: {"images": f.stats.images, "accepted": f.stats.accepted,
                                        "rejected": f.stats.rejected, "late": f.stats.late,
                                        "dropped_too_late": f.stats.dropped_too_late,
                                        "replayed_events": f.stats.replayed_events, "mean_nis": f.stats.mean_nis,
                                        "mean_dof": f.stats.mean_dof}
                                    for k, f in self.filters.items()}
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

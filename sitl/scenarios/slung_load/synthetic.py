"""Synthetic slung load: three vehicles fly the report's circle carrying a box by elastic cables
(no physics engine), seeded GNSS and PnP-like camera measurements, and the load filters run on
them (the slung-load report's sec. III-A and IV-A).

Truth: the vehicles follow a prescribed formation (a ``circle_radius_m`` circle at ``speed_m_s``
reached by a smooth ramp, the formation yawing with the circle so the same side of the load faces
the centre, as in the report); the box obeys eq. 8 (:func:`companion.load.model.
load_accelerations`) with each cable a one-sided spring-damper
``T_i = max(0, k (l_i - L_i) + c dl_i/dt)``, integrated by RK4. The filters' model (estimated
tensions, no cable elasticity) therefore differs from the truth, as it would in flight.

Measurements (every random draw from one seed): vehicle samples at ``vehicle_rate_hz`` (position
with white noise ``gnss_sigma_m`` and its covariance, velocity, attitude with white noise
``vehicle_att_sigma_rad`` and its covariance, the formation's yaw rate); per vehicle a downward camera at
``camera_rate_hz`` (staggered), detecting the marker on the load's top face with probability
``detection_prob``; its PnP pose is the true one perturbed in ``[dtheta; dt]`` by a covariance
that grows with distance (rotation and lateral linearly, depth quadratically), optionally with
P3P-like spikes (``outlier_prob``: ``outlier_m`` along the optical axis), turned into eq. 4's
measurement by :func:`~companion.load.measurements.observation_from_pnp`, and delivered
``latency_s`` + U(0, ``latency_jitter_s``) after capture.

This replaces neither MuJoCo nor the real camera pipeline (:mod:`.flight` flies both); it is the
reference for the filters' tests and the ``python -m sitl.bench load_filter`` benchmark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_nonnegative, require_positive
from companion.estimation.so3 import quat_from_rotvec, quat_mul, quat_normalize, quat_to_rotmat
from companion.vision.geometry import POS as PNP_POS
from companion.vision.geometry import ROT as PNP_ROT
from companion.load.estimate import LoadEstimate, LoadFilterConfig, initial_estimate
from companion.load.filter import LoadPoseFilter
from companion.load.formation import arc_length
from companion.load.measurements import marker_in_camera, observation_from_pnp
from companion.load.metrics import load_pose_err, pose_nees
from companion.load.model import (
    ERR_ATT,
    ERR_POS,
    NOM_OMEGA,
    NOM_POS,
    NOM_QUAT,
    NOM_VEL,
    LoadObservation,
    LoadParams,
    Pose3,
    VehicleStates,
    cable_geometry,
    cross,
    load_accelerations,
)
from companion.load.unfiltered import UnfilteredLoadPose

__all__ = ["SlungLoadSim", "LoadTruth", "simulate_truth", "LoadMeasurements", "synthesize", "LoadRun",
           "run_estimators", "summarize"]


@dataclass(frozen=True)
class SlungLoadSim:
    """The synthetic scenario (SI units; see the module docstring)."""

    mass_kg: float = 1.0
    box_size_m: tuple[float, float, float] = (0.4, 0.4, 0.2)
    attach_radius_m: float = 0.18
    formation_radius_m: float = 0.7
    cable_length_m: float = 1.0
    altitude_m: float = 3.0
    circle_radius_m: float = 2.0
    speed_m_s: float = 1.5
    ramp_s: float = 3.0
    duration_s: float = 12.0
    cable_stiffness_n_m: float = 2000.0
    cable_damping_n_s_m: float = 10.0
    sim_dt_s: float = 0.004
    vehicle_rate_hz: float = 50.0
    camera_rate_hz: float = 15.0
    latency_s: float = 0.08
    latency_jitter_s: float = 0.04
    gnss_sigma_m: float = 0.02
    vel_sigma_m_s: float = 0.05
    vehicle_att_sigma_rad: float = 0.005
    pnp_rot_sigma_deg_at_1m: float = 1.0
    pnp_roll_sigma_deg_at_1m: float = 0.3
    pnp_lateral_sigma_m_at_1m: float = 0.003
    pnp_depth_sigma_m_at_1m: float = 0.01
    detection_prob: float = 0.9
    outlier_prob: float = 0.0
    outlier_m: float = 2.0
    n_vehicles: int = 3

    def __post_init__(self) -> None:
        require_positive(self, "mass_kg", "attach_radius_m", "formation_radius_m", "cable_length_m", "circle_radius_m",
                         "ramp_s", "duration_s", "cable_stiffness_n_m", "sim_dt_s", "vehicle_rate_hz", "camera_rate_hz",
                         "pnp_rot_sigma_deg_at_1m", "pnp_roll_sigma_deg_at_1m", "pnp_lateral_sigma_m_at_1m",
                         "pnp_depth_sigma_m_at_1m", "gnss_sigma_m", "vel_sigma_m_s", "vehicle_att_sigma_rad")
        require_nonnegative(self, "speed_m_s", "cable_damping_n_s_m", "latency_s", "latency_jitter_s", "outlier_m")
        if not 0.0 < self.detection_prob <= 1.0 or not 0.0 <= self.outlier_prob < 1.0:
            raise ValueError("detection_prob must be in (0, 1] and outlier_prob in [0, 1)")
        if self.n_vehicles < 3:
            raise ValueError(f"n_vehicles must be >= 3, got {self.n_vehicles}")

    def _angles(self) -> np.ndarray:
        return 2.0 * math.pi * np.arange(self.n_vehicles) / self.n_vehicles

    def load_params(self) -> LoadParams:
        a = self._angles()
        top = 0.5 * self.box_size_m[2]
        attach = np.column_stack((self.attach_radius_m * np.cos(a), self.attach_radius_m * np.sin(a),
                                  np.full(len(a), top)))
        return LoadParams.box(self.mass_kg, self.box_size_m, attach, np.full(len(a), self.cable_length_m))

    def camera_in_body(self) -> Pose3:
        """Downward camera 5 cm below the vehicle's centre: optical z = body -z, image x = body x."""
        return Pose3([0.0, 0.0, -0.05], [0.0, 1.0, 0.0, 0.0])  # 180 deg about x

    def marker_in_load(self) -> Pose3:
        """Marker on the top face's centre, its z out of the face (up)."""
        return Pose3([0.0, 0.0, 0.5 * self.box_size_m[2]], [1.0, 0.0, 0.0, 0.0])

    def formation(self, t: np.ndarray):
        """Vehicles' positions and velocities (k, n, 3) and yaw (k,) at times ``t`` (k,)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        Rc = self.circle_radius_m
        s, s_dot = arc_length(t, self.ramp_s, self.speed_m_s)  # the formation's speed profile
        phi, phi_dot = s / Rc, s_dot / Rc
        c = np.stack((Rc * np.cos(phi) - Rc, Rc * np.sin(phi), np.full_like(phi, self.altitude_m)), axis=-1)
        c_dot = np.stack((-Rc * np.sin(phi) * phi_dot, Rc * np.cos(phi) * phi_dot, np.zeros_like(phi)), axis=-1)
        a = self._angles()
        ang = phi[:, None] + a[None, :]
        off = self.formation_radius_m * np.stack((np.cos(ang), np.sin(ang), np.zeros_like(ang)), axis=-1)
        off_dot = self.formation_radius_m * phi_dot[:, None, None] * np.stack(
            (-np.sin(ang), np.cos(ang), np.zeros_like(ang)), axis=-1)
        return c[:, None, :] + off, c_dot[:, None, :] + off_dot, phi


@dataclass(frozen=True)
class LoadTruth:
    """Ground truth on the simulation grid: times (k,), load nominal states (k, 13 + n) with the
    cables' spring tensions in the tension slots, vehicles' positions/velocities (k, n, 3), yaw (k,)."""

    t_s: np.ndarray
    x: np.ndarray
    vehicle_pos_w_m: np.ndarray
    vehicle_vel_w_m_s: np.ndarray
    vehicle_yaw_rad: np.ndarray

    def index(self, t_s: float) -> int:
        return int(np.clip(np.searchsorted(self.t_s, t_s - 1e-9), 0, len(self.t_s) - 1))


def _spring_tensions(x: np.ndarray, pv: np.ndarray, vv: np.ndarray, sim: SlungLoadSim, params: LoadParams) -> np.ndarray:
    _, length, u, R, Rr = cable_geometry(x, pv, params)
    v_attach = x[NOM_VEL] + cross(R @ x[NOM_OMEGA], Rr)
    l_dot = np.einsum("ni,ni->n", u, vv - v_attach)
    return np.maximum(0.0, sim.cable_stiffness_n_m * (length - params.cable_length_m) + sim.cable_damping_n_s_m * l_dot)


def _truth_rates(x, pv, vv, sim, params):
    x = x.copy()
    x[13:] = _spring_tensions(x, pv, vv, sim, params)
    acc, alpha = load_accelerations(x, pv, params)
    q_dot = 0.5 * quat_mul(x[NOM_QUAT], np.concatenate(([0.0], x[NOM_OMEGA])))
    return np.concatenate((x[NOM_VEL], acc, q_dot, alpha, np.zeros(params.n_cables))), x[13:]


def _hanging_start(sim: SlungLoadSim, params: LoadParams) -> np.ndarray:
    """The load at rest below the resting formation (level, cables stretched by its weight)."""
    horiz = sim.formation_radius_m - sim.attach_radius_m
    top = 0.5 * sim.box_size_m[2]
    length = sim.cable_length_m
    for _ in range(50):
        drop = math.sqrt(max(length**2 - horiz**2, 1e-6))
        T = params.mass_kg * params.gravity_m_s2 * length / (sim.n_vehicles * drop)
        length = sim.cable_length_m + T / sim.cable_stiffness_n_m
    pv, _, _ = sim.formation(np.array([0.0]))
    x = np.zeros(13 + params.n_cables)
    x[NOM_POS] = pv[0].mean(axis=0) - np.array([0.0, 0.0, drop + top])
    x[NOM_QUAT] = (1.0, 0.0, 0.0, 0.0)
    return x


def simulate_truth(sim: SlungLoadSim) -> LoadTruth:
    """Integrate the load under the prescribed formation (RK4, ``sim.sim_dt_s``)."""
    params = sim.load_params()
    n_steps = int(round(sim.duration_s / sim.sim_dt_s))
    t = np.arange(n_steps + 1) * sim.sim_dt_s
    pv_all, vv_all, yaw = sim.formation(t)
    t_half = t[:-1] + 0.5 * sim.sim_dt_s
    pv_half, vv_half, _ = sim.formation(t_half)
    X = np.empty((n_steps + 1, 13 + params.n_cables))
    x = _hanging_start(sim, params)
    h = sim.sim_dt_s
    for k in range(n_steps):
        k1, T = _truth_rates(x, pv_all[k], vv_all[k], sim, params)
        X[k] = x
        X[k, 13:] = T
        k2, _ = _truth_rates(x + 0.5 * h * k1, pv_half[k], vv_half[k], sim, params)
        k3, _ = _truth_rates(x + 0.5 * h * k2, pv_half[k], vv_half[k], sim, params)
        k4, _ = _truth_rates(x + h * k3, pv_all[k + 1], vv_all[k + 1], sim, params)
        x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        x[NOM_QUAT] = quat_normalize(x[NOM_QUAT])
    _, T = _truth_rates(x, pv_all[-1], vv_all[-1], sim, params)
    X[-1] = x
    X[-1, 13:] = T
    return LoadTruth(t, X, pv_all, vv_all, yaw)


@dataclass(frozen=True)
class LoadMeasurements:
    """Seeded measurements: vehicle samples (in time order) and images as
    ``(arrival_s, LoadObservation)`` sorted by arrival; ``frames`` counts camera frames taken and
    ``outliers`` the spikes injected."""

    vehicles: list[VehicleStates]
    images: list[tuple[float, LoadObservation]]
    frames: int
    outliers: int


def _pnp_cov(distance_m: float, sim: SlungLoadSim) -> np.ndarray:
    rot = math.radians(sim.pnp_rot_sigma_deg_at_1m) * distance_m
    roll = math.radians(sim.pnp_roll_sigma_deg_at_1m) * distance_m
    lat = sim.pnp_lateral_sigma_m_at_1m * distance_m
    depth = sim.pnp_depth_sigma_m_at_1m * distance_m**2
    cov = np.zeros((6, 6))
    cov[PNP_ROT, PNP_ROT] = np.diag([rot**2, rot**2, roll**2])
    cov[PNP_POS, PNP_POS] = np.diag([lat**2, lat**2, depth**2])
    return cov


def _yaw_quat(yaw_rad: float) -> np.ndarray:
    return np.array([math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2)])


def synthesize(truth: LoadTruth, sim: SlungLoadSim, seed: int) -> LoadMeasurements:
    """Draw the vehicle samples and the camera images for one seed (module docstring)."""
    rng = np.random.default_rng(seed)
    n = sim.n_vehicles
    cam, marker = sim.camera_in_body(), sim.marker_in_load()
    vehicles = []
    yaw_rate = np.gradient(truth.vehicle_yaw_rad, truth.t_s)
    for t in np.arange(0.0, truth.t_s[-1] + 1e-9, 1.0 / sim.vehicle_rate_hz):
        k = truth.index(t)
        q_true = _yaw_quat(truth.vehicle_yaw_rad[k])
        q_est = quat_mul(quat_from_rotvec(rng.normal(0.0, sim.vehicle_att_sigma_rad, (n, 3))), q_true)
        vehicles.append(VehicleStates(
            float(truth.t_s[k]),
            truth.vehicle_pos_w_m[k] + rng.normal(0.0, sim.gnss_sigma_m, (n, 3)),
            truth.vehicle_vel_w_m_s[k] + rng.normal(0.0, sim.vel_sigma_m_s, (n, 3)),
            np.broadcast_to(np.eye(3) * sim.gnss_sigma_m**2, (n, 3, 3)),
            q_est,
            np.broadcast_to(np.eye(3) * sim.vehicle_att_sigma_rad**2, (n, 3, 3)),
            np.broadcast_to([0.0, 0.0, yaw_rate[k]], (n, 3)),
        ))
    images = []
    frames = outliers = 0
    period = 1.0 / sim.camera_rate_hz
    for i in range(n):
        for t in np.arange(period * (1 + i / n), truth.t_s[-1], period):
            k = truth.index(t)
            frames += 1
            if rng.random() >= sim.detection_prob:
                continue
            x = truth.x[k]
            load = Pose3(x[NOM_POS], x[NOM_QUAT])
            vehicle = Pose3(truth.vehicle_pos_w_m[k, i], _yaw_quat(truth.vehicle_yaw_rad[k]))
            R_cm, t_cm = marker_in_camera(load, vehicle, cam, marker)
            cov = _pnp_cov(float(np.linalg.norm(t_cm)), sim)
            e = rng.multivariate_normal(np.zeros(6), cov)
            R_meas = quat_to_rotmat(quat_from_rotvec(e[PNP_ROT])) @ R_cm
            t_meas = t_cm + e[PNP_POS]
            if sim.outlier_prob and rng.random() < sim.outlier_prob:
                outliers += 1
                t_meas = t_meas + sim.outlier_m * t_cm / np.linalg.norm(t_cm) * rng.choice((-0.5, 1.0))
            obs = observation_from_pnp(i, float(truth.t_s[k]), R_meas, t_meas, cov, cam, marker)
            images.append((float(truth.t_s[k]) + sim.latency_s + rng.uniform(0.0, sim.latency_jitter_s), obs))
    images.sort(key=lambda a: a[0])
    return LoadMeasurements(vehicles, images, frames, outliers)


@dataclass
class LoadRun:
    """Estimates at the vehicle samples' times (the real-time output) against the truth there."""

    t_s: np.ndarray
    pos_gt_w_m: np.ndarray
    q_gt_wxyz: np.ndarray
    pos_w_m: dict[str, np.ndarray] = field(default_factory=dict)
    q_wxyz: dict[str, np.ndarray] = field(default_factory=dict)
    P_pose: dict[str, np.ndarray] = field(default_factory=dict)
    stats: dict[str, dict] = field(default_factory=dict)
    final: dict[str, LoadEstimate] = field(default_factory=dict)
    #: the unfiltered baseline at each solve, against the truth at the time it refers to:
    #: ``(t_s, pos_w_m, q_wxyz, pos_gt_w_m, q_gt_wxyz)``
    unfiltered: tuple[np.ndarray, ...] | None = None


def run_estimators(truth: LoadTruth, meas: LoadMeasurements, sim: SlungLoadSim, cfg: LoadFilterConfig,
                   seed: int, kinds=("ekf", "ukf"), open_loop: bool = True, unfiltered: bool = True,
                   init_pos_sigma_m: float = 0.05, init_att_sigma_rad: float = 0.05,
                   deliver_in_order: bool = False) -> LoadRun:
    """Feed the measurements, in arrival order, to an EKF and/or a UKF (:class:`LoadPoseFilter`),
    the unfiltered baseline (:class:`UnfilteredLoadPose`, images at arrival) and the report's
    ``open_loop`` trajectory (the model without images: its "unfiltered" of Fig. 4). Every filter
    starts from the truth perturbed by one seeded draw of its initial covariance.
    ``deliver_in_order``: deliver each image before the first vehicle sample after its capture
    (zero latency), for comparison with late delivery."""
    params = sim.load_params()
    rng = np.random.default_rng(seed + 7919)
    v0 = meas.vehicles[0]
    x0 = truth.x[truth.index(v0.stamp_s)]
    dp = rng.normal(0.0, init_pos_sigma_m, 3)
    q0 = quat_mul(quat_from_rotvec(rng.normal(0.0, init_att_sigma_rad, 3)), x0[NOM_QUAT])
    init = initial_estimate(v0.stamp_s, x0[NOM_POS] + dp, q0, v0, params,
                            pos_sigma_m=init_pos_sigma_m, att_sigma_rad=init_att_sigma_rad)
    filters = {k: LoadPoseFilter(k, params, cfg, init) for k in kinds}
    if open_loop:
        filters["open_loop"] = LoadPoseFilter("ekf", params, cfg, init)
    base = UnfilteredLoadPose(sim.n_vehicles) if unfiltered else None
    if deliver_in_order:
        images = sorted(meas.images, key=lambda a: a[1].stamp_s)
        events = [(o.stamp_s, 0, o) for _, o in images]
    else:
        events = [(arr, 0, o) for arr, o in meas.images]
    events += [(v.stamp_s, 1, v) for v in meas.vehicles]
    events.sort(key=lambda e: (e[0], e[1]))
    k_truth = np.array([truth.index(v.stamp_s) for v in meas.vehicles])
    run = LoadRun(truth.t_s[k_truth], truth.x[k_truth][:, NOM_POS], truth.x[k_truth][:, NOM_QUAT])
    names = list(filters)
    solves: list[tuple] = []
    K = len(meas.vehicles)
    for name in names:
        run.pos_w_m[name] = np.full((K, 3), np.nan)
        run.q_wxyz[name] = np.full((K, 4), np.nan)
        run.P_pose[name] = np.full((K, 6, 6), np.nan)
    vehicles_seen: list[VehicleStates] = []
    j = 0
    for _, kind, payload in events:
        if kind == 0:
            obs: LoadObservation = payload  # type: ignore[assignment]
            for name, f in filters.items():
                if name != "open_loop":
                    f.push_observation(obs)
            if base is not None:
                i = np.searchsorted([v.stamp_s for v in vehicles_seen], obs.stamp_s, side="right") - 1
                if i >= 0 and base.push(obs, vehicles_seen[i]):
                    k = truth.index(base.stamp_s)
                    solves.append((base.stamp_s, base.pos_w_m, base.q_wxyz, truth.x[k, NOM_POS], truth.x[k, NOM_QUAT]))
            continue
        vehicles_seen.append(payload)
        for name, f in filters.items():
            est = f.push_vehicles(payload)
            run.pos_w_m[name][j] = est.pos_w_m
            run.q_wxyz[name][j] = est.q_wxyz
            sl = np.r_[ERR_POS, ERR_ATT]
            run.P_pose[name][j] = est.P[np.ix_(sl, sl)]
        j += 1
    if solves:
        run.unfiltered = tuple(np.array(a) for a in zip(*solves))
    for name, f in filters.items():
        s = f.stats
        run.stats[name] = {"images": s.images, "accepted": s.accepted, "rejected": s.rejected, "late": s.late,
                           "dropped_too_late": s.dropped_too_late, "replayed_events": s.replayed_events,
                           "mean_nis": s.mean_nis}
        run.final[name] = f.estimate
    return run


def summarize(run: LoadRun, settle_s: float = 1.0) -> dict:
    """``load_pose_err`` after ``settle_s`` (convergence from the initial error left out) and the
    filters' mean pose NEES (6 dof) over the same window."""
    keep = run.t_s >= settle_s
    est = {name: (run.pos_w_m[name][keep], run.q_wxyz[name][keep]) for name in run.pos_w_m}
    out = {"load_pose_err": load_pose_err(est, run.pos_gt_w_m[keep], run.q_gt_wxyz[keep])}
    if run.unfiltered is not None:
        t, p, q, p_gt, q_gt = run.unfiltered
        k = t >= settle_s
        out["load_pose_err"].update(load_pose_err({"unfiltered": (p[k], q[k])}, p_gt[k], q_gt[k]))
    out["pose_nees_mean"] = {
        name: float(np.mean(pose_nees(run.pos_w_m[name][keep], run.q_wxyz[name][keep], run.P_pose[name][keep],
                                      run.pos_gt_w_m[keep], run.q_gt_wxyz[keep])))
        for name in run.P_pose}
    out["filter_stats"] = run.stats
    return out

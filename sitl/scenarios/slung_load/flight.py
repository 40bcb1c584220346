"""The three-vehicle slung-load flight in MuJoCo with the load's pose estimated from the vehicles' cameras (issue 16 items 3 and 5; report ``004_946c2b2ab3d872ae.txt``).

**Model** (:func:`slung_load_mjcf`, :class:`SlungLoadModel`): ``n`` ODAR links of this stack,
each with its own free joint (no joints between them: ``link{i}_root``), each carrying its eight
rotors, sensors and names exactly as in :func:`sitl.model.build_mjcf` (the one-link model
replicated), so the rotor model, the sensors and every link's firmware run unchanged; a box
``load`` (free joint, mass and inertia from ``[load]``); and one MuJoCo spatial tendon per cable,
``cable{i}`` from the vehicle's site ``link{i}_cable`` to the load's ``load_attach{i}``, limited
to ``[0, L_i]``: an inextensible cable that can go slack (its limit constraint's softness is
``load.cable_solref``). The load collides with the ground; the cables with nothing.

**Flight** (:class:`SlungLoadRunner`, a :class:`~sitl.runner.BatchRunner`): the vehicles start
hovering in formation with the load hanging at rest below; the companion engine arms them (its
chain constraint is off: ``companion.enabled = false``), and the formation's targets
(:func:`companion.formation.formation_targets`: the report's 2 m circle at 1.5 m/s, yawing with
it, with the cables' feed-forward force) replace the chain's.

**Estimation** (:class:`LoadEstimation`, as the companion would run it): every delivered camera
frame goes through :class:`~companion.vision.load_pipeline.LoadVisionPipeline` (ArUco, PnP with
``load.pnp_method``, covariance, eq. 4's observation), into an EKF and a UKF
(:class:`~companion.vision.load_filter.LoadPoseFilter`; frames arrive ``latency_s`` after capture:
the filters roll back and replay) and the unfiltered solve
(:class:`~companion.vision.load_filter.UnfilteredLoadPose`); the vehicles' own EKF states (GNSS
aided, position covariance) are the filters' vehicle samples at ``load.vehicle_rate_hz``. The
filters start from the rigging's prior (the load hanging level below the formation, 0.1 m and
0.1 rad), not from the truth.

**Outputs** (:func:`fly_slung_load`): ``metrics.json`` with ``load_pose_err`` (EKF, UKF,
unfiltered: position RMS [m], orientation RMS [deg], after ``load.settle_s``), the per-PnP-method
table (``vision.pnp``: every method on every frame against the truth, the report's Figs. 3, 7, 8),
the detection rate, detection + PnP time per frame, the filters' counters and pose NEES, the
real-time factor; ``log.npz``, ``load.npz``, ``vision.npz``; plots ``load_pose_error.png`` (Figs. 4,
9) and ``pnp_error.png`` (Figs. 3, 7, 8).
"""

from __future__ import annotations

import json
import logging
import re
import time
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np

from companion.config import project
from companion.configfile import dump_toml
from companion.engine import TargetOut
from companion.estimation.so3 import quat_from_euler_zyx
from companion.formation import formation_state, formation_targets
from companion.vision.load_filter import (
    LoadPoseFilter,
    UnfilteredLoadPose,
    initial_estimate,
)
from companion.vision.load_metrics import (
    error_summary,
    load_pose_err,
    pose_error_series,
    pose_nees,
    timing_summary_ms,
)
from companion.vision.load_model import ERR_ATT, ERR_POS, VehicleStates
from companion.vision.load_pipeline import LoadVisionPipeline
from link_firmware_sim.ekf import E_P

from .camera import CapturedFrame
from .fly import _Vision
from .model import SkeletonModel, build_mjcf
from .runner import BatchRunner
from .scenario import Scenario
from .slung_load_config import LoadConfig, SlungLoadScenario
from .video import pipeline_config

__all__ = ["slung_load_mjcf", "SlungLoadModel", "SlungLoadRunner", "LoadEstimation", "fly_slung_load"]

log = logging.getLogger(__name__)


def _fmt(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(v))


def slung_load_mjcf(sc: SlungLoadScenario, timestep_s: float) -> str:
    """MJCF of the vehicles, the load and the cables (module docstring)."""
    load: LoadConfig = sc.load
    n = load.n
    one = build_mjcf(replace(sc.skeleton, n_links=1), sc.geometry(), sc.rotors, timestep_s)
    lines = one.splitlines()
    start = next(i for i, s in enumerate(lines) if '<body name="link1"' in s)
    end = max(i for i, s in enumerate(lines) if s.strip() == "</body>")
    body = lines[start : end + 1]
    imu = next(j for j, s in enumerate(body) if 'name="link1_imu"' in s)
    indent = re.match(r"\s*", body[imu]).group(0)
    body.insert(imu + 1, f'{indent}<site name="link1_cable" pos="{_fmt(load.vehicle_attach_b_m)}" size="0.01"/>')
    actuators = [s for s in lines if "<motor " in s]
    s0, s1 = lines.index("  <sensor>"), lines.index("  </sensor>")
    sensors = lines[s0 + 1 : s1]

    def renamed(block: list[str], i: int) -> list[str]:
        return [re.sub(r"\blink1(?=[_\"])", f"link{i}", s) for s in block]

    P = load.params()
    half = 0.5 * np.asarray(load.size_m, dtype=float)
    load_body = [
        '    <body name="load" pos="0 0 0">',
        '      <freejoint name="load_root"/>',
        f'      <inertial pos="0 0 0" mass="{load.mass_kg:.9g}" diaginertia="{_fmt(np.diag(P.inertia_b_kg_m2))}"/>',
        f'      <geom name="load_box" type="box" size="{_fmt(half)}" contype="1" conaffinity="0" '
        f'rgba="0.85 0.6 0.3 1" mass="0"/>',
        '      <site name="load_center" pos="0 0 0" size="0.01"/>',
        *(f'      <site name="load_attach{i + 1}" pos="{_fmt(P.attach_b_m[i])}" size="0.01"/>' for i in range(n)),
        "    </body>",
    ]
    solref = _fmt(load.cable_solref)
    tendons = ["  <tendon>"]
    for i in range(1, n + 1):
        tendons += [
            f'    <spatial name="cable{i}" limited="true" range="0 {load.cable_length_m[i - 1]:.9g}" '
            f'width="{load.cable_width_m:.9g}" solreflimit="{solref}" rgba="0.1 0.1 0.1 1">',
            f'      <site site="link{i}_cable"/>',
            f'      <site site="load_attach{i}"/>',
            "    </spatial>",
        ]
    tendons.append("  </tendon>")
    out = lines[:start]
    for i in range(1, n + 1):
        out += renamed(body, i)
    out += load_body
    rest = lines[end + 1 :]
    wb = next(j for j, s in enumerate(rest) if "</worldbody>" in s)
    out += rest[: wb + 1] + tendons
    out.append("  <actuator>")
    for i in range(1, n + 1):
        out += renamed(actuators, i)
    out += ["  </actuator>", "  <sensor>"]
    for i in range(1, n + 1):
        out += renamed(sensors, i)
    out += ["  </sensor>", "</mujoco>"]
    return "\n".join(out) + "\n"


class SlungLoadModel(SkeletonModel):
    """The compiled slung-load model; the vehicles answer to :class:`~sitl.model.SkeletonModel`'s
    interface (truth, thrusts, begin/end step), plus the load's truth and the cables' tensions."""

    def __init__(self, sc: SlungLoadScenario, timestep_s: float):
        self.cfg = sc.skeleton
        self.geometry = sc.geometry()
        self.scenario = sc
        self.xml = slung_load_mjcf(sc, timestep_s)
        assets: dict[str, bytes] = {}
        if sc.cameras or sc.markers:
            from .camera import vision_mjcf

            self.xml, assets = vision_mjcf(self.xml, tuple(sc.cameras), tuple(sc.markers))
        self.model = mujoco.MjModel.from_xml_string(self.xml, assets)
        self.data = mujoco.MjData(self.model)
        m = self.model
        n = self.n_links = sc.skeleton.n_links
        n_rot = self.geometry.positions_m.shape[0]
        self.body_ids = np.array([m.body(f"link{i}").id for i in range(1, n + 1)])
        self.actuator_ids = np.array([[m.actuator(f"link{i}_rotor{k}").id for k in range(1, n_rot + 1)]
                                      for i in range(1, n + 1)])
        self.tip_left_ids = np.array([m.site(f"link{i}_tip_left").id for i in range(1, n + 1)])
        self.tip_right_ids = np.array([m.site(f"link{i}_tip_right").id for i in range(1, n + 1)])

        def gather(kind: str, dim: int) -> np.ndarray:
            return np.stack([np.arange(m.sensor(f"link{i}_{kind}").adr[0], m.sensor(f"link{i}_{kind}").adr[0] + dim)
                             for i in range(1, n + 1)])

        self._acc, self._gyro, self._pos = gather("acc", 3), gather("gyro", 3), gather("pos", 3)
        self._quat, self._linvel = gather("quat", 4), gather("linvel", 3)
        self._roots = [(int(m.joint(f"link{i}_root").qposadr[0]), int(m.joint(f"link{i}_root").dofadr[0]))
                       for i in range(1, n + 1)]
        self._load_root = (int(m.joint("load_root").qposadr[0]), int(m.joint("load_root").dofadr[0]))
        self.load_body = m.body("load").id
        self.cable_ids = np.array([m.tendon(f"cable{i}").id for i in range(1, n + 1)])
        self._thrust_dirs = self.geometry.directions / np.linalg.norm(self.geometry.directions, axis=1, keepdims=True)
        self.timestep_s = float(m.opt.timestep)

    def reset(self, start=None) -> None:
        """Vehicles at the formation's start, at rest; the load hanging level below, cables taut."""
        mujoco.mj_resetData(self.model, self.data)
        f = formation_state(0.0, self.scenario.load.formation)
        q = quat_from_euler_zyx(f.yaw_rad, np.zeros(self.n_links), np.zeros(self.n_links))
        qpos = self.data.qpos
        for i, (a, _) in enumerate(self._roots):
            qpos[a : a + 3] = f.pos_w_m[i]
            qpos[a + 3 : a + 7] = q[i]
        pose = self.scenario.load.nominal_pose(f.center_w_m, f.phi_rad)
        a = self._load_root[0]
        qpos[a : a + 3] = pose.pos_m
        qpos[a + 3 : a + 7] = pose.q_wxyz
        mujoco.mj_forward(self.model, self.data)

    def joint_forces(self) -> np.ndarray:
        """No joints between the vehicles: zeros (n-1, 3) (the cables: :meth:`cable_tensions`)."""
        return np.zeros((self.n_links - 1, 3))

    def load_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The load's true ``(pos_w_m, q_wxyz)`` (valid after :meth:`begin_step`)."""
        d = self.data
        return d.xpos[self.load_body].copy(), d.xquat[self.load_body].copy()

    def cable_tensions(self) -> np.ndarray:
        """Each cable's tension [N] (its limit constraint's force; 0 when slack)."""
        d = self.data
        out = np.zeros(self.n_links)
        sel = d.efc_type[: d.nefc] == mujoco.mjtConstraint.mjCNSTR_LIMIT_TENDON
        for row in np.flatnonzero(sel):
            j = np.flatnonzero(self.cable_ids == d.efc_id[row])
            if j.size:
                out[j[0]] = d.efc_force[row]
        return out


class SlungLoadRunner(BatchRunner):
    """:class:`~sitl.runner.BatchRunner` on :class:`SlungLoadModel`, the formation's targets for
    the companion's (module docstring)."""

    def __init__(self, scenario: SlungLoadScenario):
        # The base builds the chain's plant; it is replaced by the slung-load model before any tick.
        super().__init__(replace(project(scenario, Scenario), cameras=(), markers=()))
        sc = self.scenario = scenario
        plant = self.plant
        plant.scenario = sc
        model = SlungLoadModel(sc, plant.dt)
        model.reset()
        model.begin_step()
        plant.model = self.model = model
        plant._fresh = True
        truth = model.truth()
        pos, vel = plant.sensors.gps(0.0, truth.p_w_m, truth.v_w_m_s)
        att = plant.sensors.attitude(0.0, truth.q_wxyz)
        for i, fw in enumerate(self.firmware):
            fw.initialize(0.0, pos[i], vel[i], att[i])
        self.rotors.prime(np.concatenate([fw.hover_command(truth.q_wxyz[i]) for i, fw in enumerate(self.firmware)]))
        self._cable_dirs_f = sc.load.cable_dirs_f()
        self._targets_t: float | None = None
        self._targets: list = []

    def formation_targets(self, t: float) -> list:
        if self._targets_t != t:
            ld = self.scenario.load
            self._targets = formation_targets(t, ld.formation, load_mass_kg=ld.mass_kg,
                                              cable_dirs_f=self._cable_dirs_f)
            self._targets_t = t
        return self._targets

    def _apply(self, engine, outputs, t: float) -> None:
        super()._apply(engine, outputs, t)
        if any(isinstance(o, TargetOut) for o in outputs):
            targets = self.formation_targets(t)
            for o in outputs:
                if isinstance(o, TargetOut):
                    i = engine.links[o.row].index
                    self.firmware[i].set_target(t, targets[i])


class LoadEstimation:
    """The companion's load estimation on a slung-load flight, with the truth beside it
    (module docstring). ``on_tick`` at every physics tick (after the kinematics), ``on_frame``
    for every delivered camera frame."""

    def __init__(self, runner: SlungLoadRunner, duration_s: float):
        sc: SlungLoadScenario = runner.scenario
        self.runner, self.sc, self.load = runner, sc, sc.load
        self.params = sc.load.params()
        cfg = replace(pipeline_config(sc.markers), method=sc.load.pnp_method, ids=(sc.load.marker_id,),
                      sigma_floor_px=sc.load.sigma_floor_px)
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
        self.rows: dict[str, list] = {"t": [], "p_true": [], "q_true": [], "ekf_p": [], "ekf_q": [], "ekf_P": [],
                                      "ukf_p": [], "ukf_q": [], "ukf_P": []}
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
                            np.stack([fw.ekf.P[E_P, E_P] for fw in fws]))
        self.vehicles.append(veh)
        del self.vehicles[:-200]
        w0 = time.perf_counter()
        if not self.filters:
            f = formation_state(t, self.load.formation)
            prior = self.load.nominal_pose(f.center_w_m, f.phi_rad)
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
            est = {k: (a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep]) for k in self.filters}
            out["load_pose_err"] = load_pose_err(est, a["load_p_true"][keep], a["load_q_true"][keep])
            out["load_pose_nees_mean"] = {
                k: float(np.nanmean(pose_nees(a[f"load_{k}_p"][keep], a[f"load_{k}_q"][keep], a[f"load_{k}_P"][keep],
                                              a["load_p_true"][keep], a["load_q_true"][keep]))) for k in self.filters}
        if "load_unf_t" in a and np.any(a["load_unf_t"] >= settle):
            k = a["load_unf_t"] >= settle
            out.setdefault("load_pose_err", {})["unfiltered"] = error_summary(*pose_error_series(
                a["load_unf_p"][k], a["load_unf_q"][k], a["load_unf_p_true"][k], a["load_unf_q_true"][k]))
        else:
            out.setdefault("load_pose_err", {})["unfiltered"] = None
        out["load_filter_stats"] = {k: {"images": f.stats.images, "accepted": f.stats.accepted,
                                        "rejected": f.stats.rejected, "late": f.stats.late,
                                        "dropped_too_late": f.stats.dropped_too_late,
                                        "replayed_events": f.stats.replayed_events, "mean_nis": f.stats.mean_nis}
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


class _LoadVision(_Vision):
    """:class:`sitl.fly._Vision` (cameras, every PnP method against the truth, video) with the
    delivered frames also going to the load's estimation."""

    def __init__(self, runner, video, estimation: LoadEstimation):
        super().__init__(runner, video)
        self.estimation = estimation

    def _cameras(self, k: int, t: float) -> None:
        self.rig.on_tick(k, t)
        for frame in self.rig.poll(t):
            self.log.on_frame(frame)
            self.estimation.on_frame(frame)


def fly_slung_load(scenario: SlungLoadScenario, out_dir: Path | None, *, progress=None, plots: bool = True,
                   video: Path | None = None, **_ignored) -> dict:
    """Fly the slung-load scenario for its ``duration_s``; returns the metrics (and writes the
    run folder's files when ``out_dir`` is given). ``video``: an MP4 of the flight."""
    runner = SlungLoadRunner(scenario)
    sc = runner.scenario
    estimation = LoadEstimation(runner, sc.duration_s)
    runner.tick_hooks.append(estimation.on_tick)
    with _LoadVision(runner, video, estimation) as vision:
        runner.run(sc.duration_s, progress=progress)
    arrays = runner.arrays()
    metrics = {"scenario": sc.name, "seed": sc.seed, "duration_s": runner.sim_s,
               "took_off": runner.plant.took_off, "crashed": runner.crashed,
               "crash_reason": runner.crash_reason,
               "realtime_factor": runner.sim_s / runner.wall_s if runner.wall_s > 0 else None}
    metrics.update(estimation.metrics())
    metrics.update(vision.metrics())
    if vision.rig is not None:
        metrics["load_vision"]["render_ms_per_frame"] = metrics["vision"]["render_ms_per_frame"]
        _add_spikes(metrics["vision"], vision.log)
    if "t" in arrays:  # the vehicles' tracking of the formation (truth against target)
        w = arrays["t"] >= sc.load.settle_s
        err = np.linalg.norm(arrays["p_true"][w] - arrays["p_target"][w], axis=-1)
        metrics["vehicle_track_true_rms_m"] = [float(np.sqrt(np.mean(e**2))) for e in err.T]
        est_err = np.linalg.norm(arrays["p_true"][w] - arrays["p_ekf"][w], axis=-1)
        metrics["vehicle_ekf_err_rms_m"] = [float(np.sqrt(np.mean(e**2))) for e in est_err.T]
    if runner.crashed:
        log.warning("crash: %s", runner.crash_reason)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=_json_default) + "\n")
        np.savez_compressed(out_dir / "log.npz", **arrays)
        np.savez_compressed(out_dir / "load.npz", **estimation.arrays())
        if vision.log is not None:
            np.savez_compressed(out_dir / "vision.npz", **vision.log.arrays())
        (out_dir / "scenario.toml").write_text(dump_toml(replace(sc, duration_s=runner.sim_s)))
        if plots:
            write_load_plots(estimation.arrays(), vision.log.arrays() if vision.log is not None else None, out_dir,
                             sc.load.settle_s)
    return metrics


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(type(o))


def _add_spikes(vision_metrics: dict, vlog, spike_m: float = 0.5) -> None:
    """Per PnP method: the count of position errors above ``spike_m`` (the report's P3P spikes)
    and the marker's median side in the image at them."""
    a = vlog.arrays()
    for j, m in enumerate(a["vision_methods"]):
        sel = a["vision_method"] == j
        big = sel & (a["vision_pos_err_m"] > spike_m)
        row = vision_metrics["pnp"][str(m)]
        row["spikes_over_0_5_m"] = int(big.sum())
        row["side_px_median"] = float(np.median(a["vision_side_px"][sel])) if sel.any() else None


def write_load_plots(load: dict, vision: dict | None, out_dir: Path, settle_s: float) -> None:
    """``load_pose_error.png`` (the report's Figs. 4, 9: EKF, UKF, unfiltered against the truth)
    and ``pnp_error.png`` (Figs. 3, 7, 8: every PnP method's error over time)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if "load_t" in load:
        fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        t = load["load_t"]
        for kind in ("ekf", "ukf"):
            pe, ae = pose_error_series(load[f"load_{kind}_p"], load[f"load_{kind}_q"], load["load_p_true"],
                                       load["load_q_true"])
            axes[0].plot(t, 100 * pe, lw=0.8, label=kind.upper())
            axes[1].plot(t, ae, lw=0.8, label=kind.upper())
        if "load_unf_t" in load:
            pe, ae = pose_error_series(load["load_unf_p"], load["load_unf_q"], load["load_unf_p_true"],
                                       load["load_unf_q_true"])
            axes[0].plot(load["load_unf_t"], 100 * pe, ".", ms=2, label="unfiltered")
            axes[1].plot(load["load_unf_t"], ae, ".", ms=2, label="unfiltered")
        for ax in axes:
            ax.axvline(settle_s, color="gray", lw=0.5)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        axes[0].set(ylabel="load position error [cm]", title="slung load: pose error (report Figs. 4, 9)")
        axes[1].set(ylabel="orientation error [deg]", xlabel="t [s]")
        fig.tight_layout()
        fig.savefig(out_dir / "load_pose_error.png", dpi=110)
        plt.close(fig)
    if vision is not None and len(vision["vision_t"]):
        fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        for j, m in enumerate(vision["vision_methods"]):
            sel = vision["vision_method"] == j
            axes[0].semilogy(vision["vision_t"][sel], vision["vision_pos_err_m"][sel], ".", ms=2, label=str(m))
            axes[1].semilogy(vision["vision_t"][sel], vision["vision_att_err_deg"][sel], ".", ms=2, label=str(m))
        axes[0].set(ylabel="translation error [m] (eq. 2)", title="PnP of the load's marker (report Figs. 3, 7, 8)")
        axes[1].set(ylabel="geodesic angle [deg] (eq. 3)", xlabel="t [s]")
        for ax in axes:
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=8, markerscale=4)
        fig.tight_layout()
        fig.savefig(out_dir / "pnp_error.png", dpi=110)
        plt.close(fig)

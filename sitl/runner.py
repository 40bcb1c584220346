"""Batch mode: physics, firmware and companion stepped in one process on one clock.

One physics tick (1 kHz by default) is::

    kinematics (mj_step1) -> truth
    every firmware tick (500 Hz): targets (target rate), IMU sample, GPS / attitude samples
        queued (their rates), each link's firmware: EKF predict + updates + control + allocation
    every companion tick (20 Hz): link states -> SCKF (Alg. 2 + eq. 6) -> corrections
    rotor/ESC dynamics -> thrusts, wind -> forces -> dynamics and integration (mj_step2)

Everything random comes from ``numpy.random.default_rng(scenario.seed)``; MuJoCo is
deterministic, so the same scenario and seed give the same numbers.

The companion in batch mode sees the states of the current tick and its corrections arrive
in the same tick (no transport latency; the MAVLink fleet adds the wires).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from companion.corrections import compute_corrections
from companion.estimation.chain import CON_DIM, CON_POS, CON_VEL
from companion.estimation.constraints import constraint_residual
from companion.estimation.so3 import attitude_error
from link_firmware_sim.allocation import RotorGeometry
from link_firmware_sim.firmware import LinkFirmware
from sitl.bench.ekf_chain import rate_divisor

from .model import SkeletonModel
from .skeleton import link_inertia
from .rotor import RotorBank
from .scenario import Scenario, WindConfig
from .sensors import LinkSensors
from .trajectory import CpgChainTrajectory, make_trajectory

__all__ = ["Wind", "Plant", "Schedule", "BatchRunner", "RunLog", "joint_norms"]

log = logging.getLogger(__name__)

CRASH_TILT_DEG = 60.0


class Wind:
    """Steady wind plus Gauss-Markov gusts, as a drag force on every link centre."""

    def __init__(self, cfg: WindConfig, n_links: int, drag_area_m2: float, drag_coefficient: float,
                 rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self.gust = np.zeros(3)
        self.k = 0.5 * cfg.air_density_kg_m3 * drag_coefficient * drag_area_m2
        self.mean = np.asarray(cfg.mean_w_m_s, dtype=float)
        self.active = self.k > 0 and (np.any(self.mean != 0) or cfg.gust_std_m_s > 0)

    def force(self, v_w: np.ndarray, dt_s: float) -> np.ndarray | None:
        """(n, 3) drag forces for link velocities ``v_w`` (``None`` when there is no wind)."""
        if not self.active:
            return None
        cfg = self.cfg
        if cfg.gust_std_m_s > 0:
            a = math.exp(-dt_s / cfg.gust_time_constant_s)
            self.gust = a * self.gust + cfg.gust_std_m_s * math.sqrt(1 - a * a) * self.rng.normal(size=3)
        rel = self.mean + self.gust - v_w
        return self.k * np.linalg.norm(rel, axis=1, keepdims=True) * rel


@dataclass
class RunLog:
    """Time series recorded during a run (filled at the log rate and the companion rate)."""

    t: list = field(default_factory=list)
    p_true: list = field(default_factory=list)
    v_true: list = field(default_factory=list)
    q_true: list = field(default_factory=list)
    p_ekf: list = field(default_factory=list)
    q_ekf: list = field(default_factory=list)
    p_ctrl: list = field(default_factory=list)
    q_ctrl: list = field(default_factory=list)
    p_target: list = field(default_factory=list)
    q_target: list = field(default_factory=list)
    thrust: list = field(default_factory=list)
    # companion ticks
    t_sckf: list = field(default_factory=list)
    con_pos_before: list = field(default_factory=list)
    con_vel_before: list = field(default_factory=list)
    con_pos_after: list = field(default_factory=list)
    con_vel_after: list = field(default_factory=list)
    p_true_sckf: list = field(default_factory=list)
    p_ekf_sckf: list = field(default_factory=list)
    p_corr_sckf: list = field(default_factory=list)
    p_local_sckf: list = field(default_factory=list)
    iterations: list = field(default_factory=list)
    # CPG motion (log ticks): the parameters in use and the desired motion
    eta: list = field(default_factory=list)
    xi_desired: list = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(v) for k, v in self.__dict__.items() if len(v)}


def joint_norms(p, v, q, w, d) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint norms of the eq. 3 position and velocity errors."""
    c = constraint_residual(p, v, q, w, d).reshape(-1, CON_DIM)
    return np.linalg.norm(c[:, CON_POS], axis=1), np.linalg.norm(c[:, CON_VEL], axis=1)


@dataclass(frozen=True)
class Schedule:
    """Every rate of a scenario as a whole number of physics ticks."""

    dt: float
    fw: int
    gps: int
    att: int
    sckf: int
    target: int
    log: int

    @classmethod
    def of(cls, sc: Scenario) -> Schedule:
        physics = sc.sim.physics_rate_hz
        fw = rate_divisor(physics, sc.firmware.rate_hz, "firmware.rate_hz")
        return cls(
            dt=1.0 / physics,
            fw=fw,
            gps=fw * rate_divisor(sc.firmware.rate_hz, sc.sensors.gps_rate_hz, "gps"),
            att=fw * rate_divisor(sc.firmware.rate_hz, sc.sensors.attitude_rate_hz, "attitude"),
            sckf=rate_divisor(physics, sc.companion.rate_hz, "companion.rate_hz"),
            target=rate_divisor(physics, sc.sim.target_rate_hz, "target_rate_hz"),
            log=rate_divisor(physics, sc.sim.log_rate_hz, "log_rate_hz"),
        )


class Plant:
    """The physical side of a run: MuJoCo skeleton, rotors and ESCs, sensors and wind.

    Shared by batch mode (firmware called in-process) and fleet mode (firmware behind the HIL
    link). One ``numpy.random.Generator`` seeded from the scenario drives every sensor and gust.
    A physics tick is :meth:`begin_tick` (kinematics, truth) then :meth:`end_tick` (rotor
    dynamics, wind, integration).
    """

    def __init__(self, sc: Scenario):
        self.scenario = sc
        self.n = sc.skeleton.n_links
        self.dt = 1.0 / sc.sim.physics_rate_hz
        self.geometry = RotorGeometry.odar(drag_ratio=sc.rotors.drag_ratio_m, x_scale=sc.skeleton.rotor_x_scale)
        self.inertia = link_inertia(sc.skeleton, self.geometry)
        self.model = SkeletonModel(sc.skeleton, self.geometry, sc.rotors, self.dt)
        self.model.reset(sc.start)
        self.d = sc.skeleton.d_b_m
        self.rng = np.random.default_rng(sc.seed)
        self.sensors = LinkSensors(sc.sensors.suite(), self.n, self.rng)
        self.rotors = RotorBank(8 * self.n, sc.rotors)
        self.wind = Wind(sc.wind, self.n, sc.skeleton.drag_area_m2, sc.skeleton.drag_coefficient, self.rng)
        self.model.begin_step()
        self._fresh = True  # begin_step already done for the current instant
        self.crashed = False
        self.crash_reason = ""

    @property
    def time_s(self) -> float:
        return self.model.time_s

    def start_center(self) -> np.ndarray:
        """Middle point of the chain (middle link centre or middle joint) at the start."""
        p = self.model.truth().p_w_m
        mid = self.n // 2
        return p[mid].copy() if self.n % 2 else 0.5 * (p[mid - 1] + p[mid])

    def begin_tick(self):
        """Kinematics of the current instant; returns the truth."""
        if not self._fresh:
            self.model.begin_step()
        self._fresh = False
        return self.model.truth()

    def end_tick(self) -> None:
        thrust = self.rotors.step(self.dt)
        wind = self.wind.force(self.model.link_velocities(), self.dt) if self.wind.active else None
        self.model.end_step(thrust.reshape(self.n, -1), wind)

    def check_crash(self, t: float, truth, target_q: np.ndarray | None) -> None:
        """Flag a crash: a diverged simulation, or (after the take-off) a link on the ground or far
        off its target attitude (``target_q``: (n, 4))."""
        if self.crashed:
            return
        if not np.all(np.isfinite(truth.p_w_m)):
            self.crashed, self.crash_reason = True, f"simulation diverged at t = {t:.3f} s"
            return
        if t < self.scenario.flight_start_s or self.scenario.trajectory.kind == "rest":
            return
        floor = self.scenario.skeleton.bar_radius_m + 0.05
        if truth.p_w_m[:, 2].min() < floor:
            self.crashed, self.crash_reason = True, f"link below {floor:.2f} m at t = {t:.2f} s"
            return
        if target_q is None:
            return
        tilt = np.degrees(np.linalg.norm(attitude_error(truth.q_wxyz, target_q), axis=1))
        if tilt.max() > CRASH_TILT_DEG:
            self.crashed = True
            self.crash_reason = f"attitude error {tilt.max():.0f} deg on link {int(tilt.argmax()) + 1} at t = {t:.2f} s"


class BatchRunner:
    """Batch mode: a :class:`Plant`, every link's firmware and the companion, in one process."""

    def __init__(self, scenario: Scenario, sckf: bool | None = None, selective_mapping: bool | None = None):
        sc = scenario
        if selective_mapping is not None:
            fw = replace(sc.firmware, allocation=replace(sc.firmware.allocation, selective_mapping=selective_mapping))
            sc = replace(sc, firmware=fw)
        if sckf is not None:
            sc = replace(sc, companion=replace(sc.companion, enabled=sckf))
        self.scenario = sc
        self.plant = Plant(sc)
        plant = self.plant
        self.n = plant.n
        self.dt = plant.dt
        self.schedule = Schedule.of(sc)
        self.d = plant.d
        self.rotors = plant.rotors
        self.model = plant.model
        self.firmware = [LinkFirmware(i, sc.firmware, plant.inertia, plant.geometry) for i in range(self.n)]
        self.groups = sc.companion.group_layout(self.n)
        truth = plant.model.truth()
        self.trajectory = make_trajectory(sc.trajectory, sc.motion, self.n, sc.skeleton.link_length_m,
                                          plant.start_center())
        # Firmware start-up: EKF from the first GPS fix and attitude reference, then arm (a
        # resting chain stays disarmed).
        pos, vel = plant.sensors.gps(0.0, truth.p_w_m, truth.v_w_m_s)
        att = plant.sensors.attitude(0.0, truth.q_wxyz)
        for i, fw in enumerate(self.firmware):
            fw.initialize(0.0, pos[i], vel[i], att[i])
            if sc.trajectory.kind != "rest":
                fw.arm(0.0)
        if not sc.start.on_ground:
            # In-air start: rotors already spinning at the thrusts that carry each link.
            self.rotors.prime(np.concatenate([fw.hover_command(truth.q_wxyz[i]) for i, fw in enumerate(self.firmware)]))
        self.log = RunLog()
        self._seq = 0
        self.wall_s = 0.0
        self.sim_s = 0.0

    @property
    def crashed(self) -> bool:
        return self.plant.crashed

    @property
    def crash_reason(self) -> str:
        return self.plant.crash_reason

    def _companion_tick(self, t: float, truth) -> None:
        sc = self.scenario
        reports = [fw.state_report() for fw in self.firmware]
        p = np.stack([r.p_w_m for r in reports])
        v = np.stack([r.v_w_m_s for r in reports])
        q = np.stack([r.q_wxyz for r in reports])
        w = np.stack([r.omega_b_rad_s for r in reports])
        lg = self.log
        lg.t_sckf.append(t)
        lg.p_true_sckf.append(truth.p_w_m.copy())
        lg.p_ekf_sckf.append(p)
        if self.n > 1:
            pos, vel = joint_norms(p, v, q, w, self.d)
            lg.con_pos_before.append(pos)
            lg.con_vel_before.append(vel)
        if not sc.companion.enabled:
            return
        result, corrections = compute_corrections(reports, self.d, self.groups, sc.companion.params, self._seq)
        self._seq += 1
        for fw, corr in zip(self.firmware, corrections):
            fw.on_correction(t, corr)
        lg.p_corr_sckf.append(result.p)
        lg.p_local_sckf.append(np.concatenate([r.p for r in result.local]))
        lg.iterations.append(result.iterations.max())
        if self.n > 1:
            pos, vel = joint_norms(result.p, result.v, result.q, w, self.d)
            lg.con_pos_after.append(pos)
            lg.con_vel_after.append(vel)

    def _log_tick(self, t: float, truth) -> None:
        lg = self.log
        lg.t.append(t)
        lg.p_true.append(truth.p_w_m.copy())
        lg.v_true.append(truth.v_w_m_s.copy())
        lg.q_true.append(truth.q_wxyz.copy())
        ctrl = [fw.control_estimate(t) for fw in self.firmware]
        lg.p_ctrl.append(np.stack([c[0] for c in ctrl]))
        lg.q_ctrl.append(np.stack([c[2] for c in ctrl]))
        lg.p_ekf.append(np.stack([fw.ekf.p_w_m for fw in self.firmware]))
        lg.q_ekf.append(np.stack([fw.ekf.q_wxyz for fw in self.firmware]))
        lg.p_target.append(np.stack([fw.target.p_w_m for fw in self.firmware]))
        lg.q_target.append(np.stack([fw.target.q_wxyz for fw in self.firmware]))
        lg.thrust.append(self.rotors.thrust_n.reshape(self.n, -1).copy())
        if isinstance(self.trajectory, CpgChainTrajectory):
            lg.eta.append(self.trajectory.eta.copy())
            lg.xi_desired.append(self.trajectory.xi_desired.copy())

    def run(self, duration_s: float, progress=None) -> RunLog:
        """Advance the simulation by ``duration_s``; ``progress(s)`` is called every 100 ms."""
        plant, sch = self.plant, self.schedule
        sensors, rotors = plant.sensors, plant.rotors
        n_ticks = int(round(duration_s / self.dt))
        fw_dt = sch.fw * self.dt
        commands = np.zeros((self.n, 8))
        wall0 = time.perf_counter()
        tick0 = int(round(plant.time_s / self.dt))
        for k in range(tick0, tick0 + n_ticks):
            t = k * self.dt
            truth = plant.begin_tick()
            if k % sch.fw == 0:
                if not np.all(np.isfinite(truth.p_w_m)):
                    plant.check_crash(t, truth, None)
                    break
                if k % sch.target == 0:
                    for fw, target in zip(self.firmware, self.trajectory.targets(t)):
                        fw.set_target(t, target)
                if k % sch.gps == 0:
                    pos, vel = sensors.gps(t, truth.p_w_m, truth.v_w_m_s)
                    for i, fw in enumerate(self.firmware):
                        fw.on_gps(t, pos[i], vel[i])
                if k % sch.att == 0:
                    att = sensors.attitude(t, truth.q_wxyz)
                    for i, fw in enumerate(self.firmware):
                        fw.on_attitude(t, att[i])
                gyro, accel = sensors.imu(truth.specific_force_b_m_s2, truth.omega_b_rad_s, fw_dt)
                for i, fw in enumerate(self.firmware):
                    commands[i] = fw.on_imu(t, gyro[i], accel[i])
                rotors.set_command(commands.reshape(-1))
            if k % sch.sckf == 0:
                self._companion_tick(t, truth)
            if k % sch.log == 0:
                self._log_tick(t, truth)
                plant.check_crash(t, truth, np.stack([fw.target.q_wxyz for fw in self.firmware]))
            plant.end_tick()
            if progress is not None and (k - tick0) % 100 == 99:
                progress(100 * self.dt)
        self.wall_s += time.perf_counter() - wall0
        self.sim_s += n_ticks * self.dt
        return self.log

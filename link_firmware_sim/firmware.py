"""The simulated Pixhawk of one link: EKF, impedance control and allocation, on one clock.

:class:`LinkFirmware` is driven by events carrying the flight-controller time (no sockets,
no wall clock; the SITL harness or, later, the MAVLink shell calls it):

* ``on_imu`` (the IMU rate, 500 Hz): EKF propagation to the sample time, then the measurement
  updates queued since the last sample, then control and allocation; returns the eight rotor
  thrust commands;
* ``on_gps``, ``on_attitude``, ``on_baro``, ``on_mag``: queue a measurement (applied at the next
  ``on_imu``, once the EKF has been propagated to its time); barometer and magnetometer samples
  are fused when they arrive and the EKF config's ``fuse_baro`` / ``fuse_mag`` allows (a link
  without them never calls these), the barometer with the ground-effect deadzone while the link
  is armed and within ``baro_ground_effect_height_m`` of the height it armed at;
* ``on_correction``: the companion's :class:`~companion.messages.Correction`;
* ``on_external_pose``: an external-vision pose (standard-messages mode: the companion's
  corrected estimate), turned into the same correction against the current EKF output;
* ``set_target``: a :class:`~companion.messages.PoseTarget` (under PSPM teleoperation,
  ``pspm_mode = "on"``, an operator set pose that PSPM modulates before the slave law tracks it);
* ``set_contact``: the hybrid controller's :class:`~companion.messages.ContactTarget` (from the SITL
  runner, or MAV_CMD_SKELETON_SET_CONTACT on a vehicle), bounded by ``contact_max_force_n``;
* ``arm`` / ``disarm``.

Control runs on the EKF output plus the latest correction delta, never feeding the delta into
the EKF (paper sec. III-A). The delta is held at full weight for ``correction_hold_s`` after it
arrives and then fades linearly to zero at ``correction_stale_s`` (control on the raw EKF, like
a lost companion). A target older than ``target_stale_s`` is replaced by holding the current
estimated position at the last target attitude (PX4's offboard-loss hold).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from companion.configfile import require_positive
from companion.estimation.so3 import attitude_error, quat_to_rotmat, retract
from companion.mavlink.frames import FRAME_CHANGE_QUATS
from companion.messages import (
    STATE_FLAG_ARMED,
    STATE_FLAG_CORRECTION_ACTIVE,
    STATE_FLAG_EKF_OK,
    STATE_FLAG_GPS_FAULT,
    Correction,
    ExternalWrench,
    LinkState,
    PoseTarget,
)

from companion.skeleton.body import GRAVITY_M_S2, GRAVITY_W_M_S2, LinkInertia
from companion.skeleton.rotors import RotorGeometry

from .allocation import AllocationParams, Allocator
from . import _fast
from .control import ControlIntegrals, ImpedanceGains, impedance_control, impedance_control_compiled, weight_wrench
from .ekf import X_BG, X_P, EkfConfig, EkfNoise, LinkEkf
from .events import StatusEvent
from .gps_health import GpsHealth, GpsHealthConfig
from .hybrid import (ContactTarget, HybridController, HybridGains, MomentumObserver, ObserverConfig,
                     contact_force_estimate, contact_pfaffian)
from .se3_control import Se3PidController, Se3PidGains
from .thrust_limit import ThrustLimit, ThrustLimitConfig
from .pspm import PspmGains, PspmModulator, PspmSlave

__all__ = ["CorrectionRejected", "FirmwareConfig", "LinkFirmware", "outdoor_ekf_config", "m8_ekf_config", "EKF_TUNINGS"]

#: eq. 1 as the fast loop runs it: compiled (:mod:`._fast`, numba installed) or the numpy specification;
#: the EKF and the allocator choose the same way
_IMPEDANCE = impedance_control_compiled if _fast.ENABLED else impedance_control

log = logging.getLogger(__name__)

TAKEOFF_HEIGHT_M = 0.15  # above the arming height: the land detector's take-off
TAKEOFF_SPEED_M_S = 0.5  # armed faster than this: already in flight


def outdoor_ekf_config() -> EkfConfig:
    """EKF tuning for the SITL ``outdoor`` sensor profile (MEMS IMU, M8-class GPS, AHRS).

    The filter estimates position, velocity, attitude and the IMU biases; the companion receives
    the marginal 9x9 covariance of ``[p~; v~; dtheta]``. The GPS position drift (0.5 m below
    0.1 Hz) and the AHRS drift (2 deg) are not white: fused at 10 / 50 Hz as if they were, a
    filter tuned to the white noise alone claims far less error than it has (measured on a 60 s
    three_link flight: time-averaged NEES per 3-dof block of 4.5-11 for position and 31 for
    attitude, where 3 is consistent). The correlated parts are therefore carried in the noise
    this filter assumes: a GPS position variance of 0.6 m^2 (white 0.15 / 0.3 m plus the drift
    seen over the filter's memory) and the process noise that keeps the estimate following the
    drift (position 8e-4 m^2/s). The attitude reference's tilt and heading are set apart
    (``att_yaw_*``): the tilt is also held by gravity through the accelerometers and the GPS
    velocity, so its reference variance is 0.003 rad^2 and its process density 3e-5 rad^2/s,
    while the heading, held by the reference alone, carries its 3 deg white noise and 2 deg
    drift: 0.015 rad^2 and 1.2e-4 rad^2/s. GPS velocity variance is the receiver's white
    0.05 m/s (0.0025 m^2/s^2), with 3e-5 m^2/s^3 process noise (the accelerometer's white
    noise is 5e-6: 0.05 m/s^2 per 500 Hz sample; the rest stands for the accelerometer bias and
    the tilt error that the propagation turns into velocity error).

    Calibrated with the Monte Carlo NEES (``python -m sitl.bench nees``, 10 seeds of 60 s
    three_link) and the per-axis ratio error^2 / variance: with one attitude variance for all
    axes (0.015 rad^2, 1.2e-4 rad^2/s) the tilt's covariance was 2.6 times its error (ratio
    0.38) and the heading's right (0.93), and the velocity block inherited the over-stated tilt
    (NEES 1.9-2.2 with the receiver's variance); with the tilt at 0.0015 rad^2 and 1e-5 rad^2/s
    it turned over-confident, and the horizontal velocity with it (ratios 1.3-1.6 and 1.7-1.9,
    NEES velocity 4.0-4.7). The velocity process noise was 6e-5 at first: the seed-averaged
    velocity NEES was then 2.8-3.1 for the EKF and 2.9 corrected, but single flights read low
    (three_link seed 1: corrected 2.30-2.39, under its bands from 2.32-2.41); with 3e-5 the ten
    seeds read 3.0-3.2 / 3.0 and that flight 2.4-2.5 (bands from 2.29-2.39). Figures with this
    tuning: README, "SITL batch mode". Before any of it (white-noise tuning): NEES position
    6.3-9.4, velocity 1.6-3.5, attitude 15-50, and a true tracking error of 13 cm where it is now
    9 cm on three_link.
    """
    return EkfConfig(
        noise=EkfNoise(
            pos_m2_s=8e-4, vel_m2_s3=3e-5, att_rad2_s=3e-5, accel_bias_m2_s5=1e-6, gyro_bias_rad2_s3=1e-8,
            att_yaw_rad2_s=1.2e-4,
        ),
        gps_pos_var_m2=0.6,
        gps_vel_var_m2_s2=0.0025,
        att_var_rad2=0.003,
        att_yaw_var_rad2=0.015,
        heading_var_rad2=0.04,
        init_pos_var_m2=1.0,
        init_vel_var_m2_s2=0.1,
        init_att_var_rad2=3e-3,
        init_accel_bias_var=2.5e-3,
        init_gyro_bias_var=1e-5,
    )


def m8_ekf_config() -> EkfConfig:
    """EKF tuning for a standalone u-blox M8-class receiver (the SITL ``m8`` profile).

    Such a receiver errs by metres, slowly: a bias that nearby receivers share (1.8 m per axis
    horizontal, 2.7 m vertical, over about 5 min) plus its own (0.8 / 1.2 m over about 60 s), on
    top of 0.1 / 0.2 m of white noise. Nothing on a link can tell that bias from its position
    (only an RTK base or a map could), so the filter follows the receiver, bias and all, with
    :func:`outdoor_ekf_config`'s gains, and says so: the bias's variance (0.8^2 + 1.8^2 = 3.9 m^2
    horizontal, 1.2^2 + 2.7^2 = 8.7 m^2 vertical) is added to the position covariance it reports
    (``gps_bias_var_m2``), not to the gains. Following the bias's wander faster (position process
    noise at its diffusion, 0.06 m^2/s, with the white noise's 0.04 m^2 as the GPS variance) made
    the estimate jump with it and crashed a three_link flight (seed 2, 26 s): the gains stay.
    Measured on three_link 40 s, seeds 1 and 2: position NEES 2.6-5.4 (outdoor's tuning: 1900-3600);
    velocity 3.8-7.4, as with outdoor's tuning (the receiver's correlated velocity error)."""
    return replace(outdoor_ekf_config(), gps_bias_var_m2=(3.9, 8.7))


#: Named EKF tunings (:func:`outdoor_ekf_config`, :func:`m8_ekf_config`), by the receiver they suit
EKF_TUNINGS = {"outdoor": outdoor_ekf_config, "m8": m8_ekf_config}


@dataclass(frozen=True)
class FirmwareConfig:
    """Parameters of one simulated Pixhawk."""

    rate_hz: float = 500.0
    ekf: EkfConfig = field(default_factory=outdoor_ekf_config)
    gains: ImpedanceGains = field(default_factory=ImpedanceGains)
    allocation: AllocationParams = field(default_factory=AllocationParams)
    correction_hold_s: float = 0.1
    correction_stale_s: float = 0.5
    target_stale_s: float = 1.0
    #: largest correction accepted (SKL_CORR_MAXP / _MAXV / _MAXR); a larger one is rejected,
    #: never clamped. The SCKF's largest in the SITL scenarios: 0.78 m, 0.20 m/s, 0.006 rad.
    correction_max_dp_m: float = 2.0
    correction_max_dv_m_s: float = 1.0
    correction_max_dtheta_rad: float = 0.5
    gps: GpsHealthConfig = field(default_factory=GpsHealthConfig)
    #: when the rotors' thrust limit is reported and when the report ends (SKL_TLIM_WARN / _CLR)
    thrust_limit: ThrustLimitConfig = field(default_factory=ThrustLimitConfig)
    #: the pose controller (SKL_CTRL): eq. 1's impedance control, the SE(3) PID of thesis sec. 2.3.2
    #: (:mod:`.se3_control`) or the hybrid pose/wrench control of sec. 2.3.3 (:mod:`.hybrid`: pose
    #: control until a contact is commanded, with the momentum observer running)
    controller: Literal["impedance", "se3_pid", "hybrid"] = "impedance"
    se3_pid: Se3PidGains = field(default_factory=Se3PidGains)
    hybrid: HybridGains = field(default_factory=HybridGains)
    observer: ObserverConfig = field(default_factory=ObserverConfig)
    #: largest contact force a command may ask of the hybrid controller (SKL_CT_FMAX) [N]
    contact_max_force_n: float = 30.0
    #: PSPM teleoperation (SKL_PSPM_EN; thesis sec. 2.3.4, :mod:`.pspm`): ``"off"``; ``"on"``: every
    #: pose target is an operator set pose, modulated by PSPM (:meth:`LinkFirmware.set_target`), and
    #: the slave law of sec. 2.3.4 with ``pspm``'s gains (instead of ``controller``) tracks the
    #: modulated pose; ``"bypass"``: the same slave law on the raw set poses (the unmodulated comparison)
    pspm_mode: Literal["off", "on", "bypass"] = "off"
    #: the reservoirs start full: at rest nothing dissipates, so empty ones would never release a
    #: step (0.4 J pass 0.27 m of the 11 N/m spring at once, 0.3 J 18 deg of the 6 N m/rad one)
    pspm: PspmGains = field(default_factory=lambda: PspmGains(e_max_t_j=0.4, e_max_r_j=0.3, e0_t_j=0.4, e0_r_j=0.3))

    def __post_init__(self) -> None:
        require_positive(self, "rate_hz", "correction_max_dp_m", "correction_max_dv_m_s", "correction_max_dtheta_rad")
        require_positive(self, "contact_max_force_n")
        if not 0 <= self.correction_hold_s < self.correction_stale_s:
            raise ValueError(
                f"correction_hold_s must be in [0, correction_stale_s), got {self.correction_hold_s} "
                f"(stale {self.correction_stale_s})"
            )
        require_positive(self, "target_stale_s")


class CorrectionRejected(ValueError):
    """A correction outside the configured bounds (counted and reported by the shell)."""


class LinkFirmware:
    """One link's flight controller (see the module docstring for the event interface)."""

    def __init__(
        self, link: int, config: FirmwareConfig, inertia: LinkInertia, geometry: RotorGeometry
    ):
        self.link = link
        self.config = config
        self.inertia = inertia
        self.allocator = Allocator(geometry, config.allocation)
        self.ekf: LinkEkf | None = None
        self.armed = False
        self._arm_height_m = 0.0
        self._thrust_total_n = 0.0
        self._airborne = False
        self.integrals = ControlIntegrals()
        self._kernel_const: tuple | None = None  # _tick_fused's packed configuration
        self.target: PoseTarget | None = None
        self._target_time_s = -math.inf
        self._hold: PoseTarget | None = None
        self.correction: Correction | None = None
        self._correction_time_s = -math.inf
        #: seq of the last correction applied and its latency (arrival minus the EKF time it was
        #: computed against) [us]: reported back in the link state
        self.correction_seq = 0
        self.correction_latency_us = 0
        #: (arrival time, latency) of every correction [s]
        self.latency_log: list[tuple[float, float]] = []
        self.time_s = 0.0
        self._zero = np.zeros(8)
        self._pending: list[tuple[str, tuple]] = []
        self.gps_health = GpsHealth(config.gps)
        #: the rotors' thrust limit: time at it, episodes (reported as events)
        self.thrust_limit = ThrustLimit(config.thrust_limit)
        #: GPS health and thrust-limit transitions not yet reported by the shell (STATUSTEXT)
        self.events: list[StatusEvent] = []
        self._make_controller()

    def _make_controller(self) -> None:
        """The selected controller other than eq. 1 (``None`` for the impedance controller), the
        observer (hybrid only) and the commanded contact."""
        cfg = self.config
        self._controller = (Se3PidController(cfg.se3_pid, self.inertia) if cfg.controller == "se3_pid" else
                            HybridController(cfg.hybrid, self.inertia) if cfg.controller == "hybrid" else None)
        self.observer = MomentumObserver(cfg.observer, self.inertia) if cfg.controller == "hybrid" else None
        self.contact: ContactTarget | None = None
        #: PSPM's modulator (``pspm_mode = "on"``) and the last operator set pose it modulated
        self.pspm = PspmModulator(cfg.pspm) if cfg.pspm_mode == "on" else None
        self.operator_target: PoseTarget | None = None
        if cfg.pspm_mode != "off":  # the slave law of sec. 2.3.4 replaces the selected controller
            self._controller, self.observer = PspmSlave(cfg.pspm, self.inertia.mass_kg, self.pspm), None

    def reconfigure(self, config: FirmwareConfig) -> None:
        """Apply a new configuration at once (parameter changes); the EKF keeps its state."""
        if config.allocation != self.config.allocation:
            self.allocator = Allocator(self.allocator.geometry, config.allocation)
        self.gps_health.config = config.gps
        self.thrust_limit.config = config.thrust_limit
        rebuild = (config.controller, config.se3_pid, config.hybrid, config.observer, config.pspm_mode, config.pspm) != (
            self.config.controller, self.config.se3_pid, self.config.hybrid, self.config.observer,
            self.config.pspm_mode, self.config.pspm)
        self.config = config
        if rebuild:
            self._make_controller()

    # -- estimator -------------------------------------------------------------------
    @property
    def initialized(self) -> bool:
        return self.ekf is not None

    def initialize(self, t_s: float, p_w_m, v_w_m_s, q_wxyz) -> None:
        """Start the EKF (from the first GPS fix and attitude reference)."""
        self.ekf = LinkEkf(p_w_m, v_w_m_s, q_wxyz, self.config.ekf)
        self.time_s = t_s
        self.gps_health = GpsHealth(self.config.gps, t_s)

    def on_gps(self, t_s: float, pos_w_m, vel_w_m_s) -> None:
        if self.ekf is not None:
            self._pending.append(("gps", (pos_w_m, vel_w_m_s)))

    def on_attitude(self, t_s: float, q_wxyz) -> None:
        if self.ekf is not None:
            self._pending.append(("att", (q_wxyz,)))

    def on_baro(self, t_s: float, height_m: float) -> None:
        """A barometric height [m] (any constant offset: the EKF references it at its first sample)."""
        if self.ekf is not None and self.config.ekf.fuse_baro:
            self._pending.append(("baro", (height_m,)))

    def on_mag(self, t_s: float, mag_b_gauss) -> None:
        """A magnetometer sample, body frame (FLU) [gauss]."""
        if self.ekf is not None and self.config.ekf.fuse_mag:
            self._pending.append(("mag", (mag_b_gauss,)))

    def in_ground_effect(self) -> bool:
        """Armed and within the EKF config's ``baro_ground_effect_height_m`` above the height it
        armed at (on the ground or taking off or landing: the rotors' downwash reaches the ground
        and the barometer reads low)."""
        if not self.armed or self.ekf is None:
            return False
        return float(self.ekf.x[X_P][2]) - self._arm_height_m < self.config.ekf.baro_ground_effect_height_m

    def _apply_pending(self) -> None:
        ekf = self.ekf
        for kind, args in self._pending:
            if kind == "gps":
                self._fuse_gps(*args)
            elif kind == "att":
                ekf.update_attitude(args[0])
            elif kind == "baro":
                ekf.update_baro(args[0], ground_effect=self.in_ground_effect())
            else:
                ekf.update_mag(args[0])
        self._pending.clear()

    def _fuse_gps(self, pos_w_m, vel_w_m_s) -> None:
        """A GPS fix through the health checks (:mod:`.gps_health`): its position is fused
        only while the GPS is healthy and the fix passes the EKF's gate and the consistency
        test; in a fault it is only tested (the estimate dead-reckons). The velocity is fused."""
        ekf, health, t = self.ekf, self.gps_health, self.time_s
        consistent = health.consistent(t, pos_w_m, vel_w_m_s)
        if not consistent:
            accepted, why = False, f"drifts {health.drift_m_s:.1f} m/s from its velocity"
        elif health.fault:
            accepted, why = ekf.position_test_ratio(pos_w_m) <= 1.0, "position fix rejected"
        else:
            accepted, why = ekf.update_position(pos_w_m).accepted, "position fix rejected"
        was_fault = health.fault
        for ev in health.on_fix(t, accepted, self.correction_weight(t) > 0, why):
            if ev.kind == "reset":
                jump = float(np.linalg.norm(np.asarray(pos_w_m) - ekf.p_w_m))
                ekf.reset_position(pos_w_m)
                ev = StatusEvent("reset", f"GPS reset: position jumped {jump:.1f} m")
            self.events.append(ev)
        if was_fault and not health.fault:  # recovered: this fix is fused again
            ekf.update_position(pos_w_m)
        ekf.update_velocity(vel_w_m_s)

    # -- companion and targets ---------------------------------------------------------
    def on_correction(self, t_s: float, correction: Correction | None) -> None:
        """Apply the companion's correction (``None``: withdrawn, control on the raw EKF).

        Raises :class:`CorrectionRejected` (nothing changes: the previous correction keeps
        fading) when a component exceeds its bound (``correction_max_*``)."""
        if correction is None:
            self.correction = None
            return
        cfg = self.config
        for name, value, bound, unit in (
            ("dp", correction.dp_w_m, cfg.correction_max_dp_m, "m"),
            ("dv", correction.dv_w_m_s, cfg.correction_max_dv_m_s, "m/s"),
            ("dtheta", correction.dtheta_w_rad, cfg.correction_max_dtheta_rad, "rad"),
        ):
            norm = float(np.linalg.norm(value))
            if not norm <= bound:
                raise CorrectionRejected(f"correction {name} {norm:.3g} {unit} exceeds the bound {bound:g} {unit}")
        self.correction = correction
        self._correction_time_s = t_s
        self.correction_seq = correction.seq
        self.correction_latency_us = int(round((t_s - correction.ekf_time_s) * 1e6))
        self.latency_log.append((t_s, t_s - correction.ekf_time_s))

    def on_external_pose(self, t_s: float, p_w_m, v_w_m_s, q_wxyz) -> None:
        """Standard-messages mode: an external pose (the companion's corrected estimate) becomes
        the correction against the current EKF output (it never enters the EKF); without a
        velocity (``None``) the velocity is not corrected."""
        if self.ekf is None:
            return
        st = self.state_report()
        dv = np.zeros(3) if v_w_m_s is None else np.asarray(v_w_m_s, dtype=float) - st.v_w_m_s
        self.on_correction(t_s, Correction(self.link, st.time_s, np.asarray(p_w_m, dtype=float) - st.p_w_m, dv,
                                           attitude_error(np.asarray(q_wxyz, dtype=float), st.q_wxyz),
                                           seq=(self.correction_seq + 1) & 0xFFFF))

    def flags(self, t_s: float) -> int:
        """The state flags reported with every link state."""
        flags = STATE_FLAG_EKF_OK if self.initialized else 0
        if self.initialized and self.gps_health.fault:
            flags |= STATE_FLAG_GPS_FAULT
        if self.armed:
            flags |= STATE_FLAG_ARMED
        if self.correction_weight(t_s) > 0:
            flags |= STATE_FLAG_CORRECTION_ACTIVE
        return flags

    def set_target(self, t_s: float, target: PoseTarget) -> None:
        if self.pspm is not None and self.ekf is not None:
            # an operator set pose (sec. 2.3.4): the controller gets the pose PSPM's reservoirs pay for
            self.operator_target = target
            p, _, q = self.control_estimate(t_s)
            target = PoseTarget.hold(*self.pspm.update(target.p_w_m, target.q_wxyz, p, q, t_s))
        self.target = target
        self._target_time_s = t_s
        self._hold = None

    def set_contact(self, t_s: float, contact: ContactTarget | None) -> None:
        """Command a contact force (hybrid controller; ``None``: pose control only)."""
        if self.config.controller != "hybrid":
            raise ValueError(f"a contact needs controller = 'hybrid' (this link runs {self.config.controller!r})")
        if self.config.pspm_mode != "off":
            raise ValueError("no contact under PSPM teleoperation (SKL_PSPM_EN): the slave law runs")
        if contact is not None and not contact.force_n <= self.config.contact_max_force_n:
            raise ValueError(f"force {contact.force_n:g} N > bound {self.config.contact_max_force_n:g} N")
        self.contact = contact

    def external_wrench_report(self) -> ExternalWrench | None:
        """The observer's estimate as streamed (SKELETON_EXTERNAL_WRENCH); ``None`` without an observer."""
        est = self.external_wrench()
        if est is None:
            return None
        w_e, lam = est
        c = self.contact
        return ExternalWrench(self.link, self.time_s, w_e[:3].copy(), w_e[3:].copy(),
                              float(lam[0]) if lam.size else math.nan, c.force_n if c is not None else math.nan)

    def external_wrench(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The observer's external wrench ``[f_e,w; tau_e,b]`` and its contact-force estimate
        (one per contact; empty without one), or ``None`` when no observer runs."""
        if self.observer is None:
            return None
        if self.ekf is None:
            return self.observer.wrench_e, np.zeros(0)
        return self.observer.wrench_e, self._contact_estimate(self.ekf.q_wxyz)

    def pspm_report(self) -> tuple[float, float, float] | None:
        """PSPM's reservoirs ``(E_t, E_r)`` [J] and how far the modulated set position lags the
        operator's [m]; ``None`` when PSPM is off or before its first operator sample."""
        st = self.pspm.state if self.pspm is not None else None
        if st is None or self.operator_target is None:
            return None
        return st.energy_t_j, st.energy_r_j, float(np.linalg.norm(self.operator_target.p_w_m - st.p_bar_w_m))

    def correction_weight(self, t_s: float) -> float:
        """1 while fresh, linear fade after ``correction_hold_s``, 0 once stale."""
        if self.correction is None:
            return 0.0
        age = t_s - self._correction_time_s
        cfg = self.config
        if age <= cfg.correction_hold_s:
            return 1.0
        if age >= cfg.correction_stale_s:
            return 0.0
        return (cfg.correction_stale_s - age) / (cfg.correction_stale_s - cfg.correction_hold_s)

    def control_estimate(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(p, v, q)`` used by the controller: EKF output plus the weighted correction."""
        ekf = self.ekf
        p, v, q = ekf.p_w_m, ekf.v_w_m_s, ekf.q_wxyz
        wgt = self.correction_weight(t_s)
        if wgt > 0.0:
            c = self.correction
            p = p + wgt * c.dp_w_m
            v = v + wgt * c.dv_w_m_s
            q = retract(q, wgt * c.dtheta_w_rad)
        return p, v, q

    def state_report(self) -> LinkState:
        """The EKF state and covariance sent to the companion."""
        p, v, q, w, P9 = self.ekf.sckf_view()
        return LinkState(self.link, self.time_s, p, v, q, w, P9)

    # -- arming --------------------------------------------------------------------------
    def arm(self, t_s: float) -> bool:
        """Arm (requires an initialised EKF). Without a target the link holds its pose. Arming an
        armed link accepts and changes nothing (PX4: a repeated ARM is acknowledged): a retried
        command that crossed the link's armed state report does not reset its integrators or its
        take-off reference in flight."""
        if self.ekf is None:
            log.warning("link %d: arming refused, EKF not initialised", self.link)
            return False
        if self.armed:
            return True
        self.armed = True
        self.integrals = ControlIntegrals()
        if self._controller is not None:
            self._controller.reset()
        if self.observer is not None:
            self.observer.reset()
        self.allocator.reset()
        p, v, _ = self.control_estimate(t_s)
        self._arm_height_m = float(p[2])
        self._thrust_total_n = 0.0
        # armed while moving (e.g. re-armed after a forced disarm in the air): in flight from the start
        self._airborne = float(np.linalg.norm(v)) > TAKEOFF_SPEED_M_S
        return True

    def landed(self, t_s: float) -> bool:
        """A land detector for disarm checks (PX4's MC land detector in spirit): disarmed; armed
        and not yet taken off (never more than 0.15 m above where it armed, armed at rest); or
        back within 0.15 m of that height, not moving vertically (under 0.5 m/s) and with the
        rotors no longer carrying the link (commanded force under half its weight)."""
        if not self.armed:
            return True
        p, v, _ = self.control_estimate(t_s)
        height = float(p[2]) - self._arm_height_m
        if height > TAKEOFF_HEIGHT_M:
            self._airborne = True
        if not self._airborne:
            return True
        return (self._thrust_total_n < 0.5 * self.inertia.mass_kg * GRAVITY_M_S2 and height < TAKEOFF_HEIGHT_M
                and abs(float(v[2])) < TAKEOFF_SPEED_M_S)

    def hover_command(self, q_wxyz) -> np.ndarray:
        """Thrusts that carry the link's weight at attitude ``q_wxyz`` (no torque).

        Used to start a simulation in the air with the rotors already spinning; the
        allocator's state is left as it was before the call.
        """
        command = self.allocator.allocate(weight_wrench(self.inertia, q_wxyz)).command_n
        self.allocator.reset()
        return command

    def disarm(self) -> None:
        self.armed = False

    def active_target(self, t_s: float, estimate: tuple | None = None) -> PoseTarget:
        """The target the controller tracks at ``t_s`` (disarmed: a hold of the control estimate);
        ``estimate``: :meth:`control_estimate` at ``t_s`` when the caller has it already."""
        p, _, q = self.control_estimate(t_s) if estimate is None else estimate
        return self._active_target(t_s, p) if self.armed else PoseTarget.hold(p, q)

    def _active_target(self, t_s: float, p_w_m) -> PoseTarget:
        if self.target is not None and t_s - self._target_time_s <= self.config.target_stale_s:
            return self.target
        if self._hold is None:
            q = self.target.q_wxyz if self.target is not None else self.ekf.q_wxyz
            self._hold = PoseTarget.hold(p_w_m, q)
            if self.target is not None:
                log.warning("link %d: target stale (%.2f s), holding position", self.link, t_s - self._target_time_s)
        return self._hold

    # -- the fast loop ---------------------------------------------------------------------
    def on_imu(self, t_s: float, gyro_b_rad_s, accel_b_m_s2) -> np.ndarray:
        """EKF propagation, then (armed) control and allocation; returns thrust commands [N]."""
        if self.ekf is None:
            return self._zero
        dt = self._tick_dt(t_s)
        command = self._tick_fused(t_s, dt, gyro_b_rad_s, accel_b_m_s2)  # the steps below in one kernel
        if command is not None:
            return command
        self.ekf.predict(gyro_b_rad_s, accel_b_m_s2, dt)
        self.time_s = t_s
        if self._pending:
            self._apply_pending()
        self.events.extend(self.gps_health.on_tick(t_s))
        if not self.armed:
            self.events.extend(self.thrust_limit.on_tick(t_s, dt, False))
            return self._zero
        p, v, q = self.control_estimate(t_s)
        omega = np.asarray(gyro_b_rad_s, dtype=float) - self.ekf.x[X_BG]
        target = self._active_target(t_s, p)
        ctrl = self._controller
        if ctrl is None:  # the one dispatch point: eq. 1 (default), sec. 2.3.2 or sec. 2.3.3
            U, self.integrals = _IMPEDANCE(
                p, v, q, omega, target, self.config.gains, self.inertia, self.integrals, dt
            )
        elif self.observer is None:
            U = ctrl(p, v, q, omega, target, dt)
        else:
            U = ctrl(p, v, q, omega, target, self.contact, self._contact_estimate(q), dt)
        self._thrust_total_n = float(np.linalg.norm(U[:3]))  # the commanded force (rotors spin both ways)
        if not self._airborne and p[2] - self._arm_height_m > TAKEOFF_HEIGHT_M:
            self._airborne = True  # take-off detected: a disarm now needs the force value
        command = self.allocator.command(U, weight_wrench(self.inertia, q))  # at the limit, the weight kept
        self.events.extend(self.thrust_limit.on_tick(t_s, dt, self.allocator.saturated, self.allocator.scale))
        if self.observer is not None:
            self._observe(v, q, omega, command, dt)
        return command

    def _tick_dt(self, t_s: float) -> float:
        """The step since the last tick; the nominal ``1 / rate_hz`` when not positive (the first
        tick, a repeated stamp). :func:`._fast.hil_loop_kernel` steps its ticks the same way."""
        dt = t_s - self.time_s
        return 1.0 / self.config.rate_hz if dt <= 0.0 else dt

    def _contact_estimate(self, q_wxyz) -> np.ndarray:
        if self.contact is None:
            return np.zeros(0)
        return contact_force_estimate(contact_pfaffian(self.contact, quat_to_rotmat(q_wxyz)), self.observer.wrench_e)

    def _observe(self, v, q_wxyz, omega, command_n, dt: float) -> None:
        """Momentum observer step with the wrench the clipped commands produce, ``[R B_f l; B_tau l]``."""
        U = self.allocator.mapping_matrix @ command_n
        self.observer.step(v, omega, np.concatenate((quat_to_rotmat(q_wxyz) @ U[:3], U[3:])), dt)

    #: run :meth:`on_imu`'s common case as one compiled kernel (:meth:`_tick_fused`); ``False`` on an
    #: instance: every tick through the step-by-step path (the two agree: ``tests/test_fast_paths.py``)
    fused_tick: bool = _fast.ENABLED

    def _tick_fused(self, t_s: float, dt: float, gyro_b_rad_s, accel_b_m_s2) -> np.ndarray | None:
        """:meth:`on_imu`'s common case (armed, eq. 1's controller, a fresh target) by
        :func:`._fast.tick_kernel`: the EKF's propagation, the control estimate, eq. 1 and the
        allocation in one call (with measurements queued: the propagation and the updates first,
        as the step-by-step path runs them), with the same state changes as the step-by-step path.
        ``None`` (nothing changed) in any other case, or without the compiled kernels. The packed
        arrays the kernel reads are kept per object (targets at 50 Hz, gains and the inertia when
        they change), not rebuilt at 500 Hz. A tick with an attitude reference alone queued (the
        attitude reference's ticks between GPS fixes) runs the propagation, the update and the
        tick as one call too (:func:`._fast.attitude_tick_kernel`)."""
        if not self._fused_applies(t_s):
            return None
        ekf = self.ekf
        gyro = np.array(gyro_b_rad_s, dtype=float)
        accel = np.asarray(accel_b_m_s2, dtype=float)
        out = np.empty(_fast.TICK_OUT_SIZE)
        predict = not self._pending
        if not predict:
            pending = self._pending
            if len(pending) == 1 and pending[0][0] == "att" and dt > 0.0:  # an attitude reference alone
                q = np.asarray(pending[0][1][0], dtype=float)
                if q.shape == (4,):
                    x, P, status = _fast.attitude_tick_kernel(ekf.x, ekf.P, q, *self._kernel_consts()[-1], gyro,
                                                              accel, dt, *self._fused_args(t_s), out)
                    if status >= 0:  # (else the steps below raise the specification's error)
                        ekf.x, ekf.P = x, P
                        ekf.count_attitude(int(status == 1), int(status == 0))
                        pending.clear()
                        return self._fused_done(t_s, dt, gyro, out)
            ekf.predict(gyro, accel, dt)
            self.time_s = t_s
            self._apply_pending()
        ekf.x, ekf.P = _fast.tick_kernel(ekf.x, ekf.P, predict, gyro, accel, dt, *self._fused_args(t_s), out)
        return self._fused_done(t_s, dt, gyro, out)

    def _fused_applies(self, t_s: float) -> bool:
        """The fused tick's case: armed, eq. 1's controller without the observer, a fresh target."""
        target = self.target
        return (self.fused_tick and self.armed and self._controller is None and self.observer is None
                and target is not None and t_s - self._target_time_s <= self.config.target_stale_s)

    def _kernel_consts(self) -> tuple:
        """What the kernels read from the configuration and the inertia, packed once (again when
        one of the three is replaced): ``(config, ekf config, inertia, densities, baro_density,
        gains, inertia packed, (the attitude update's covariance, gate))``."""
        const, ekf = self._kernel_const, self.ekf
        if const is None or const[0] is not self.config or const[1] is not ekf.config or const[2] is not self.inertia:
            noise = ekf.config.noise
            const = self._kernel_const = (self.config, ekf.config, self.inertia, noise.densities, noise.baro_bias_m2_s,
                                          _fast.packed(self.config.gains, _fast.pack_gains),
                                          _fast.packed(self.inertia, _fast.pack_inertia), ekf.attitude_kernel_args())
        return const

    def _fused_args(self, t_s: float) -> tuple:
        """:func:`._fast.tick_kernel`'s arguments after ``dt_s`` and before ``out``."""
        wgt = self.correction_weight(t_s)
        corr = _fast.packed(self.correction, _fast.pack_correction) if wgt > 0.0 else _NO_CORRECTION
        _, _, _, densities, baro_density, gains, inertia, _ = self._kernel_consts()
        integrals = self.integrals
        return (densities, baro_density, _GRAVITY_W, wgt, corr, _fast.packed(self.target, _fast.pack_target), gains,
                inertia, integrals.pos, integrals.att, GRAVITY_M_S2, *self.allocator.kernel_args())

    def _fused_done(self, t_s: float, dt: float, gyro: np.ndarray, out: np.ndarray) -> np.ndarray:
        """The state the fused tick leaves outside ``x, P`` (its ``out``, :data:`._fast.TICK_OUT`);
        returns the thrust commands."""
        self.ekf.last_gyro_b_rad_s = gyro
        self.time_s = t_s
        self.events.extend(self.gps_health.on_tick(t_s))
        self.integrals = ControlIntegrals(out[_OUT_POS_INT], out[_OUT_ATT_INT])
        if not out[_OUT_FINITE]:
            raise ValueError(f"U must be 6 finite numbers [force (N); torque (Nm)]; got {out[_OUT_U]!r}")
        self._thrust_total_n = float(out[_OUT_FORCE_NORM])
        if not self._airborne and out[_OUT_P_CTRL_Z] - self._arm_height_m > TAKEOFF_HEIGHT_M:
            self._airborne = True
        alloc = self.allocator
        alloc.scale, alloc.saturated = float(out[_OUT_SCALE]), bool(out[_OUT_SATURATED])
        self.events.extend(self.thrust_limit.on_tick(t_s, dt, alloc.saturated, alloc.scale))
        return out[_OUT_COMMAND]

    def on_hil_record(self, t_s: float, record: np.ndarray, answer: np.ndarray, thrust_max_n: float, mode: int,
                      answered=None, ahrs: np.ndarray | None = None) -> np.ndarray | None:
        """:meth:`on_imu`'s fused case (armed, eq. 1, a fresh target) with no measurement queued,
        straight from a same-host simulator-link record to its answer record, by
        :func:`._fast.hil_tick_kernel`: ``record`` (uint8) one HIL_SENSOR of sample time ``t_s``
        (after a SKELETON_AHRS_REFERENCE on the attitude reference's ticks: :meth:`on_attitude`'s
        update, counted by the EKF; ``ahrs``, when given, gets :data:`._fast.AHRS_OUT`),
        ``answer`` (uint8) gets the HIL_ACTUATOR_CONTROLS (``thrust_max_n``, ``mode``), and
        ``answered(answer)``, when given, is called as soon as it is written and its wrench found
        finite, before the tick's bookkeeping (integrals, health and thrust-limit monitors): the
        simulator is not kept waiting for what does not change the answer. Returns the thrust
        commands; ``None`` (nothing changed or written) in any other case, for a record the kernel
        leaves to the decoding path, or without the compiled kernels. The vehicle's shell calls it;
        the record layouts are :data:`._fast.HIL_SENSOR_RECORD` / ``HIL_ACTUATOR_RECORD``, which
        :mod:`.simlink` checks against the dialect."""
        if self.ekf is None or self._pending or not self._fused_applies(t_s):
            return None
        dt = self._tick_dt(t_s)
        gyro, out, ekf = np.empty(3), np.empty(_fast.TICK_OUT_SIZE), self.ekf
        ahrs = np.zeros(_fast.AHRS_OUT_SIZE) if ahrs is None else ahrs
        ahrs[:] = 0.0
        x, P, taken = _fast.hil_tick_kernel(record, thrust_max_n, mode, answer, gyro, ekf.x, ekf.P, dt,
                                            *self._fused_args(t_s), *self._kernel_consts()[-1], FRAME_CHANGE_QUATS,
                                            ahrs, out)
        if not taken:
            return None
        ekf.x, ekf.P = x, P
        ekf.count_attitude(int(ahrs[_AHRS_ACCEPTED]), int(ahrs[_AHRS_REJECTED]))
        if answered is not None and out[_OUT_FINITE]:
            answered(answer)
        return self._fused_done(t_s, dt, gyro, out)

    #: let the vehicle run its quiet lockstep ticks in :func:`._fast.hil_loop_kernel` (:meth:`on_hil_loop`);
    #: ``False`` on an instance: every tick through :meth:`on_hil_record` (the two agree: ``tests/test_simlink.py``)
    hil_loop: bool = _fast.ENABLED

    def on_hil_loop(self, pfd: np.ndarray, n_fds: int, timeout_ms: int, max_ticks: int, buf: np.ndarray,
                    answer: np.ndarray, thrust_max_n: float, mode: int, due_us: int, answered,
                    ahrs: np.ndarray, framing: np.ndarray | None = None, rec: np.ndarray | None = None,
                    frame: np.ndarray | None = None) -> tuple | None:
        """The vehicle's lockstep over quiet ticks (:func:`._fast.hil_loop_kernel`, the waits and the
        socket calls in it): each is :meth:`on_hil_record`'s tick, answered through the simulator's
        socket (``pfd``'s first descriptor) from ``answer``, with the bookkeeping left out that such a
        tick does not change. The newest tick's bookkeeping is done here (``answered(answer)`` first
        if the kernel did not send it), as :meth:`on_hil_record` does it, and stands for the ticks
        before it. ``due_us``: the vehicle's next stream or log row (a tick at or after it is the
        last). ``ahrs`` gets :data:`._fast.AHRS_OUT` (the attitude references fused, counted by the
        EKF). ``framing`` (:data:`._fast.FRAMING`, with the buffers ``rec`` and ``frame``): the
        simulator's link is PX4's TCP link, MAVLink 2 frames on a stream (``None``: the same-host
        link's records). Returns ``(status, ticks, sent, t_us, packet, taken_bytes)`` (:data:`._fast.LOOP_INFO`); ``None``
        (nothing waited for or changed) unless the case holds: armed, eq. 1, a target, no
        measurement or event queued, the GPS and thrust-limit monitors quiet."""
        if not (self.hil_loop and self.ekf is not None and not self._pending and not self.events
                and not self.gps_health.fault and self.thrust_limit.quiet and self._fused_applies(self.time_s)):
            return None
        ekf, cfg = self.ekf, self.config
        corr = self.correction
        corr_time = math.nan if corr is None else self._correction_time_s
        corr_arr = _NO_CORRECTION if corr is None else _fast.packed(corr, _fast.pack_correction)
        args = self._fused_args(self.time_s)  # (the kernel weighs the correction itself, tick by tick)
        densities, baro_density, gravity_w, _, _, tgt, gains, inertia, pos, att, gravity, *alloc = args
        pos, att = pos.copy(), att.copy()  # updated in place by the kernel
        gyro, out, info = np.empty(3), np.empty(_fast.TICK_OUT_SIZE), np.zeros(_fast.LOOP_INFO_SIZE)
        ahrs[:] = 0.0
        if framing is None:  # (records: the frame buffers are not touched)
            framing, rec, frame = np.zeros(_fast.FRAMING_SIZE, dtype=np.int64), _NO_BYTES, _NO_BYTES
        x, P = _fast.hil_loop_kernel(
            pfd, n_fds, timeout_ms, max_ticks, buf, thrust_max_n, mode, answer, gyro, ekf.x, ekf.P, self.time_s,
            1.0 / cfg.rate_hz, self._target_time_s, cfg.target_stale_s, corr_time, cfg.correction_hold_s,
            cfg.correction_stale_s, self.gps_health.last_fix_s, self.gps_health.config.timeout_s, due_us,
            math.inf if self._airborne else self._arm_height_m, TAKEOFF_HEIGHT_M, densities, baro_density,
            gravity_w, corr_arr, tgt, gains, inertia, pos, att, gravity, *alloc, *self._kernel_consts()[-1],
            FRAME_CHANGE_QUATS, ahrs, out, info, framing, rec, frame)
        status, ticks, sent, t_us, packet, taken_bytes = (int(info[k]) for k in (0, 1, 2, 3, 5, 6))
        if ticks:
            ekf.x, ekf.P = x, P
            ekf.count_attitude(int(ahrs[_AHRS_ACCEPTED]), int(ahrs[_AHRS_REJECTED]))
            t_s = t_us * 1e-6
            if sent < ticks and out[_OUT_FINITE]:
                answered(answer)
            self._fused_done(t_s, float(info[4]), gyro, out)
        return status, ticks, sent, t_us, packet, taken_bytes


_OUT_COMMAND = _fast.TICK_OUT["command"]
_OUT_U = _fast.TICK_OUT["U"]
_OUT_POS_INT = _fast.TICK_OUT["pos_int"]
_OUT_ATT_INT = _fast.TICK_OUT["att_int"]
_OUT_FORCE_NORM = _fast.TICK_OUT["force_norm"]
_OUT_P_CTRL_Z = _fast.TICK_OUT["p_ctrl"].start + 2
_OUT_FINITE = _fast.TICK_OUT["finite"]
_OUT_SCALE = _fast.TICK_OUT["scale"]
_OUT_SATURATED = _fast.TICK_OUT["saturated"]
_AHRS_ACCEPTED = _fast.AHRS_OUT["accepted"]
_AHRS_REJECTED = _fast.AHRS_OUT["rejected"]


_NO_BYTES = np.zeros(0, dtype=np.uint8)  # the frame buffers of the lockstep loop over records (unused)
_NO_CORRECTION = np.zeros(9)
_NO_CORRECTION.setflags(write=False)  # as a packed correction: one compiled signature
_GRAVITY_W = np.array(GRAVITY_W_M_S2, dtype=float)

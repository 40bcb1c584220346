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
the EKF (paper sec. III-A), except while the GPS is in fault: then the corrected position aids
the EKF (:mod:`.estimators.correction_aid`). The delta is held at full weight for
``correction_hold_s`` after it arrives and then fades linearly to zero at ``correction_stale_s``
(control on the raw EKF, like a lost companion). A target older than ``target_stale_s`` is
replaced by holding the current estimated position at the last target attitude (PX4's
offboard-loss hold).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from companion.estimation.so3 import attitude_error, retract
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

from companion.skeleton.body import GRAVITY_M_S2, LinkInertia
from companion.skeleton.rotors import RotorGeometry

from .allocation import Allocator
from .controllers import ControlIntegrals, ImpedanceController, make_controller, weight_wrench
from .controllers.hybrid import ContactTarget
from .controllers.pspm import PspmModulator
from .estimators import X_BG, X_P, X_Q, GpsHealth, LinkEkf
from .estimators.correction_aid import CorrectionAid
from .estimators.ekf import attitude_variance
from .estimators.imu_health import ImuHealth
from .estimators.stale_rate import StaleGyroRate
from .events import StatusEvent
from .firmware_config import FirmwareConfig
from .fused import TAKEOFF_HEIGHT_M, FusedTicks
from .motor_failure import MotorFailureDetector
from .thrust_limit import ThrustLimit
from .wrench_guard import WrenchGuard

__all__ = ["CorrectionRejected", "FirmwareConfig", "LinkFirmware"]

log = logging.getLogger(__name__)

TAKEOFF_SPEED_M_S = 0.5  # armed faster than this: already in flight


class CorrectionRejected(ValueError):
    """A correction outside the configured bounds (counted and reported by the shell)."""


class LinkFirmware(FusedTicks):
    """One link's flight controller (see the module docstring for the event interface; the fused
    ticks, :class:`~.fused.FusedTicks`, run its common case in one kernel call)."""

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
        self.target: PoseTarget | None = None
        self._target_time_s = -math.inf
        self._hold: PoseTarget | None = None
        self.correction: Correction | None = None
        self._correction_time_s = -math.inf
        #: seq of the last correction applied and its latency (arrival minus the EKF time it was
        #: computed against) [us]: reported back in the link state
        self.correction_seq = 0
        self.correction_latency_us = 0
        #: (arrival time, latency) of the corrections [s] (a vehicle's flight log moves them to its
        #: file every second)
        self.latency_log: list[tuple[float, float]] = []
        self.time_s = 0.0
        self._zero = np.zeros(8)
        self._pending: list[tuple[str, tuple]] = []
        self.gps_health = GpsHealth(config.gps)
        #: while the GPS is in fault: the companion's corrected position fused into the EKF
        self.correction_aid = CorrectionAid(config.gps.aid_std_m, config.gps.aid_reset_s)
        #: the rotors' thrust limit: time at it, episodes (reported as events)
        self.thrust_limit = ThrustLimit(config.thrust_limit)
        #: a gyro or an accelerometer that repeats one sample in flight (stuck): not used while it
        #: does (:mod:`.estimators.imu_health`; armed only: at rest a noise-free simulated IMU
        #: repeats itself)
        self.imu_health = ImuHealth(self._stale_gyro_rate())
        #: a non-finite wrench from the controller: refused, the last finite commands held
        self.wrench_guard = WrenchGuard()
        #: rotors whose ESCs report them stopped while commanded (:meth:`on_esc_telemetry`)
        self.motor_failure = MotorFailureDetector()
        #: GPS health and thrust-limit transitions not yet reported by the shell (STATUSTEXT)
        self.events: list[StatusEvent] = []
        self._init_fused()
        self._make_controller()

    def _stale_gyro_rate(self) -> StaleGyroRate:
        """The stand-in of a stale gyro: this link's inertia, its ESCs' lag, the references' noise."""
        return StaleGyroRate(self.inertia.inertia_kgm2, self.config.observer.actuator_time_constant_s,
                             np.broadcast_to(attitude_variance(self.config.ekf), (3,)))

    def _make_controller(self) -> None:
        """The selected controller (:func:`~.controllers.make_controller`; the hybrid one with its
        observer and, at first, no contact) and PSPM's modulator (``pspm_mode = "on"``)."""
        cfg = self.config
        #: PSPM's modulator (``pspm_mode = "on"``) and the last operator set pose it modulated
        self.pspm = PspmModulator(cfg.pspm) if cfg.pspm_mode == "on" else None
        self.operator_target: PoseTarget | None = None
        self._controller = make_controller(cfg, self.inertia, self.pspm)

    @property
    def controller(self):
        """The pose controller the firmware runs (:class:`~.controllers.base.Controller`)."""
        return self._controller

    @property
    def observer(self):
        """The controller's momentum observer (the hybrid controller's), else ``None``."""
        return self._controller.observer

    @property
    def contact(self) -> ContactTarget | None:
        """The commanded contact of the hybrid controller (``None``: none, or another controller)."""
        return getattr(self._controller, "contact", None)

    @property
    def integrals(self):
        """The controller's integrals (eq. 1's: :class:`~.controllers.impedance.ControlIntegrals`)."""
        return getattr(self._controller, "integrals", None)

    # the land detector's state (:meth:`landed`), read-only
    @property
    def arm_height_m(self) -> float:
        """The control estimate's height when the link armed: where a take-off is measured from."""
        return self._arm_height_m

    @property
    def airborne(self) -> bool:
        """Whether the link has taken off since it armed."""
        return self._airborne

    @property
    def thrust_total_n(self) -> float:
        """The norm of the force the controller commanded at the last armed tick [N]."""
        return self._thrust_total_n

    def reconfigure(self, config: FirmwareConfig) -> None:
        """Apply a new configuration at once (parameter changes); the EKF keeps its state."""
        if config.allocation != self.config.allocation:
            old = self.allocator
            self.allocator = Allocator(old.geometry, config.allocation)
            if old.removed_rotor is not None and config.allocation.remove_failed_rotor:
                self.allocator.remove_rotor(old.removed_rotor, old.test_thrust_n)
        self.gps_health.config = config.gps
        self.thrust_limit.config = config.thrust_limit
        rebuild = (config.controller, config.se3_pid, config.hybrid, config.observer, config.pspm_mode, config.pspm) != (
            self.config.controller, self.config.se3_pid, self.config.hybrid, self.config.observer,
            self.config.pspm_mode, self.config.pspm)
        self.config = config
        if not self.imu_health.rate.running:
            self.imu_health.rate = self._stale_gyro_rate()
        if rebuild:
            self._make_controller()
        elif isinstance(self._controller, ImpedanceController) and self._controller.gains != config.gains:
            self._controller.gains = config.gains  # (eq. 1's integrals kept)

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
                self._fuse_attitude(args[0])
            elif kind == "baro":
                ekf.update_baro(args[0], ground_effect=self.in_ground_effect())
            else:
                ekf.update_mag(args[0])
        self._pending.clear()

    def _fuse_attitude(self, q_wxyz) -> None:
        """An attitude reference, or the attitude reset to it once the gate has rejected
        ``att_reset_rejections`` in a row (the estimate ran off: a stuck gyro, say)."""
        ekf = self.ekf
        if ekf.attitude_reset_due:
            jump = ekf.reset_attitude(q_wxyz)
            self.events.append(StatusEvent("reset", f"EKF attitude reset: jumped {math.degrees(jump):.0f} deg"))
        else:
            ekf.update_attitude(q_wxyz)
        self.imu_health.on_attitude_reference(q_wxyz)

    def _fuse_gps(self, pos_w_m, vel_w_m_s) -> None:
        """A GPS fix through the health checks (:mod:`.gps_health`): its position is fused
        only while the GPS is healthy and the fix is not stuck and passes the EKF's gate and the
        consistency test; in a fault it is only tested (the estimate dead-reckons). The velocity is
        fused (or, after ``vel_reset_rejections`` rejected in a row, the velocity reset to it),
        except a stuck fix's: nothing of it enters the EKF."""
        ekf, health, t = self.ekf, self.gps_health, self.time_s
        stuck = health.repeats(t, pos_w_m, vel_w_m_s, self.armed and self.airborne)
        consistent = stuck or health.consistent(t, pos_w_m, vel_w_m_s)  # (a stuck fix: not in the drift test)
        if stuck:
            accepted, why = False, "fix stuck, repeats itself"
        elif not consistent:
            accepted, why = False, f"drifts {health.drift_m_s:.1f} m/s from its velocity"
        elif health.fault:
            accepted, why = ekf.position_test_ratio(pos_w_m) <= 1.0, "position fix rejected"
        else:
            accepted, why = ekf.update_position(pos_w_m).accepted, "position fix rejected"
        was_fault = health.fault
        for ev in health.on_fix(t, accepted, self.correction_weight(t) > 0, why):
            if ev.kind == "reset":
                if stuck:  # never reset to a stuck fix (nor fuse its velocity, below)
                    continue
                jump = float(np.linalg.norm(np.asarray(pos_w_m) - ekf.p_w_m))
                ekf.reset_position(pos_w_m)
                ev = StatusEvent("reset", f"GPS reset: position jumped {jump:.1f} m")
            self.events.append(ev)
        if stuck:
            return
        if was_fault and not health.fault:  # recovered: this fix is fused again
            ekf.update_position(pos_w_m)
        if ekf.velocity_reset_due:
            jump = ekf.reset_velocity(vel_w_m_s)
            self.events.append(StatusEvent("reset", f"EKF velocity reset: jumped {jump:.1f} m/s"))
        else:
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
        over = [(name, norm, bound, unit) for name, norm, bound, unit in (
            ("dp", float(np.linalg.norm(correction.dp_w_m)), cfg.correction_max_dp_m, "m"),
            ("dv", float(np.linalg.norm(correction.dv_w_m_s)), cfg.correction_max_dv_m_s, "m/s"),
            ("dtheta", float(np.linalg.norm(correction.dtheta_w_rad)), cfg.correction_max_dtheta_rad, "rad"),
        ) if not norm <= bound]
        aid = self.correction_aid
        if over:
            name, norm, bound, unit = over[0]
            jump = None
            if all(np.all(np.isfinite(x)) for x in (correction.dp_w_m, correction.dv_w_m_s)) and \
                    all(o[0] != "dtheta" for o in over):
                # dead-reckoned past the bound in a GPS fault: reset to the chain's view once
                # refused for SKL_GPS_AID_RST (estimators.correction_aid)
                jump = aid.refused(correction, self.ekf, self.time_s, self.gps_health.fault, cfg.correction_stale_s)
            if jump is None:
                raise CorrectionRejected(f"correction {name} {norm:.3g} {unit} exceeds the bound {bound:g} {unit}")
            self.events.append(StatusEvent("reset", f"EKF reset to the chain: jumped {jump:.1f} m"))
        else:
            aid.accepted()
        # against the EKF as it now is and, in a GPS fault, fused into it (estimators.correction_aid)
        self.correction = aid.apply(correction, self.ekf, self.time_s, self.gps_health.fault)
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

    def gps_report(self, t_s: float) -> dict:
        """The GPS health's account at ``t_s`` and, under ``"chain"``, the correction aid's: resets
        to the chain's view and refused corrections that disagreed with their run."""
        return {**self.gps_health.report(t_s), "chain": self.correction_aid.report()}

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
        self._controller.contact = contact

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
        return self.observer.wrench_e, self._controller.contact_estimate(self.ekf.q_wxyz)

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
        self._controller.reset()
        self.allocator.reset()
        self.wrench_guard.passed(self._zero)  # (nothing from an earlier flight is held)
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
        self.imu_health.stop(self.time_s)  # (watched in flight only)
        self.motor_failure.reset()  # (PX4: a failed motor stays handled until disarmed)
        self.allocator.restore_rotors()

    def on_esc_telemetry(self, t_s: float, command_n, reported_n) -> None:
        """The ESCs' report of the tick at ``t_s`` (armed only): what each rotor runs at against its
        command [N]. A rotor found failed is reported and, with ``allocation.remove_failed_rotor``
        (SKL_CA_FAIL), flown without until it turns again (:meth:`.motor_failure.MotorFailureDetector.answer`).
        The shell feeds every tick while a rotor is out (:attr:`rotor_out`)."""
        if self.armed:
            self.events.extend(self.motor_failure.answer(t_s, command_n, reported_n, self.allocator,
                                                         self.config.allocation.remove_failed_rotor))

    @property
    def rotor_out(self) -> bool:
        """A rotor is left out of the allocation: the shell must feed :meth:`on_esc_telemetry` each tick."""
        return self.allocator.removed_rotor is not None

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
        imu = self.imu_health
        imu.sample(gyro_b_rad_s, accel_b_m_s2)
        command = self._tick_fused(t_s, dt, gyro_b_rad_s, accel_b_m_s2)  # the steps below in one kernel
        if command is not None:
            return command
        if imu.stale:  # in place of a stale gyro or accelerometer: what the commanded thrusts do
            wrench = self.allocator.mapping_matrix @ self.wrench_guard.command
            if imu.accel.stale:
                accel_b_m_s2 = wrench[:3] / self.inertia.mass_kg
            if imu.gyro.stale:  # (the model's rate, as the EKF takes a gyro's: with its bias)
                gyro_b_rad_s = imu.stale_rate(self.ekf.x[X_Q], wrench[3:], dt) + self.ekf.x[X_BG]
            self.ekf.predict_stale(gyro_b_rad_s, accel_b_m_s2, dt, imu.gyro.stale, imu.accel.stale)
        else:
            self.ekf.predict(gyro_b_rad_s, accel_b_m_s2, dt)
        self.time_s = t_s
        if self._pending:
            self._apply_pending()
        self.events.extend(self.gps_health.on_tick(t_s))
        if not self.armed:
            self.events.extend(self.thrust_limit.on_tick(t_s, dt, False))
            return self._zero
        p, v, q = self.control_estimate(t_s)
        if imu.gyro.stale:
            omega = imu.rate.rate_b_rad_s
        else:
            omega = np.asarray(gyro_b_rad_s, dtype=float) - self.ekf.x[X_BG]
        target = self._active_target(t_s, p)
        ctrl = self._controller
        held = self.integrals if imu.gyro.stale else None
        U = ctrl(p, v, q, omega, target, dt)  # eq. 1 (default), sec. 2.3.2, 2.3.3 or 2.3.4's slave law
        if isinstance(held, ControlIntegrals):
            # eq. 1's attitude integral holds while the gyro is stale: the damping then comes from a
            # model's rate, and the larger errors it may leave would wind the integral up, to swing
            # the link over once the gyro is back
            ctrl.integrals = ControlIntegrals(ctrl.integrals.pos, held.att)
        if not math.isfinite(float(np.sum(U))):
            return self._refuse_wrench(t_s)
        self._thrust_total_n = float(np.linalg.norm(U[:3]))  # the commanded force (rotors spin both ways)
        if not self._airborne and p[2] - self._arm_height_m > TAKEOFF_HEIGHT_M:
            self._airborne = True  # take-off detected: a disarm now needs the force value
        command = self.allocator.command(U, weight_wrench(self.inertia, q))  # at the limit, the weight kept
        self.events.extend(self.thrust_limit.on_tick(t_s, dt, self.allocator.saturated, self.allocator.scale))
        if ctrl.observer is not None:  # with the wrench the clipped commands produce
            ctrl.observe(v, q, omega, self.allocator.mapping_matrix @ command, dt)
        self.wrench_guard.passed(command)
        return command

    def _refuse_wrench(self, t_s: float) -> np.ndarray:
        """A tick whose wrench is not finite (:mod:`.wrench_guard`): the last finite commands held,
        the controller reset, the refusal counted and reported."""
        command, events = self.wrench_guard.refuse(t_s)
        self.events.extend(events)
        self._controller.reset()
        return command

    def watch_imu(self, t_s: float) -> None:
        """The newest tick's gyro and accelerometer samples to the stuck-sensor watch (armed
        only). The shell calls it on a fixed grid of simulated time, its log or stream rows: the
        compiled lockstep loop returns on them, so both paths see the same samples."""
        if self.armed:
            self.events.extend(self.imu_health.watch(t_s))

    def _tick_dt(self, t_s: float) -> float:
        """The step since the last tick; the nominal ``1 / rate_hz`` when not positive (the first
        tick, a repeated stamp). The lockstep loop's kernel steps its ticks the same way."""
        dt = t_s - self.time_s
        return 1.0 / self.config.rate_hz if dt <= 0.0 else dt

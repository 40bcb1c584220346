"""SITL scenario configuration: one validated TOML file per scenario (``configs/sitl/``).

A scenario composes the companion's schema (:class:`companion.config.CompanionSetup`: skeleton,
companion, zenoh, trajectory, motion), the vehicles' (:class:`link_firmware_sim.config.VehicleSetup`:
rotors, firmware, origin) and the simulator's sections below (duration, seed, start, sensors,
wind, sim, faults). :func:`load_scenario` reads a file through :mod:`companion.configfile`, so an unknown key, a wrong type or an invalid value is reported
as ``<file>: <section.key>: <reason>``. Every rate must be a whole divisor of the physics rate
(and the sensor rates of the firmware rate), else the file is rejected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Literal

import numpy as np

from companion.config import CompanionConfig, CompanionSetup, load_setup, project
from companion.configfile import require_nonnegative, require_positive
from link_firmware_sim.config import VehicleSetup
from link_firmware_sim.firmware_config import FirmwareConfig
from link_firmware_sim.estimators import (GpsHealthConfig, m8_ekf_config, outdoor_ekf_config, paper_ekf_config,
                                          rtk_ekf_config)
from link_firmware_sim.vehicle.failures import OK, SUPPORTED, TYPE_NAMES, UNIT_NAMES

from .cameras.config import CameraMount, MarkerMount
from .cameras.scene import SceneConfig
from .plant.schedule import rate_divisor
from .plant.sensors import PROFILES, BaroNoise, MagNoise, SensorSuite
from .plant.start import StartPose

__all__ = [
    "SensorConfig",
    "SitlCompanionConfig",
    "WindConfig",
    "SimConfig",
    "LinkRebootFault",
    "MavlinkWireFault",
    "GpsFault",
    "InjectFault",
    "FaultConfig",
    "Scenario",
    "load_scenario",
    "with_options",
]


#: The sensors a profile may leave out, and the model a ``[sensors.<name>]`` table then fits.
_OPTIONAL_SENSORS = {"baro": BaroNoise, "mag": MagNoise}


@dataclass(frozen=True)
class SensorConfig:
    """A named sensor profile with optional per-field overrides and the sensor rates.

    ``[sensors.imu]``, ``[sensors.gps]``, ``[sensors.attitude]``, ``[sensors.baro]``,
    ``[sensors.mag]`` override single fields of the profile's :class:`~sitl.plant.sensors.ImuNoise`,
    :class:`~sitl.plant.sensors.GpsNoise`, :class:`~sitl.plant.sensors.AttitudeRefNoise`,
    :class:`~sitl.plant.sensors.BaroNoise`, :class:`~sitl.plant.sensors.MagNoise`. A ``[sensors.baro]`` or
    ``[sensors.mag]`` table (even an empty one) on a profile without that sensor fits one (its
    defaults, overridden);
    a profile's own barometer or magnetometer is left out by choosing the profile without it
    (``m8`` for ``m8_baro_mag``). Barometer and magnetometer samples arrive at ``baro_rate_hz``
    and ``mag_rate_hz``.
    """

    profile: Literal["outdoor", "paper", "m8", "rtk", "m8_baro_mag", "ideal"] = "outdoor"
    gps_rate_hz: float = 10.0
    attitude_rate_hz: float = 50.0
    baro_rate_hz: float = 50.0
    mag_rate_hz: float = 50.0
    imu: dict[str, float] = field(default_factory=dict)
    gps: dict[str, float] = field(default_factory=dict)
    attitude: dict[str, float] = field(default_factory=dict)
    baro: dict[str, float] | None = None
    mag: dict[str, float] | None = None

    def __post_init__(self) -> None:
        base = PROFILES[self.profile]
        for section in ("imu", "gps", "attitude", "baro", "mag"):
            model = getattr(base, section)
            known = {f.name for f in fields(model if model is not None else _OPTIONAL_SENSORS[section])}
            for key in getattr(self, section) or {}:
                if key not in known:
                    raise ValueError(f"{section}: unknown field {key!r} (expected one of: {', '.join(sorted(known))})")
            try:
                self._section(section)
            except ValueError as exc:  # an invalid value: reported at sensors.<section>
                raise ValueError(f"{section}: {exc}") from None

    def _section(self, section: str):
        """The profile's model of ``section`` with this config's overrides (``None``: not fitted)."""
        model = getattr(PROFILES[self.profile], section)
        overrides = getattr(self, section)
        if model is None:
            return None if overrides is None else _OPTIONAL_SENSORS[section](**overrides)
        return replace(model, **(overrides or {}))

    def suite(self) -> SensorSuite:
        return SensorSuite(**{s: self._section(s) for s in ("imu", "gps", "attitude", "baro", "mag")})


@dataclass(frozen=True)
class WindConfig:
    """Steady wind plus gusts (first-order Gauss-Markov per world axis), drag at link centres."""

    mean_w_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_std_m_s: float = 0.0
    gust_time_constant_s: float = 2.0
    air_density_kg_m3: float = 1.225

    def __post_init__(self) -> None:
        require_nonnegative(self, "gust_std_m_s")
        require_positive(self, "gust_time_constant_s")


@dataclass(frozen=True)
class SimConfig:
    """Physics rate and the rate of the run's log (the companion's rates are in ``[companion]``)."""

    physics_rate_hz: float = 1000.0
    log_rate_hz: float = 50.0

    def __post_init__(self) -> None:
        rate_divisor(self.physics_rate_hz, self.log_rate_hz, "log_rate_hz")


@dataclass(frozen=True)
class LinkRebootFault:
    """``[faults.link]``: SIGKILL link ``kill``'s firmware process (1-based; 0: none) at
    ``kill_at_s``, as if its Pixhawk lost power, and power it on again ``restart_after_s`` of
    simulated time later (0: never). Meanwhile the physics runs on with that link's rotors stopped
    (the other links carry it on the cables). The new process is started at the kill and waits
    for the simulator, silent like PX4's SITL; at the restart the harness connects it, so the outage
    lasts ``restart_after_s`` unless the host took longer than that to start the process (then
    until it listens; ``rejoined_at_s`` in the metrics). It initialises its EKF in flight from GPS and the attitude reference, and is
    re-admitted and re-armed by the companion. Batch and fleet mode: in batch mode the firmware
    object is replaced at the restart and keeps the simulation clock (:meth:`sitl.runner.BatchRunner._link_reboot`)."""

    kill: int = 0
    kill_at_s: float = 0.0
    restart_after_s: float = 0.0

    def __post_init__(self) -> None:
        require_nonnegative(self, "kill", "kill_at_s", "restart_after_s")


@dataclass(frozen=True)
class MavlinkWireFault:
    """``[faults.mavlink]``: the wires between the vehicles and the companion(s) lose each
    datagram with probability ``loss`` and delay it by ``delay_ms`` plus a uniform jitter of up to
    ``jitter_ms`` (ms of simulated time, as a network would in flight; both ways; datagrams may then arrive out of
    order). ``links``: the affected links (1-based; empty: all). Fleet mode only: a proxy process
    (:mod:`sitl.fleet.wire`) sits on every affected wire and counts what it dropped."""

    loss: float = 0.0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    links: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss < 1.0:
            raise ValueError(f"loss must be in [0, 1), got {self.loss}")
        require_nonnegative(self, "delay_ms", "jitter_ms")
        if any(i < 1 for i in self.links):
            raise ValueError(f"links are 1-based, got {list(self.links)}")

    @property
    def active(self) -> bool:
        return self.loss > 0 or self.delay_ms > 0 or self.jitter_ms > 0


@dataclass(frozen=True)
class GpsFault:
    """``[faults.gps]``: glitches of link ``link``'s GPS position (1-based; 0: none), in the
    world frame (ENU, metres), batch and fleet mode:

    * a step: ``step_m`` added from ``step_at_s`` for ``step_duration_s`` (a multipath jump);
    * a ramp: an offset growing linearly from zero to ``ramp_m`` over ``ramp_duration_s`` from
      ``ramp_at_s``, held for ``ramp_hold_s``, then gone (a slow drift, spoofing-like);
    * an outage: no fix at all from ``outage_at_s`` for ``outage_s``.

    The GPS velocity is not glitched (a position-only fault, as multipath and spoofing of the
    position solution are)."""

    link: int = 0
    step_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    step_at_s: float = 0.0
    step_duration_s: float = 0.0
    ramp_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ramp_at_s: float = 0.0
    ramp_duration_s: float = 0.0
    ramp_hold_s: float = 0.0
    outage_at_s: float = 0.0
    outage_s: float = 0.0

    def __post_init__(self) -> None:
        require_nonnegative(self, "link", "step_at_s", "step_duration_s", "ramp_at_s", "ramp_duration_s",
                            "ramp_hold_s", "outage_at_s", "outage_s")
        if any(not math.isfinite(x) for x in (*self.step_m, *self.ramp_m)):
            raise ValueError("step_m and ramp_m must be finite")

    def offset_w_m(self, t_s: float) -> np.ndarray:
        """The glitch added to the position fix at ``t_s`` [m, ENU]."""
        out = np.zeros(3)
        if self.step_at_s <= t_s < self.step_at_s + self.step_duration_s:
            out += self.step_m
        end = self.ramp_at_s + self.ramp_duration_s
        if self.ramp_duration_s > 0 and self.ramp_at_s <= t_s < end + self.ramp_hold_s:
            out += np.asarray(self.ramp_m) * min((t_s - self.ramp_at_s) / self.ramp_duration_s, 1.0)
        return out

    def in_outage(self, t_s: float) -> bool:
        return self.outage_at_s <= t_s < self.outage_at_s + self.outage_s

    def apply(self, t_s: float, pos_w_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The fixes of every link after the glitches, and which links get a fix at ``t_s``."""
        has_fix = np.ones(len(pos_w_m), dtype=bool)
        if not self.link:
            return pos_w_m, has_fix
        pos = np.array(pos_w_m, dtype=float)
        pos[self.link - 1] += self.offset_w_m(t_s)
        has_fix[self.link - 1] = not self.in_outage(t_s)
        return pos, has_fix


@dataclass(frozen=True)
class InjectFault:
    """``[faults.inject]``: a failure injected into link ``link``'s vehicle (1-based; 0: none) at
    ``at_s`` and cleared ``duration_s`` later (0: never), as PX4's MAV_CMD_INJECT_FAILURE does
    (:mod:`link_firmware_sim.vehicle.failures`): ``unit`` ``gps`` (``type`` ``off``, ``stuck`` or
    ``wrong``), ``gyro`` or ``accel`` (``stuck``, ``garbage``), ``motor`` (``off``) or
    ``mavlink_signal`` (``off``: the link to the companion dead both ways), ``instance``
    as PX4 numbers them (0: every one; motors 1-8). Batch mode applies it through the same failure
    filter the vehicle runs; fleet mode sends the vehicle the command over its ground-station link,
    with SYS_FAILURE_EN set in its parameters."""

    link: int = 0
    unit: Literal["gps", "gyro", "accel", "motor", "mavlink_signal"] = "gps"
    type: Literal["off", "stuck", "garbage", "wrong"] = "off"
    instance: int = 0
    at_s: float = 0.0
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        require_nonnegative(self, "link", "instance", "at_s", "duration_s")
        most = 8 if self.unit == "motor" else 1  # an ODAR link's rotors; one GPS, gyro, accelerometer
        if self.instance > most:
            raise ValueError(f"instance {self.instance}: the {self.unit} instances are 1-{most} (0: all)")
        if self.type_id not in SUPPORTED[self.unit_id]:
            raise ValueError(f"type {self.type!r} is not a failure of the {self.unit} (it can be: "
                             f"{', '.join(TYPE_NAMES[t] for t in sorted(SUPPORTED[self.unit_id]) if t)})")

    @property
    def unit_id(self) -> int:
        """FAILURE_UNIT of MAVLink's common.xml."""
        return next(k for k, v in UNIT_NAMES.items() if v == self.unit)

    @property
    def type_id(self) -> int:
        """FAILURE_TYPE of MAVLink's common.xml."""
        return next(k for k, v in TYPE_NAMES.items() if v == self.type)

    def active(self, t_s: float) -> bool:
        """Whether the failure is in effect at ``t_s``."""
        return bool(self.link) and self.at_s <= t_s and (not self.duration_s or t_s < self.at_s + self.duration_s)

    def due(self, t_s: float, done: dict) -> int | None:
        """The FAILURE_TYPE to apply at ``t_s`` (the failure's, or FAILURE_TYPE_OK to clear it),
        or ``None`` when nothing changes; ``done`` records when each change was applied
        (``injected_at_s``, ``cleared_at_s``) and is updated."""
        on = self.active(t_s)
        if on == ("injected_at_s" in done and "cleared_at_s" not in done):
            return None
        done["injected_at_s" if on else "cleared_at_s"] = round(t_s, 3)
        return self.type_id if on else OK


@dataclass(frozen=True)
class FaultConfig:
    """Scripted faults (times in simulation seconds).

    ``kill_companion_group``: SIGKILL the companion of this group (1-based; 0: none) at
    ``kill_at_s``, as if its onboard computer lost power; ``restart_after_s`` later a new one
    starts (0: never). Needs ``companion.distributed``. Fleet mode only. The sub-sections:
    ``[faults.link]`` (:class:`LinkRebootFault`), ``[faults.mavlink]`` (:class:`MavlinkWireFault`),
    ``[faults.gps]`` (:class:`GpsFault`), ``[faults.inject]`` (:class:`InjectFault`).
    """

    kill_companion_group: int = 0
    kill_at_s: float = 0.0
    restart_after_s: float = 0.0
    link: LinkRebootFault = field(default_factory=LinkRebootFault)
    mavlink: MavlinkWireFault = field(default_factory=MavlinkWireFault)
    gps: GpsFault = field(default_factory=GpsFault)
    inject: InjectFault = field(default_factory=InjectFault)

    def __post_init__(self) -> None:
        require_nonnegative(self, "kill_companion_group", "kill_at_s", "restart_after_s")

    def check_links(self, n_links: int) -> None:
        """``ValueError`` for a fault on a link the skeleton does not have."""
        for where, i in (("faults.link.kill", self.link.kill), ("faults.gps.link", self.gps.link),
                         ("faults.inject.link", self.inject.link),
                         *(("faults.mavlink.links", i) for i in self.mavlink.links)):
            if i > n_links:
                raise ValueError(f"{where}: the skeleton has links 1..{n_links}, got {i}")

    @property
    def touches_gps(self) -> bool:
        """Whether a fault here acts on a link's GPS: a scripted glitch (``[faults.gps]``) or an
        injected GPS failure (``[faults.inject]`` on the gps unit); then ``metrics.json`` reports
        every link's firmware GPS health (``faults.gps``)."""
        return bool(self.gps.link) or (bool(self.inject.link) and self.inject.unit == "gps")

    @property
    def fleet_only(self) -> list[str]:
        """The sections set here that batch mode cannot play (no processes, no wires)."""
        out = []
        if self.kill_companion_group:
            out.append("faults.kill_companion_group")
        if self.mavlink.active:
            out.append("faults.mavlink")
        return out


@dataclass(frozen=True)
class SitlCompanionConfig(CompanionConfig):
    """A scenario's companion: as the daemon's (:class:`~companion.config.CompanionConfig`), but
    arming the simulated links unless the scenario says ``arm = false``: a simulated chain takes
    off by itself, a real one when its pilot arms it (the daemon's default)."""

    arm: bool = True


@dataclass(frozen=True)
class Scenario(CompanionSetup, VehicleSetup):
    """A SITL scenario: the companion's sections (:class:`~companion.config.CompanionSetup`), the
    vehicles' (:class:`~link_firmware_sim.config.VehicleSetup`) and the simulator's own: the run
    length and seed, the start pose, sensors, wind, physics rates and scripted faults. ``kind``
    names the scenario's kind (:mod:`sitl.scenarios`): a chain flight here, a subclass's own
    otherwise."""

    kind: Literal["chain"] = "chain"
    companion: SitlCompanionConfig = field(default_factory=SitlCompanionConfig)
    duration_s: float = 30.0
    seed: int = 0
    start: StartPose = field(default_factory=StartPose)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    wind: WindConfig = field(default_factory=WindConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    faults: FaultConfig = field(default_factory=FaultConfig)
    # [[cameras]] / [[markers]]: cameras rendered offscreen and ArUco markers (sitl.cameras.rig)
    cameras: tuple[CameraMount, ...] = ()
    markers: tuple[MarkerMount, ...] = ()
    # [scene]: the ground, the light and the clutter the cameras see (sitl.cameras.scene)
    scene: SceneConfig = field(default_factory=SceneConfig)

    def __post_init__(self) -> None:
        if not math.isfinite(self.duration_s):
            raise ValueError(f"duration_s must be a finite number of seconds, got {self.duration_s!r}")
        require_nonnegative(self, "seed")
        if not self.duration_s > self.flight_start_s:
            raise ValueError(f"duration_s must be longer than the take-off, which ends at {self.flight_start_s:g} s "
                             f"(trajectory.takeoff_start_s + takeoff_duration_s: the metrics window starts there), got "
                             f"{self.duration_s:g}")
        physics = self.sim.physics_rate_hz
        rate_divisor(physics, self.firmware.rate_hz, "firmware.rate_hz")
        rate_divisor(physics, self.companion.rate_hz, "companion.rate_hz")
        rate_divisor(self.firmware.rate_hz, self.sensors.gps_rate_hz, "sensors.gps_rate_hz")
        rate_divisor(self.firmware.rate_hz, self.sensors.attitude_rate_hz, "sensors.attitude_rate_hz")
        rate_divisor(self.firmware.rate_hz, self.sensors.baro_rate_hz, "sensors.baro_rate_hz")
        rate_divisor(self.firmware.rate_hz, self.sensors.mag_rate_hz, "sensors.mag_rate_hz")
        rate_divisor(self.firmware.rate_hz, self.companion.state_rate_hz, "companion.state_rate_hz")
        for i, cam in enumerate(self.cameras):
            rate_divisor(physics, cam.rate_hz, f"cameras[{i}].rate_hz")
        if len({c.name for c in self.cameras}) != len(self.cameras):
            raise ValueError("cameras: names must be unique")
        if len({m.id for m in self.markers}) != len(self.markers):
            raise ValueError("markers: ids must be unique")
        CompanionSetup.__post_init__(self)
        VehicleSetup.__post_init__(self)
        n_groups = len(self.companion.group_layout(self.skeleton.n_links))
        self.faults.check_links(self.skeleton.n_links)
        if self.faults.kill_companion_group:
            if not self.companion.distributed:
                raise ValueError("faults.kill_companion_group needs companion.distributed = true")
            if self.faults.kill_companion_group > n_groups:
                raise ValueError(f"faults.kill_companion_group: the config has groups 1..{n_groups}")

    def companion_setup(self) -> CompanionSetup:
        """The companion's part (what ``companion.toml`` of a fleet run holds)."""
        return self._part(CompanionSetup)

    def vehicle_setup(self) -> VehicleSetup:
        """The vehicles' part (what ``link.toml`` of a fleet run holds)."""
        return self._part(VehicleSetup)

    def _part(self, cls: type):
        """The ``cls`` part, its ``[companion]`` the daemon's config (``arm`` written out as the
        scenario has it, whatever the daemon's default)."""
        part = project(self, cls)
        if any(f.name == "companion" for f in fields(cls)):
            part = replace(part, companion=project(self.companion, CompanionConfig))
        return part


def with_options(scenario: Scenario, sckf: bool | None = None, selective_mapping: bool | None = None) -> Scenario:
    """``scenario`` with the command line's flight options where given (``None``: as it is):
    ``sckf`` turns the companion's corrections on or off (``companion.enabled``),
    ``selective_mapping`` the allocation's selective mapping (``firmware.allocation``)."""
    sc = scenario
    if selective_mapping is not None:
        fw = replace(sc.firmware, allocation=replace(sc.firmware.allocation, selective_mapping=selective_mapping))
        sc = replace(sc, firmware=fw)
    if sckf is not None:
        sc = replace(sc, companion=replace(sc.companion, enabled=sckf))
    return sc


def load_scenario(path: str | Path, schema: type[Scenario] = Scenario, **overrides) -> Scenario:
    """Read a scenario file as ``schema`` (a kind's subclass of :class:`Scenario`); ``overrides``
    replace top-level fields (e.g. ``duration_s``). The firmware gets its sensor profile's tuning
    where the file leaves the defaults (:func:`with_profile_tuning`), and the companion its sensor
    terms (:func:`with_rate_noise`)."""
    return with_rate_noise(with_profile_tuning(load_setup(schema, path, **overrides)))


#: the EKF tuning a sensor profile flies when the scenario leaves ``[firmware.ekf]`` at its default
#: (:func:`~link_firmware_sim.estimators.tunings.outdoor_ekf_config`, which the other profiles fly)
PROFILE_EKF_TUNINGS = {"m8": m8_ekf_config, "m8_baro_mag": m8_ekf_config, "rtk": rtk_ekf_config,
                       "paper": paper_ekf_config}

#: the GPS consistency test's threshold (SKL_GPS_DRIFT, ``[firmware.gps] drift_max_m_s``) a sensor profile
#: flies when the scenario leaves it at its default (0.5 m/s, which the others fly): above what the
#: profile's healthy receiver reaches. Measured on a hovering receiver's fixes (7 links, 5 seeds of
#: 600 s, 210000 tests of the default 2 s window): the m8 receiver's wandering biases exceed 0.5 m/s
#: in 0.9 % of tests (a false glitch every few seconds of a seven-link flight) and reach 0.85 m/s
#: at most; the paper profile's white 0.32 m/s velocity noise exceeds 1.0 m/s twice. A 1 m/s
#: drift is found in 1.5-1.7 s (m8) instead of about 1 s; on paper in 1-3.5 s, and 1.5 m/s in about 1 s.
PROFILE_GPS_DRIFT_MAX_M_S = {"m8": 0.9, "m8_baro_mag": 0.9, "paper": 1.0}

#: how many standard deviations of a receiver's own bias the firmware's correction bound covers
CORRECTION_BOUND_SIGMAS = 3.0


def with_profile_tuning(scenario: Scenario) -> Scenario:
    """``scenario`` with the firmware tuned for its receivers where it left the defaults:

    * the EKF tuning of its sensor profile (:data:`PROFILE_EKF_TUNINGS`) if ``[firmware.ekf]`` is
      the default (``outdoor``) tuning: that is tuned for ``outdoor``'s decimetre-level drift and
      degree-level attitude reference: with the ``m8`` receiver's metre-level biases it would claim
      about a hundredth of its position error (a barometer does not help: it is referenced to the
      EKF's height, bias and all), with the ``rtk`` receiver's centimetres ten to thirty times
      its error, and with the ``paper`` profile's white noise it rejects most attitude references
      and the chain falls over;
    * the GPS consistency test's threshold of its sensor profile (:data:`PROFILE_GPS_DRIFT_MAX_M_S`)
      if ``[firmware.gps] drift_max_m_s`` is the default: that suits ``outdoor``'s receiver, and
      noisier ones trip it in health (a false GPS glitch: their fixes left out for seconds);
    * the largest correction a link accepts (``correction_max_dp_m``, SKL_CORR_MAXP) at least
      :data:`CORRECTION_BOUND_SIGMAS` times the RMS of a receiver's own position bias (``m8`` and
      ``m8_baro_mag``: 5 m), if ``[firmware]`` left it at its default: a link's correction is its
      offset from where the chain puts it, the receiver's own bias among it, and one the bound
      refuses leaves the link flying on its own EKF, metres off its neighbours (with ``m8`` the
      default 2 m would refuse about one correction in ten of a three-link chain's).
    """
    firmware = scenario.firmware
    tuning = PROFILE_EKF_TUNINGS.get(scenario.sensors.profile)
    if tuning is not None and firmware.ekf == outdoor_ekf_config():
        firmware = replace(firmware, ekf=tuning())
    drift_max_m_s = PROFILE_GPS_DRIFT_MAX_M_S.get(scenario.sensors.profile)
    if drift_max_m_s is not None and firmware.gps.drift_max_m_s == GpsHealthConfig().drift_max_m_s:
        firmware = replace(firmware, gps=replace(firmware.gps, drift_max_m_s=drift_max_m_s))
    g = scenario.sensors.suite().gps
    own_bias_rms_m = math.sqrt(2.0 * g.bias_horizontal_std_m ** 2 + g.bias_vertical_std_m ** 2)
    bound = math.ceil(CORRECTION_BOUND_SIGMAS * own_bias_rms_m)
    default = FirmwareConfig().correction_max_dp_m
    if firmware.correction_max_dp_m == default and bound > default:
        firmware = replace(firmware, correction_max_dp_m=float(bound))
    return scenario if firmware is scenario.firmware else replace(scenario, firmware=firmware)


def with_rate_noise(scenario: Scenario) -> Scenario:
    """``scenario`` with the companion's sensor terms from its sensor models where unset:
    ``omega_std_rad_s`` its gyro's white noise, ``gnss_common_pos_var_m2`` its receivers' common
    mode (``m8``: 1.8 m / 2.7 m per axis; none in the other profiles) if the links' EKF reports a
    bias variance that holds it (``[firmware.ekf] gps_bias_var_m2``), else none."""
    comp, suite = scenario.companion, scenario.sensors.suite()
    if comp.omega_std_rad_s is None:
        comp = replace(comp, omega_std_rad_s=suite.imu.gyro_std_rad_s)
    if comp.gnss_common_pos_var_m2 is None:
        g = suite.gps
        common = (g.common_horizontal_std_m ** 2, g.common_vertical_std_m ** 2)
        reported = scenario.firmware.ekf.gps_bias_var_m2
        comp = replace(comp, gnss_common_pos_var_m2=common if all(r >= c for r, c in zip(reported, common)) else (0.0, 0.0))
    return scenario if comp is scenario.companion else replace(scenario, companion=comp)

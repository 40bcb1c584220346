"""SITL scenario configuration: one validated TOML file per scenario (``configs/sitl/``).

A scenario composes the companion's schema (:class:`companion.config.CompanionSetup`: skeleton,
companion, zenoh, trajectory, motion), the vehicles' (:class:`link_firmware_sim.config.VehicleSetup`:
rotors, firmware, origin) and the simulator's sections below (duration, seed, start, sensors,
wind, sim, faults). :func:`load_scenario` reads a file through :mod:`companion.configfile`, so an unknown key, a wrong type or an invalid value is reported
as ``<file>: <section.key>: <reason>``. Every rate must be a whole divisor of the physics rate
(and the sensor rates of the firmware rate), else the file is rejected.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Literal

from companion.config import CompanionSetup, load_setup, project
from companion.configfile import require_nonnegative, require_positive
from link_firmware_sim.config import VehicleSetup

from .bench.ekf_chain import rate_divisor
from .sensors import PROFILES, SensorSuite
from .skeleton import StartPose

__all__ = [
    "SensorConfig",
    "WindConfig",
    "SimConfig",
    "FaultConfig",
    "Scenario",
    "load_scenario",
]


@dataclass(frozen=True)
class SensorConfig:
    """A named sensor profile with optional per-field overrides and the sensor rates.

    ``[sensors.imu]``, ``[sensors.gps]``, ``[sensors.attitude]`` override single fields of the
    profile's :class:`~sitl.sensors.ImuNoise`, :class:`~sitl.sensors.GpsNoise`,
    :class:`~sitl.sensors.AttitudeRefNoise`.
    """

    profile: Literal["outdoor", "paper", "ideal"] = "outdoor"
    gps_rate_hz: float = 10.0
    attitude_rate_hz: float = 50.0
    imu: dict[str, float] = field(default_factory=dict)
    gps: dict[str, float] = field(default_factory=dict)
    attitude: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        base = PROFILES[self.profile]
        for section in ("imu", "gps", "attitude"):
            known = {f.name for f in fields(getattr(base, section))}
            for key in getattr(self, section):
                if key not in known:
                    raise ValueError(f"{section}: unknown field {key!r} (expected one of: {', '.join(sorted(known))})")

    def suite(self) -> SensorSuite:
        base = PROFILES[self.profile]
        return SensorSuite(
            imu=replace(base.imu, **self.imu),
            gps=replace(base.gps, **self.gps),
            attitude=replace(base.attitude, **self.attitude),
        )


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
class FaultConfig:
    """Scripted faults for fleet mode (times in simulation seconds).

    ``kill_companion_group``: SIGKILL the companion of this group (1-based; 0: none) at
    ``kill_at_s``, as if its onboard computer lost power; ``restart_after_s`` later a new one
    starts (0: never). Needs ``companion.distributed``.
    """

    kill_companion_group: int = 0
    kill_at_s: float = 0.0
    restart_after_s: float = 0.0

    def __post_init__(self) -> None:
        require_nonnegative(self, "kill_companion_group", "kill_at_s", "restart_after_s")


@dataclass(frozen=True)
class Scenario(CompanionSetup, VehicleSetup):
    """A SITL scenario: the companion's sections (:class:`~companion.config.CompanionSetup`), the
    vehicles' (:class:`~link_firmware_sim.config.VehicleSetup`) and the simulator's own: the run
    length and seed, the start pose, sensors, wind, physics rates and scripted faults."""

    duration_s: float = 30.0
    seed: int = 0
    start: StartPose = field(default_factory=StartPose)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    wind: WindConfig = field(default_factory=WindConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    faults: FaultConfig = field(default_factory=FaultConfig)

    def __post_init__(self) -> None:
        if not self.duration_s > self.flight_start_s:
            raise ValueError(f"duration_s must be longer than the take-off, which ends at {self.flight_start_s:g} s "
                             f"(the metrics window starts there), got {self.duration_s:g}")
        physics = self.sim.physics_rate_hz
        rate_divisor(physics, self.firmware.rate_hz, "firmware.rate_hz")
        rate_divisor(physics, self.companion.rate_hz, "companion.rate_hz")
        rate_divisor(self.firmware.rate_hz, self.sensors.gps_rate_hz, "sensors.gps_rate_hz")
        rate_divisor(self.firmware.rate_hz, self.sensors.attitude_rate_hz, "sensors.attitude_rate_hz")
        rate_divisor(self.firmware.rate_hz, self.companion.state_rate_hz, "companion.state_rate_hz")
        CompanionSetup.__post_init__(self)
        VehicleSetup.__post_init__(self)
        n_groups = len(self.companion.group_layout(self.skeleton.n_links))
        if self.faults.kill_companion_group:
            if not self.companion.distributed:
                raise ValueError("faults.kill_companion_group needs companion.distributed = true")
            if self.faults.kill_companion_group > n_groups:
                raise ValueError(f"faults.kill_companion_group: the config has groups 1..{n_groups}")

    def companion_setup(self) -> CompanionSetup:
        """The companion's part (what ``companion.toml`` of a fleet run holds)."""
        return project(self, CompanionSetup)

    def vehicle_setup(self) -> VehicleSetup:
        """The vehicles' part (what ``link.toml`` of a fleet run holds)."""
        return project(self, VehicleSetup)


def load_scenario(path: str | Path, **overrides) -> Scenario:
    """Read a scenario file; ``overrides`` replace top-level fields (e.g. ``duration_s``)."""
    return load_setup(Scenario, path, **overrides)

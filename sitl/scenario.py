"""SITL scenario configuration: one validated TOML file per scenario (``configs/sitl/``).

The schema is the dataclass tree below; :func:`load_scenario` reads a file through
:mod:`companion.configfile`, so an unknown key, a wrong type or an invalid value is reported
as ``<file>: <section.key>: <reason>``. Every rate must be a whole divisor of the physics rate
(and the sensor rates of the firmware rate), else the file is rejected.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Literal

from companion.configfile import ConfigError, build, load_toml, require_nonnegative, require_positive
from companion.geo import GeoOrigin
from companion.estimation.sckf import CAParams
from companion.estimation.semi import Groups, make_groups, validate_groups
from companion.fleetnet.config import PREFIX_RE, ZenohConfig
from companion.motion.inverse import InverseModel
from companion.motion.schedule import MotionConfig
from link_firmware_sim.firmware import FirmwareConfig
from sitl.bench.ekf_chain import rate_divisor

from .skeleton import SkeletonConfig, StartPose
from .rotor import RotorParams
from .sensors import PROFILES, SensorSuite
from .trajectory import TrajectoryConfig

__all__ = [
    "SensorConfig",
    "LinkEndpoint",
    "CompanionConfig",
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
class LinkEndpoint:
    """How the companion reaches one link's flight controller.

    ``url``: ``udpin://127.0.0.1:14540`` (SITL, PX4 habits), or on hardware a serial device by id
    with its baud rate, e.g. ``serial:///dev/serial/by-id/usb-ArduPilot_fmuv3_...-if00:921600``.
    """

    system_id: int
    url: str

    def __post_init__(self) -> None:
        if not 1 <= self.system_id <= 250:
            raise ValueError(f"system_id must be in 1..250, got {self.system_id}")
        scheme, sep, rest = self.url.partition("://")
        if not sep or scheme not in ("udpin", "udpout", "tcpin", "tcpout", "serial"):
            raise ValueError(f"url must be udpin://, udpout://, tcpin://, tcpout:// or serial://, got {self.url!r}")
        where, _, number = rest.split("?", 1)[0].rpartition(":")
        if scheme == "serial":
            if not where.startswith("/") or not number.isdigit() or int(number) <= 0:
                raise ValueError(f"url must be serial:///dev/...:BAUD, e.g. serial:///dev/ttyACM0:921600, got {self.url!r}")
        elif not number.isdigit() or not 0 <= int(number) <= 65535:
            raise ValueError(f"url must be {scheme}://HOST:PORT with a port in 0..65535, got {self.url!r}")


@dataclass(frozen=True)
class CompanionConfig:
    """The companion: SCKF step, its links and what it sends them.

    ``groups`` uses 1-based link numbers, e.g. ``[[1, 2], [3, 4, 5], [6, 7]]``; empty means
    one group of all links. ``links`` lists the flight controllers in chain order; empty means
    the SITL defaults (link ``i`` has system id ``i + 1`` on ``udpin://127.0.0.1:14540+i``: the
    simulated vehicles are on this machine, so nothing off it can reach the companion).
    ``mode``: ``dialect`` (SKELETON_LINK_STATE in, SKELETON_CORRECTION out) or ``standard``
    (stock PX4: ODOMETRY in, corrections as external-vision ODOMETRY in MAV_FRAME_LOCAL_FRD).
    ``targets``: ``trajectory`` forwards the scenario's ``[trajectory]`` as pose targets,
    ``none`` sends none. ``arm``: arm every link once all report a usable EKF.
    ``time_base``: ``flight_controller`` (the links' EKF stamps share one clock: SITL) or ``gps``
    (real Pixhawks: each link's boot clock is mapped to GPS time through its SYSTEM_TIME).
    ``distributed``: one companion per group (``python -m companion --config F --group G``),
    joined over Zenoh (``[zenoh]``) for the global step; otherwise one companion serves the
    whole chain and runs the global step in-process.
    """

    enabled: bool = True
    rate_hz: float = 20.0
    groups: tuple[tuple[int, ...], ...] = ()
    eps_m: float = 0.01
    alpha: float = 0.01
    max_iter: int = 20
    links: tuple[LinkEndpoint, ...] = ()
    mode: Literal["dialect", "standard"] = "dialect"
    targets: Literal["trajectory", "none"] = "trajectory"
    target_rate_hz: float = 50.0
    state_rate_hz: float = 50.0
    arm: bool = True
    health_period_s: float = 5.0
    distributed: bool = False
    time_base: Literal["flight_controller", "gps"] = "flight_controller"

    def __post_init__(self) -> None:
        CAParams(alpha=self.alpha, eps=self.eps_m, max_iter=self.max_iter)
        require_positive(self, "rate_hz", "target_rate_hz", "state_rate_hz", "health_period_s")
        ids = [link.system_id for link in self.links]
        if len(set(ids)) != len(ids):
            raise ValueError(f"links: system ids must be distinct, got {ids}")

    def endpoints(self, n_links: int, host: str = "127.0.0.1") -> tuple[LinkEndpoint, ...]:
        """The configured links, or the SITL defaults for ``n_links`` links."""
        if self.links:
            return self.links
        return tuple(LinkEndpoint(i + 1, f"udpin://{host}:{14540 + i}") for i in range(n_links))

    @property
    def params(self) -> CAParams:
        return CAParams(alpha=self.alpha, eps=self.eps_m, max_iter=self.max_iter)

    def group_layout(self, n_links: int) -> Groups:
        if not self.groups:
            return make_groups(n_links, n_links)
        return validate_groups([[i - 1 for i in g] for g in self.groups], n_links)


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
    physics_rate_hz: float = 1000.0
    log_rate_hz: float = 50.0
    target_rate_hz: float = 50.0

    def __post_init__(self) -> None:
        for name in ("log_rate_hz", "target_rate_hz"):
            rate_divisor(self.physics_rate_hz, getattr(self, name), name)


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
class Scenario:
    name: str
    description: str = ""
    duration_s: float = 30.0
    seed: int = 0
    skeleton: SkeletonConfig = field(default_factory=SkeletonConfig)
    start: StartPose = field(default_factory=StartPose)
    rotors: RotorParams = field(default_factory=RotorParams)
    firmware: FirmwareConfig = field(default_factory=FirmwareConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    companion: CompanionConfig = field(default_factory=CompanionConfig)
    wind: WindConfig = field(default_factory=WindConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    origin: GeoOrigin = field(default_factory=GeoOrigin)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    faults: FaultConfig = field(default_factory=FaultConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)

    def __post_init__(self) -> None:
        if not self.duration_s > self.flight_start_s:
            raise ValueError(f"duration_s must be longer than the take-off, which ends at {self.flight_start_s:g} s "
                             f"(the metrics window starts there), got {self.duration_s:g}")
        physics = self.sim.physics_rate_hz
        rate_divisor(physics, self.firmware.rate_hz, "firmware.rate_hz")
        rate_divisor(physics, self.companion.rate_hz, "companion.rate_hz")
        rate_divisor(self.firmware.rate_hz, self.sensors.gps_rate_hz, "sensors.gps_rate_hz")
        rate_divisor(self.firmware.rate_hz, self.sensors.attitude_rate_hz, "sensors.attitude_rate_hz")
        n_groups = len(self.companion.group_layout(self.skeleton.n_links))
        try:
            self.zenoh.check_groups(n_groups, 1e3 / self.companion.rate_hz)
        except ValueError as exc:
            raise ValueError(f"zenoh.{exc}") from None
        if self.trajectory.kind == "cpg":
            if not self.motion.commands:
                raise ValueError("trajectory.kind 'cpg' needs [[motion.commands]]")
            if self.motion.start_s < self.trajectory.takeoff_end_s:
                raise ValueError(f"motion.start_s ({self.motion.start_s:g}) must not be before the end of the "
                                 f"take-off ({self.trajectory.takeoff_end_s:g} s)")
            if self.trajectory.pitch_deg != 0.0:
                raise ValueError("trajectory.pitch_deg must be 0 with kind 'cpg' (the CPG body starts level)")
        if self.trajectory.kind == "rest" and self.companion.arm:
            raise ValueError("trajectory.kind 'rest' keeps the links on the ground: set companion.arm = false")
        if self.faults.kill_companion_group:
            if not self.companion.distributed:
                raise ValueError("faults.kill_companion_group needs companion.distributed = true")
            if self.faults.kill_companion_group > n_groups:
                raise ValueError(f"faults.kill_companion_group: the config has groups 1..{n_groups}")
        if not self.zenoh.prefix and not PREFIX_RE.match(self.name):
            raise ValueError(f"name {self.name!r} cannot be the Zenoh prefix: set zenoh.prefix")
        if self.companion.links and len(self.companion.links) != self.skeleton.n_links:
            raise ValueError(
                f"companion.links lists {len(self.companion.links)} links, the skeleton has {self.skeleton.n_links}"
            )
        if self.rotors.thrust_max_n != self.firmware.allocation.thrust_max_n:
            raise ValueError(
                f"firmware.allocation.thrust_max_n ({self.firmware.allocation.thrust_max_n}) must equal "
                f"rotors.thrust_max_n ({self.rotors.thrust_max_n})"
            )

    @property
    def zenoh_prefix(self) -> str:
        """Key-expression prefix of this fleet: ``zenoh.prefix``, else the scenario name."""
        return self.zenoh.prefix or self.name

    @property
    def flight_start_s(self) -> float:
        """Start of the metrics window: the end of the take-off."""
        return self.trajectory.takeoff_end_s


def load_scenario(path: str | Path, **overrides) -> Scenario:
    """Read a scenario file; ``overrides`` replace top-level fields (e.g. ``duration_s``).

    ``motion.model`` is resolved against the file's folder; with ``trajectory.kind = "cpg"``
    the model is loaded and must fit the skeleton."""
    data = load_toml(path)
    scenario = build(Scenario, data, file=str(path))
    model_path = Path(path).resolve().parent / scenario.motion.model
    scenario = replace(scenario, motion=replace(scenario.motion, model=str(model_path)))
    if scenario.trajectory.kind == "cpg":
        try:
            model = InverseModel.load(model_path)
        except (OSError, ValueError) as exc:
            raise ConfigError(str(path), "motion.model", f"cannot load the inverse CPG model: {exc}") from None
        try:
            model.steady.check_chain(scenario.skeleton.n_links, scenario.skeleton.link_length_m)
        except ValueError as exc:
            raise ConfigError(str(path), "motion.model", f"{model_path} {exc}") from None
    if overrides:
        try:
            scenario = replace(scenario, **overrides)
        except ValueError as exc:
            raise ConfigError(str(path), "(command line)", str(exc)) from None
    return scenario

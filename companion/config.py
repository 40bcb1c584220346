"""The companion's configuration file: its schema, validation and loader (pure; no simulator).

A companion config (``configs/hardware/*.toml``, or the ``companion.toml`` a SITL launch writes in
its run folder) has these sections, each a frozen dataclass validated by
:mod:`companion.configfile` (errors name the file, the key and the reason)::

    name, description            the chain's name (the default Zenoh prefix)
    [skeleton]                   the physical chain (companion.skeleton.body.SkeletonConfig)
    [companion]                  the daemon: SCKF rate and groups, its links, mode, targets, arming
    [[companion.links]]          one flight controller per link (system id and URL)
    [signing]                    MAVLink 2 signing: mode per link, key file (companion.mavlink.signing)
    [zenoh]                      the companions' network (distributed mode)
    [trajectory]                 the target source (take-off, hover, bending, CPG, a formation)
    [motion]                     the CPG motion commands (trajectory.kind = "cpg")
    [load]                       a slung load and the formation carrying it (trajectory.kind = "formation")

:class:`ChainSetup` holds what every layer shares (name, skeleton); :class:`CompanionSetup`
adds the companion's sections. The link firmware (:mod:`link_firmware_sim.config`) and a SITL
scenario (:mod:`sitl.scenario`) extend :class:`ChainSetup` with their own sections; a scenario
is both a companion setup and a vehicle setup, so its file holds every section and each
process validates what it runs.
"""

from __future__ import annotations

import math

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

from .configfile import ConfigError, build, load_toml, require_nonnegative, require_positive, with_settings
from .estimation.gate import CHI2_6_1E6, GateParams
from .estimation.sckf import CAParams
from .estimation.semi import Groups, make_groups, validate_groups
from .fleetnet.config import PREFIX_RE, ZenohConfig
from .load.config import LoadConfig
from .mavlink.signing import SigningConfig
from .mavlink.tlog import TLOG_KEEP, TLOG_MAX_MB
from .motion.inverse import InverseModel
from .motion.schedule import MotionConfig
from .plausibility import StampWindow
from .skeleton.body import SkeletonConfig
from .trajectory import TrajectoryConfig

__all__ = [
    "LinkEndpoint",
    "CompanionConfig",
    "ChainSetup",
    "CompanionSetup",
    "load_setup",
    "project",
    "SITL_STATE_PORT",
]

#: SITL defaults (PX4 habits): link ``i`` (0-based) streams to the companion on UDP 14540+i.
SITL_STATE_PORT = 14540


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
    (stock PX4: ODOMETRY in, corrections as external-vision ODOMETRY in MAV_FRAME_LOCAL_NED).
    ``targets``: ``trajectory`` forwards the ``[trajectory]`` as pose targets, ``none`` sends
    none. ``arm``: arm every link once all report a usable EKF; off unless asked for (a SITL
    scenario asks: :class:`sitl.scenario.Scenario`), and refused with a link on a serial port, a
    real flight controller, whose arming is the pilot's.
    ``time_base``: ``flight_controller`` (the links' EKF stamps share one clock: SITL) or ``gps``
    (real Pixhawks: each link's boot clock is mapped to GPS time through its SYSTEM_TIME).
    ``omega_std_rad_s``: the noise (std per axis) of the body rates the links report, the
    velocity input of eq. 3; the corrected covariance then includes its effect
    (:attr:`~companion.estimation.sckf.CAParams.omega_std_rad_s`). Unset: the rates count as exact
    (the paper's Alg. 1); a SITL scenario that leaves it unset takes its simulated gyro's white
    noise (the firmware reports the raw rate less its bias estimate). On hardware: the IMU's rate
    noise after the flight controller's gyro filter.
    ``gnss_common_pos_var_m2``: the variance (horizontal, vertical) of the GNSS position error
    every link shares (a standalone receiver's atmosphere, ephemeris and clock errors, the same
    for receivers metres apart), inside the position covariance the links report. No constraint
    sees a common offset: the step takes it out of every link's covariance before it starts (so
    the gate and the constraint application weigh only what differs between links) and puts it
    back into the corrected covariance. Unset: none (RTK, or no common error); a SITL scenario
    that leaves it unset takes its receiver model's common mode. A link whose reported position
    covariance is not larger than it keeps its covariance as it is.
    ``distributed``: one companion per group (``python -m companion --config F --group G``),
    joined over Zenoh (``[zenoh]``) for the global step; otherwise one companion serves the
    whole chain and runs the global step in-process. ``enabled = false`` runs no constraint
    application (the links fly on their EKFs; targets and arming go on).

    Plausibility (:mod:`companion.plausibility`, :mod:`companion.estimation.gate`): a link's state
    stamp must be newer than its last and at most ``clock_rate_max`` times the time elapsed since
    that one plus ``stamp_margin_s`` ahead of it (a SITL launch sets ``clock_rate_max`` from its
    pace); a link whose stream went silent for ``reboot_silence_s`` and comes back on a new clock
    (``reboot_frames`` consistent states) has rebooted. The joint gate cuts a joint whose NIS
    (6 dof) exceeds ``gate_threshold`` with ``gate_pos_m`` / ``gate_vel_m_s`` of slack.

    Carrying a link whose rotors are off (``trajectory.feedforward`` only): a link that has flown
    and is now silent for ``carry_silence_s`` (its newest state that far behind the chain's, on
    the time base: its Pixhawk lost power), disarmed (rebooted in flight), or armed again for
    less than ``carry_spinup_s`` (its ESCs restart from standstill: SITL's rotor model takes its
    ``restart_dwell_s`` 0.25 s plus the spin-up; counted from its first armed state after a
    disarmed one or after a silence of ``reboot_silence_s``) is carried by its neighbours: the
    targets' whole-chain feed-forward holds its rotor wrench at zero
    (:meth:`~companion.skeleton.dynamics.ChainModel.inverse_dynamics`, ``passive``). Each 50 ms
    of delay lets a dead link pull its neighbours further off (tens of degrees in ``three_link``).
    A link alive but unheard that long is carried too: its neighbours push up by its weight until
    it is heard again. ``carry_silence_max_s`` (unset: ``carry_silence_s``, a fixed silence) lets
    the silence grow with the loss of the link's state stream (:mod:`companion.engine.silence`:
    estimated from the gaps between its stamps, one state period more per lost state that a run
    must reach to happen by chance less than once in ten minutes), up to that value: fewer false
    carries on a lossy wire, a dead link carried later there.

    ``neighbour_cameras``: apply the camera measurements between neighbouring links that reach
    the companion (a camera on one link seeing its neighbour's marker:
    :mod:`companion.engine.neighbours`) in the step, before the constraint; ``false`` counts and
    drops them (the comparison flight). ``neighbour_mount_std_m`` / ``neighbour_mount_std_deg``:
    how well the cameras' and markers' mounts on their links are known (each position per axis,
    each orientation per axis); their share of a measurement's covariance
    (:func:`~companion.estimation.neighbour.mount_covariance`) is added to the PnP's.
    ``neighbour_hold_s``: each pair's newest accepted measurement goes into the later steps too
    while it is at most this old (its age at each step taken into account; 0: each once,
    :class:`~companion.engine.neighbours.NeighbourQueue`), so a camera slower than the step still
    corrects every step.

    Disk: each link's tlog is rotated when it reaches ``tlog_max_mb`` (0: never), keeping
    ``tlog_keep`` older files (:mod:`companion.mavlink.tlog`), so a daemon left running keeps at
    most ``(tlog_keep + 1) tlog_max_mb`` per link.
    """

    enabled: bool = True
    rate_hz: float = 20.0
    groups: tuple[tuple[int, ...], ...] = ()
    eps_m: float = 0.01
    alpha: float = 0.01
    max_iter: int = 20
    omega_std_rad_s: float | None = None
    gnss_common_pos_var_m2: tuple[float, float] | None = None
    links: tuple[LinkEndpoint, ...] = ()
    mode: Literal["dialect", "standard"] = "dialect"
    targets: Literal["trajectory", "none"] = "trajectory"
    target_rate_hz: float = 50.0
    state_rate_hz: float = 50.0
    arm: bool = False
    health_period_s: float = 5.0
    distributed: bool = False
    time_base: Literal["flight_controller", "gps"] = "flight_controller"
    stamp_margin_s: float = 0.25
    clock_rate_max: float = 1.1
    reboot_silence_s: float = 1.0
    reboot_frames: int = 10
    carry_silence_s: float = 0.06
    carry_silence_max_s: float | None = None
    carry_spinup_s: float = 0.35
    gate_threshold: float = CHI2_6_1E6
    gate_pos_m: float = 0.05
    gate_vel_m_s: float = 0.25
    tlog_max_mb: float = TLOG_MAX_MB
    tlog_keep: int = TLOG_KEEP
    neighbour_cameras: bool = True
    neighbour_mount_std_m: float = 0.002
    neighbour_mount_std_deg: float = 0.1
    neighbour_hold_s: float = 0.25

    def __post_init__(self) -> None:
        self.params
        require_positive(self, "rate_hz", "target_rate_hz", "state_rate_hz", "health_period_s", "stamp_margin_s",
                         "clock_rate_max", "reboot_silence_s", "reboot_frames", "carry_silence_s")
        require_nonnegative(self, "carry_spinup_s", "tlog_max_mb", "tlog_keep", "neighbour_mount_std_m",
                            "neighbour_mount_std_deg", "neighbour_hold_s")
        m = self.carry_silence_max_s
        if m is not None and not (math.isfinite(m) and m >= self.carry_silence_s):
            raise ValueError(f"carry_silence_max_s ({m}) must be finite and at least carry_silence_s "
                             f"({self.carry_silence_s})")
        self.gate
        c = self.gnss_common_pos_var_m2
        if c is not None and (len(c) != 2 or not all(math.isfinite(x) and x >= 0.0 for x in c)):
            raise ValueError(f"gnss_common_pos_var_m2 must be two finite non-negative variances (horizontal, vertical), "
                             f"got {c!r}")
        ids = [link.system_id for link in self.links]
        if len(set(ids)) != len(ids):
            raise ValueError(f"links: system ids must be distinct, got {ids}")
        serial = [link.url for link in self.links if link.url.startswith("serial://")]
        if self.arm and serial:
            raise ValueError(f"arm = true with flight controllers on serial links ({serial[0]}, ...): the companion would "
                             "arm real vehicles, and arm them again after the pilot disarms; set arm = false (the "
                             "pilot arms; arming from the companion is for SITL)")

    @property
    def carry_silence_cap_s(self) -> float:
        """The longest silence before a flown link is carried (``carry_silence_max_s``, or
        ``carry_silence_s`` when that is unset)."""
        return self.carry_silence_s if self.carry_silence_max_s is None else self.carry_silence_max_s

    def endpoints(self, n_links: int, host: str = "127.0.0.1") -> tuple[LinkEndpoint, ...]:
        """The configured links, or the SITL defaults for ``n_links`` links."""
        if self.links:
            return self.links
        return tuple(LinkEndpoint(i + 1, f"udpin://{host}:{SITL_STATE_PORT + i}") for i in range(n_links))

    @property
    def params(self) -> CAParams:
        return CAParams(alpha=self.alpha, eps=self.eps_m, max_iter=self.max_iter,
                        omega_std_rad_s=self.omega_std_rad_s or 0.0)

    @property
    def gate(self) -> GateParams:
        return GateParams(self.gate_threshold, self.gate_pos_m, self.gate_vel_m_s)

    @property
    def stamp_window(self) -> StampWindow:
        return StampWindow(self.stamp_margin_s, self.clock_rate_max, self.reboot_silence_s, self.reboot_frames)

    def group_layout(self, n_links: int) -> Groups:
        if not self.groups:
            return make_groups(n_links, n_links)
        return validate_groups([[i - 1 for i in g] for g in self.groups], n_links)


@dataclass(frozen=True)
class ChainSetup:
    """What every layer's configuration shares: the chain's name, its physical skeleton and how
    its MAVLink links are signed."""

    name: str
    description: str = ""
    skeleton: SkeletonConfig = field(default_factory=SkeletonConfig)
    signing: SigningConfig = field(default_factory=SigningConfig)


@dataclass(frozen=True)
class CompanionSetup(ChainSetup):
    """The companion's whole configuration file (see the module docstring)."""

    companion: CompanionConfig = field(default_factory=CompanionConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    #: ``[load]``: the slung load the vehicles carry in formation (``trajectory.kind = "formation"``)
    load: LoadConfig | None = None

    def __post_init__(self) -> None:
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
        if self.trajectory.kind == "formation" and self.load is None:
            raise ValueError("trajectory.kind 'formation' needs a [load] table (the load and its [load.formation])")
        if self.load is not None:
            if self.trajectory.kind != "formation":
                raise ValueError(f"trajectory.kind must be 'formation' with a [load] table (the vehicles carry the "
                                 f"load in formation), got {self.trajectory.kind!r}")
            if self.load.formation.n_vehicles != self.skeleton.n_links:
                raise ValueError(f"load.formation.n_vehicles ({self.load.formation.n_vehicles}) must equal "
                                 f"skeleton.n_links ({self.skeleton.n_links}): one vehicle per cable")
            if self.companion.enabled:
                raise ValueError("companion.enabled must be false with trajectory.kind 'formation': the vehicles "
                                 "are not joined, the chain's constraint (SCKF) does not hold between them")
            if self.companion.distributed:
                raise ValueError("companion.distributed must be false with a [load] table: one companion takes "
                                 "every carrying vehicle's state for the load filter")
        if self.trajectory.kind == "rest" and self.companion.arm:
            raise ValueError("trajectory.kind 'rest' keeps the links on the ground: set companion.arm = false")
        if not self.zenoh.prefix and not PREFIX_RE.match(self.name):
            raise ValueError(f"name {self.name!r} cannot be the Zenoh prefix: set zenoh.prefix")
        if self.companion.links and len(self.companion.links) != self.skeleton.n_links:
            raise ValueError(
                f"companion.links lists {len(self.companion.links)} links, the skeleton has {self.skeleton.n_links}"
            )

    @property
    def zenoh_prefix(self) -> str:
        """Key-expression prefix of this fleet: ``zenoh.prefix``, else the name."""
        return self.zenoh.prefix or self.name

    @property
    def flight_start_s(self) -> float:
        """End of the take-off (trajectory time): where flight metrics start."""
        return self.trajectory.takeoff_end_s


def project(setup, cls: type):
    """The ``cls`` part of ``setup`` (an instance of a subclass of ``cls``, e.g. a scenario's
    companion setup): the same field values, validated by ``cls`` alone."""
    return cls(**{f.name: getattr(setup, f.name) for f in fields(cls) if f.init})


def load_setup(cls: type, path: str | Path, settings: Mapping[str, Any] | None = None, **overrides):
    """Read the config file at ``path`` as ``cls`` (a :class:`ChainSetup` subclass).

    ``settings``: dotted keys set in the file's tables before it is validated
    (:func:`~companion.configfile.with_settings`: ``{"firmware.ekf.gate_sigma": 4.0}``), checked
    as if the file held them. ``overrides`` replace top-level fields (e.g. ``duration_s``). Relative paths of
    ``signing.key_file``, ``zenoh.users_file``, ``zenoh.tls.certs_dir`` and a ``[motion]`` section's
    ``model`` are resolved against the file's folder; with ``trajectory.kind = "cpg"`` the model
    is loaded and must fit the skeleton. Raises :class:`~companion.configfile.ConfigError`.
    """
    data = load_toml(path)
    if settings:
        data = with_settings(data, settings, str(path))
    setup = build(cls, data, file=str(path))
    if setup.signing.key_file:
        key_path = Path(path).resolve().parent / Path(setup.signing.key_file).expanduser()
        setup = replace(setup, signing=replace(setup.signing, key_file=str(key_path)))
    zenoh_cfg = getattr(setup, "zenoh", None)
    if zenoh_cfg is not None and (zenoh_cfg.users_file or zenoh_cfg.tls.certs_dir):
        setup = replace(setup, zenoh=zenoh_cfg.resolved(Path(path).resolve().parent))
    motion = getattr(setup, "motion", None)
    if motion is not None:
        model_path = Path(path).resolve().parent / motion.model
        setup = replace(setup, motion=replace(motion, model=str(model_path)))
        if setup.trajectory.kind == "cpg":
            try:
                model = InverseModel.load(model_path)
            except (OSError, ValueError) as exc:
                raise ConfigError(str(path), "motion.model", f"cannot load the inverse CPG model: {exc}") from None
            try:
                if model.steady is None:
                    raise ValueError("is not a flying chain's model (it records no expected physics)")
                model.steady.check_chain(setup.skeleton.n_links, setup.skeleton.link_length_m)
            except ValueError as exc:
                raise ConfigError(str(path), "motion.model", f"{model_path} {exc}") from None
    if overrides:
        try:
            setup = replace(setup, **overrides)
        except ValueError as exc:
            raise ConfigError(str(path), "(command line)", str(exc)) from None
    return setup

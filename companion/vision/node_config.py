"""Configuration of the vision consumer, ``python -m companion.vision --config FILE``.

No OpenCV and no Zenoh here: the file loads and is validated on any install. One TOML file::

    name = "down_camera"
    source = "zenoh"            # or "video"

    [zenoh]                     # source = "zenoh": frames on <prefix>/camera/<vehicle>/image
    prefix = "three_link_camera"
    connect = ["tcp/127.0.0.1:7450"]   # the publisher's endpoint (the SITL harness writes this file)
    fleet = "companion.toml"    # a secured fleet: the config whose [zenoh] table has its credentials,
    group = 2                   # and the group (1-based) whose credentials this consumer presents

    [video]                     # source = "video": a cv2.VideoCapture on this computer
    device = 0                  # /dev/video0; or url = "clip.mp4" / "rtsp://..." (not both)
    camera = "down"
    vehicle = 2                 # 1-based, as in the Zenoh keys
    width_px = 640
    height_px = 480
    fovy_deg = 60.0             # or the calibration: fx_px, fy_px, cx_px, cy_px
    dist_coeffs = [-0.05, 0.01, 0.0, 0.0]

    [pipeline]                  # companion.vision.config.PipelineConfig
    marker_length_m = 0.5
    ids = [7]

    [[neighbours]]              # a chain camera seeing its neighbour's marker (source = "zenoh")
    camera = "tip2"             # the camera's name in the frames' headers
    observer = 2                # the 1-based link that carries it
    observed = 3                # the neighbouring link that carries the marker
    marker_id = 12
    camera_pos_b_m = [0.45, 0.0, 0.05]        # the camera on the observer, body frame
    camera_q_bc_wxyz = [0.5, -0.5, 0.5, -0.5] # camera to body
    marker_pos_b_m = [-0.45, 0.0, 0.06]       # the marker on the observed link
    marker_q_bm_wxyz = [1.0, 0.0, 0.0, 0.0]   # marker to body

    [load]                      # a slung load's marker seen by its carrying vehicles' cameras
    marker_id = 7
    marker_pos_b_m = [0.0, 0.0, 0.102]        # the marker on the load, load frame
    marker_q_bm_wxyz = [1.0, 0.0, 0.0, 0.0]   # marker to load

    [[load.cameras]]
    camera = "cam1"
    vehicle = 1                 # the 1-based vehicle that carries it (its cable)
    camera_pos_b_m = [0.15, 0.0, -0.05]
    camera_q_bc_wxyz = [0.5, -0.5, 0.5, -0.5]

Each pose of a ``[[neighbours]]`` marker in that camera's frames goes out, with its covariance
and the two mounts, as a :class:`~companion.messages.NeighbourPose` on
``<prefix>/link/<observer>/neighbour`` for the companion that steps both links. Each pose of the
``[load]`` marker in a ``[[load.cameras]]`` camera's frames goes out as the slung-load report's
eq. 4 measurement (:class:`~companion.load.model.LoadObservation`: the vehicle's position in the
load frame and the load's attitude in the vehicle's, with their covariance) on
``<prefix>/vehicle/<vehicle>/load`` for the carrying companion's load filter. The frames' capture
times must be on the observing vehicle's flight-controller clock, as the SITL harness stamps them.

Every key is checked (unknown keys, types, ranges: :mod:`companion.configfile`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from companion.configfile import ConfigError, build, load_toml, require_nonnegative
from companion.fleetnet.codec import MAX_MOUNT_OFFSET_M
from companion.fleetnet.config import PREFIX_RE, load_zenoh_table
from companion.fleetnet.credentials import ZenohSetting, group_credentials

from .config import PipelineConfig
from .geometry import CameraIntrinsics

__all__ = ["ZenohCameraSource", "VideoCaptureSource", "NeighbourCamera", "LoadCamera", "LoadMarker", "VisionNodeSetup", "fleet_credentials", "load_vision_setup"]

_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")
_SECURE_TRANSPORTS = ("tls/", "quic/")
_NAME_RE = re.compile(r"[A-Za-z0-9_]{1,64}")


@dataclass(frozen=True)
class ZenohCameraSource:
    """Frames from Zenoh, ``<prefix>/camera/*/image``: a peer session that connects to ``connect``
    and/or listens on ``listen``, multicast scouting off unless enabled.
    ``vehicles``: 1-based vehicles whose frames are processed (empty: every vehicle's).
    ``runtime_threads``: Zenoh worker threads per runtime pool (``ZENOH_RUNTIME``, unless set).

    A secured fleet (its ``[zenoh]`` table has ``users_file``, ``[zenoh.tls]`` or
    ``access_control``): ``fleet`` names that config file (a companion's or a scenario; relative
    to this file's folder) and ``group`` the 1-based group whose credentials the session presents
    (the group of the computer it runs on), as that group's companion does: its user and password,
    its TLS certificate; the endpoints are then ``tls/`` (or ``quic/``) when the fleet's are, else
    ``tcp/`` (or ``udp/``). Without ``fleet`` the session has no credentials, over tcp or udp.
    """

    prefix: str = ""
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = False
    vehicles: tuple[int, ...] = ()
    runtime_threads: int = 1
    fleet: str = ""
    group: int = 0

    def __post_init__(self) -> None:
        if self.prefix and not PREFIX_RE.match(self.prefix):
            raise ValueError(f"prefix {self.prefix!r}: letters, digits, '_' and '-' in '/'-separated chunks")
        for key in ("connect", "listen"):
            for ep in getattr(self, key):
                m = _ENDPOINT_RE.match(ep)
                if not m or not 0 < int(m.group(3)) <= 65535:
                    raise ValueError(f"{key}: {ep!r} is not a Zenoh endpoint like tcp/127.0.0.1:7450 "
                                     "(tcp, udp, tls or quic; port 1..65535)")
                if ep.startswith(_SECURE_TRANSPORTS) and not self.fleet:
                    raise ValueError(f"{key}: {ep!r}: tls/ and quic/ need the fleet's credentials (fleet, group)")
        if self.fleet and not 1 <= self.group <= 0xFFFF:
            raise ValueError(f"group: with fleet, the 1-based group whose credentials the consumer presents, "
                             f"got {self.group}")
        if self.group and not self.fleet:
            raise ValueError("group: needs fleet, the config that holds the group's credentials")
        if any(v < 1 or v > 0xFFFF for v in self.vehicles):
            raise ValueError(f"vehicles: 1-based vehicle numbers, got {list(self.vehicles)}")
        if not 0 <= self.runtime_threads <= 64:
            raise ValueError(f"runtime_threads must be in 0..64, got {self.runtime_threads}")

    def runtime_env(self) -> str | None:
        if not self.runtime_threads:
            return None
        return "(" + ", ".join(f"{p}: (worker_threads: {self.runtime_threads})" for p in ("app", "acc", "tx", "rx", "net")) + ")"


@dataclass(frozen=True)
class VideoCaptureSource:
    """Frames from ``cv2.VideoCapture``: ``device`` (a camera index, /dev/video<N>) or ``url`` (a
    video file, relative to the config file's folder, or a stream URL), not both.

    The frames are attributed to ``camera`` on 1-based ``vehicle``. ``width_px`` x ``height_px``
    is the calibrated image size (asked of a device; a frame of another size is rejected and
    counted); the intrinsics come from the calibration (``fx_px``, ``fy_px``, ``cx_px``, ``cy_px``)
    or, without one, from the vertical field of view ``fovy_deg``; ``dist_coeffs`` as OpenCV's.
    ``fps``: the rate asked of a device (0: its default). ``max_frames``: stop after that many
    frames (0: at the end of the stream, or SIGTERM). Time stamps: a device's frames are stamped
    with this computer's monotonic clock when read; a file's or URL's with their position in the
    stream (``CAP_PROP_POS_MSEC``)."""

    device: int = -1
    url: str = ""
    camera: str = "cam0"
    vehicle: int = 1
    width_px: int = 640
    height_px: int = 480
    fovy_deg: float = 0.0
    fx_px: float = 0.0
    fy_px: float = 0.0
    cx_px: float = 0.0
    cy_px: float = 0.0
    dist_coeffs: tuple[float, ...] = ()
    fps: float = 0.0
    max_frames: int = 0

    def __post_init__(self) -> None:
        if not _NAME_RE.fullmatch(self.camera):
            raise ValueError(f"camera {self.camera!r}: 1-64 letters, digits or '_'")
        if not 1 <= self.vehicle <= 0xFFFF:
            raise ValueError(f"vehicle: 1-based, 1..65535, got {self.vehicle}")
        if not (0 < self.width_px <= 4096 and 0 < self.height_px <= 4096):
            raise ValueError(f"width_px and height_px must be in 1..4096, got {self.width_px} x {self.height_px}")
        require_nonnegative(self, "fovy_deg", "fx_px", "fy_px", "fps", "max_frames")
        if self.device < -1:
            raise ValueError(f"device: a camera index >= 0 (or -1 with url), got {self.device}")
        if self.fovy_deg and self.fx_px:
            raise ValueError("fovy_deg: give the calibration (fx_px, fy_px, cx_px, cy_px) or the field of view, not both")
        if self.fovy_deg or self.fx_px:
            self.intrinsics()

    def check_source(self) -> None:
        """``ValueError`` unless exactly one of ``device`` / ``url`` and the intrinsics are given."""
        if (self.device >= 0) == bool(self.url):
            raise ValueError("device: name a camera index (device) or a file / URL (url), exactly one")
        if not (self.fovy_deg or self.fx_px):
            raise ValueError("fx_px: the intrinsics are needed: fx_px, fy_px, cx_px, cy_px (calibration) or fovy_deg")

    def intrinsics(self) -> CameraIntrinsics:
        if self.fovy_deg:
            if not self.fovy_deg < 180:
                raise ValueError(f"fovy_deg must be in (0, 180), got {self.fovy_deg}")
            return CameraIntrinsics.from_fov(self.width_px, self.height_px, self.fovy_deg, self.dist_coeffs)
        return CameraIntrinsics(self.width_px, self.height_px, self.fx_px, self.fy_px, self.cx_px, self.cy_px,
                                self.dist_coeffs)


@dataclass(frozen=True)
class NeighbourCamera:
    """A camera (``camera``) on 1-based chain link ``observer`` that may see the marker
    ``marker_id`` on the neighbouring link ``observed``; the camera's mount on the observer
    (``camera_pos_b_m``, ``camera_q_bc_wxyz``: camera to body) and the marker's on the observed
    link (``marker_pos_b_m``, ``marker_q_bm_wxyz``: marker to body), body frames, metres."""

    camera: str
    observer: int
    observed: int
    marker_id: int
    camera_pos_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    camera_q_bc_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    marker_pos_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    marker_q_bm_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not _NAME_RE.fullmatch(self.camera):
            raise ValueError(f"camera {self.camera!r}: 1-64 letters, digits or '_'")
        if not 1 <= self.observer <= 0xFFFF:
            raise ValueError(f"observer: a 1-based link, got {self.observer}")
        if abs(self.observed - self.observer) != 1:
            raise ValueError(f"observed: a neighbour of link {self.observer} ({self.observer - 1} or "
                             f"{self.observer + 1}), got {self.observed}")
        if self.marker_id < 0:
            raise ValueError(f"marker_id must be >= 0, got {self.marker_id}")
        _check_mount(self, "camera_pos_b_m", "camera_q_bc_wxyz")
        _check_mount(self, "marker_pos_b_m", "marker_q_bm_wxyz")


def _check_mount(obj, pos_name: str, q_name: str) -> None:
    """``ValueError`` unless ``obj``'s mount (position ``pos_name`` within
    :data:`~companion.fleetnet.codec.MAX_MOUNT_OFFSET_M` of its body's centre, rotation ``q_name`` a
    unit quaternion) is finite and sane."""
    v = getattr(obj, pos_name)
    if not all(math.isfinite(x) for x in v) or math.hypot(*v) > MAX_MOUNT_OFFSET_M:
        raise ValueError(f"{pos_name}: finite and within {MAX_MOUNT_OFFSET_M:g} m of the body's centre, got {list(v)}")
    q = getattr(obj, q_name)
    if not all(math.isfinite(x) for x in q) or abs(math.hypot(*q) - 1.0) > 1e-3:
        raise ValueError(f"{q_name}: a unit quaternion (w, x, y, z), got {list(q)}")


@dataclass(frozen=True)
class LoadCamera:
    """A camera (``camera``) on 1-based carrying ``vehicle`` (the vehicle on cable ``vehicle``)
    that may see the slung load's marker; its mount (``camera_pos_b_m``, ``camera_q_bc_wxyz``:
    camera to body), body frame, metres."""

    camera: str
    vehicle: int
    camera_pos_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    camera_q_bc_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not _NAME_RE.fullmatch(self.camera):
            raise ValueError(f"camera {self.camera!r}: 1-64 letters, digits or '_'")
        if not 1 <= self.vehicle <= 0xFFFF:
            raise ValueError(f"vehicle: a 1-based vehicle, got {self.vehicle}")
        _check_mount(self, "camera_pos_b_m", "camera_q_bc_wxyz")


@dataclass(frozen=True)
class LoadMarker:
    """The slung load's marker ``marker_id``, where it sits on the load (``marker_pos_b_m``,
    ``marker_q_bm_wxyz``: marker to load, load frame) and the carrying vehicles' cameras that may
    see it (``[[load.cameras]]``)."""

    marker_id: int
    marker_pos_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    marker_q_bm_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    cameras: tuple[LoadCamera, ...] = ()

    def __post_init__(self) -> None:
        if self.marker_id < 0:
            raise ValueError(f"marker_id must be >= 0, got {self.marker_id}")
        _check_mount(self, "marker_pos_b_m", "marker_q_bm_wxyz")
        if not self.cameras:
            raise ValueError("cameras: at least one carrying vehicle's camera")
        names = [c.camera for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"cameras: each camera once, got {names}")


@dataclass(frozen=True)
class VisionNodeSetup:
    """The consumer's whole config (module docstring). ``idle_timeout_s``: stop when no frame has
    arrived for that long (0: never; the SITL stops the consumer with SIGTERM). ``neighbours``:
    the chain cameras whose neighbour markers go out as neighbour poses."""

    name: str = "vision"
    source: Literal["zenoh", "video"] = "zenoh"
    zenoh: ZenohCameraSource = field(default_factory=ZenohCameraSource)
    video: VideoCaptureSource = field(default_factory=VideoCaptureSource)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    idle_timeout_s: float = 0.0
    neighbours: tuple[NeighbourCamera, ...] = ()
    load: LoadMarker | None = None

    def __post_init__(self) -> None:
        if not _NAME_RE.fullmatch(self.name):
            raise ValueError(f"name {self.name!r}: 1-64 letters, digits or '_'")
        require_nonnegative(self, "idle_timeout_s")
        if self.source == "zenoh":
            if not self.zenoh.prefix:
                raise ValueError("zenoh: prefix (the fleet's key prefix) is needed with source = 'zenoh'")
            if not (self.zenoh.connect or self.zenoh.listen or self.zenoh.multicast_scouting):
                raise ValueError("zenoh: name the publisher's endpoint (connect), one to listen on (listen), "
                                 "or enable multicast_scouting")
        else:
            try:
                self.video.check_source()
            except ValueError as exc:
                raise ValueError(f"video: {exc}") from None
            for key in ("neighbours", "load"):
                if getattr(self, key):
                    raise ValueError(f"{key}: need source = 'zenoh' (the measurements go out on its session, and a "
                                     "device's frames are stamped on this computer's clock, not the vehicles')")
        pairs = [(n.camera, n.marker_id) for n in self.neighbours]
        if len(set(pairs)) != len(pairs):
            raise ValueError(f"neighbours: each (camera, marker_id) once, got {pairs}")


def fleet_credentials(src: ZenohCameraSource, file: str = "<config>") -> list[ZenohSetting]:
    """The Zenoh settings of ``src.group``'s credentials in the fleet config ``src.fleet`` (empty
    without one): :func:`~companion.fleetnet.credentials.group_credentials`, its files checked.
    :class:`~companion.configfile.ConfigError` names ``file``'s key (the fleet config missing, a
    group it does not have, an endpoint whose transport is not the fleet's) or the fleet config's
    own (``zenoh.users_file``, ``zenoh.tls.certs_dir``, ...)."""
    if not src.fleet:
        return []
    if not Path(src.fleet).is_file():
        raise ConfigError(file, "zenoh.fleet", f"no such file: {src.fleet} (the fleet's config: its [zenoh] table "
                                               "holds the credentials)")
    fleet = load_zenoh_table(src.fleet)
    n_groups = len(fleet.endpoints) or src.group
    if src.group > n_groups:
        raise ConfigError(file, "zenoh.group", f"{src.fleet} has {n_groups} groups (zenoh.endpoints), not {src.group}")
    for key in ("connect", "listen"):
        for ep in getattr(src, key):
            if ep.startswith(_SECURE_TRANSPORTS) != fleet.tls.configured:
                raise ConfigError(file, f"zenoh.{key}", f"{ep!r}: " + (
                    f"the fleet ({src.fleet}) uses TLS: use tls/ or quic/ endpoints" if fleet.tls.configured
                    else f"tls/ and quic/ need [zenoh.tls] in the fleet's config ({src.fleet})"))
    return group_credentials(fleet, src.group - 1, n_groups, src.fleet)


def load_vision_setup(path: str | Path) -> VisionNodeSetup:
    """Read a consumer config (:class:`~companion.configfile.ConfigError` naming the key). A
    relative ``video.url`` that is no URL and a relative ``zenoh.fleet`` are resolved against the
    file's folder; the fleet's credentials are checked (:func:`fleet_credentials`)."""
    setup = build(VisionNodeSetup, load_toml(path), file=str(path))
    folder = Path(path).resolve().parent
    url = setup.video.url
    if url and "://" not in url and not Path(url).expanduser().is_absolute():
        setup = replace(setup, video=replace(setup.video, url=str(folder / url)))
    if setup.zenoh.fleet:
        fleet = str(folder / Path(setup.zenoh.fleet).expanduser())
        setup = replace(setup, zenoh=replace(setup.zenoh, fleet=fleet))
        if setup.source == "zenoh":
            fleet_credentials(setup.zenoh, str(path))
    return setup

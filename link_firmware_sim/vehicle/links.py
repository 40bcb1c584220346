"""The vehicle's links: which ports it opens (:class:`VehiclePorts`, PX4 SITL's by default), each
open MAVLink link with its streams and trust (:class:`Endpoint`), what each side acts on, and a
STATUSTEXT to one link.

* simulator: ``tcpin://127.0.0.1:4560+i`` (PX4's simulator MAVLink API, lockstep: HIL_SENSOR,
  HIL_GPS and SKELETON_AHRS_REFERENCE in, HIL_ACTUATOR_CONTROLS out), or the same-host link
  ``unixin:///PATH`` (:mod:`.simlink`); never signed: it is the physics;
* onboard (companion): ``udpout://127.0.0.1:14540+i`` from local port 14580+i;
* GCS: ``udpout://127.0.0.1:14550`` from local port 18570+i.

Only the message types of :data:`MAVLINK_ACCEPT` are acted on; everything else is counted
(:class:`~companion.mavlink.port.MavlinkPort`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from companion.mavlink.dialect import load_dialect
from companion.mavlink.port import MavlinkPort
from companion.mavlink.signing import UNSIGNED_ALLOWED, SigningConfig
from companion.mavlink.tlog import TlogWriter

from .streams.schedule import Stream

__all__ = ["HIL_ACCEPT", "MAVLINK_ACCEPT", "LINK_NAMES", "VehiclePorts", "Endpoint", "open_endpoints", "statustext"]

D = load_dialect()

#: what the vehicle takes from the simulator link
HIL_ACCEPT = frozenset({"HIL_SENSOR", "HIL_GPS", "SKELETON_AHRS_REFERENCE"})
#: what it acts on from the onboard and GCS links
MAVLINK_ACCEPT = frozenset({
    "HEARTBEAT", "PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET", "COMMAND_LONG", "COMMAND_INT",
    "SET_POSITION_TARGET_LOCAL_NED", "SET_ATTITUDE_TARGET", "SKELETON_TARGET_FEEDFORWARD", "SKELETON_CORRECTION",
    "ODOMETRY", "VISION_POSITION_ESTIMATE", "SET_GPS_GLOBAL_ORIGIN", "SETUP_SIGNING", "FILE_TRANSFER_PROTOCOL",
})
#: the MAVLink links by link id (0, 1): their names in ``[signing]`` and in the tlogs' names
LINK_NAMES = ("onboard", "gcs")


@dataclass(frozen=True)
class VehiclePorts:
    sim: str
    onboard: str
    gcs: str | None

    @classmethod
    def px4_sitl(cls, instance: int, host: str = "127.0.0.1") -> VehiclePorts:
        return cls(
            sim=f"tcpin://{host}:{4560 + instance}",
            onboard=f"udpout://{host}:{14540 + instance}?bind={14580 + instance}",
            gcs=f"udpout://{host}:14550?bind={18570 + instance}",
        )

    @classmethod
    def for_instance(cls, instance: int, sim: str | None = None, onboard: str | None = None,
                     gcs: str | None = None) -> VehiclePorts:
        """PX4 SITL's ports of ``instance`` where a URL is not given; ``gcs="none"``: no GCS link."""
        defaults = cls.px4_sitl(instance)
        return cls(sim=sim or defaults.sim, onboard=onboard or defaults.onboard,
                   gcs=defaults.gcs if gcs is None else (None if gcs == "none" else gcs))


@dataclass
class Endpoint:
    """One MAVLink link of the vehicle: its port, its name (``onboard`` or ``gcs``), whether
    SETUP_SIGNING is accepted on it, and its telemetry streams by message id."""

    port: MavlinkPort
    name: str = "onboard"
    trusted: bool = False
    streams: dict[int, Stream] = field(default_factory=dict)


def open_endpoints(ports: VehiclePorts, system_id: int, signing: SigningConfig, key: bytes | None,
                   out_dir: Path | None) -> list[Endpoint]:
    """The onboard and (when it has a URL) GCS links, each signed as ``signing`` says for it and
    with its own tlog in ``out_dir`` (``link<sysid>.tlog``, ``link<sysid>_gcs.tlog``: each link has
    its own sequence numbers). A port that cannot open closes the ones opened before it."""
    endpoints: list[Endpoint] = []
    for link_id, (name, url) in enumerate(zip(LINK_NAMES, (ports.onboard, ports.gcs))):
        if not url:
            continue
        trusted = name in signing.trusted
        suffix = "" if name == "onboard" else f"_{name}"
        tlog = TlogWriter(out_dir / f"link{system_id}{suffix}.tlog") if out_dir is not None else None
        allowed = UNSIGNED_ALLOWED | ({"SETUP_SIGNING"} if trusted else set())
        try:
            port = MavlinkPort(url, system_id, accept=MAVLINK_ACCEPT, tlog=tlog, signing=signing.link_mode(name),
                               key=key, link_id=link_id, unsigned_allowed=allowed)
        except Exception:
            for ep in endpoints:
                ep.port.close()
            raise
        endpoints.append(Endpoint(port, name, trusted))
    return endpoints


def statustext(ep: Endpoint, severity: int, text: str) -> None:
    """A STATUSTEXT to one link (at most 50 characters, as PX4 sends them)."""
    ep.port.send(D.MAVLink_statustext_message(severity, text[:50].encode()))

"""SET_GPS_GLOBAL_ORIGIN: the shared local origin of every link's local frame, answered with
GPS_GLOBAL_ORIGIN, refused while armed (the frame would jump) and persisted with the parameters.
As on PX4 the origin is not a parameter: a degE7 latitude needs more bits than a float carries."""

from __future__ import annotations

import logging

from companion.mavlink.dialect import load_dialect

from ..geo import GeoOrigin
from .links import Endpoint, statustext
from .streams.position import gps_global_origin

__all__ = ["on_set_origin"]

log = logging.getLogger(__name__)
D = load_dialect()


def on_set_origin(v, ep: Endpoint, msg) -> None:
    """SET_GPS_GLOBAL_ORIGIN ``msg`` to vehicle ``v`` from link ``ep``."""
    if msg.target_system not in (0, v.system_id):
        return
    if v.fw.armed:
        statustext(ep, D.MAV_SEVERITY_WARNING, "Origin not changed: armed")
    else:
        try:
            origin = GeoOrigin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        except ValueError as exc:
            statustext(ep, D.MAV_SEVERITY_WARNING, f"Origin refused: {exc}")
        else:
            v.params.set_origin(origin)
            v.origin = origin
            v.home.clear()  # (held in the old origin's frame)
            log.info("link %d: origin set to %.7f, %.7f, %.2f m", v.system_id, origin.lat_deg, origin.lon_deg,
                     origin.alt_m)
    ep.port.send(gps_global_origin(v))

"""The home position, kept as PX4 keeps it: set from the position estimate once the EKF runs
(disarmed), set again at arming on the ground (not in the air, and not over a home set at a given
place by MAV_CMD_DO_SET_HOME), or set by MAV_CMD_DO_SET_HOME; reported as HOME_POSITION (on
request, in both links' streams, and to every link when it changes).

The home is held in the local frame (ENU, m) with its heading; its WGS84 form is the shared
origin's (:class:`~link_firmware_sim.geo.GeoOrigin`), so a new origin (only while disarmed)
clears it and the next estimate sets it again.

MAV_CMD_DO_SET_HOME (param1 1: the current position and heading; 0: the given place, param5-7
latitude [deg], longitude [deg], altitude [m, AMSL], or COMMAND_INT's x, y [degE7] and z in
MAV_FRAME_GLOBAL or MAV_FRAME_GLOBAL_INT, with param4 the heading [deg], NaN for the vehicle's) is
acknowledged: ACCEPTED; TEMPORARILY_REJECTED for the current position before the EKF runs;
DENIED, with a STATUSTEXT saying why, for a latitude or longitude out of range or a home more than
:data:`MAX_HOME_DISTANCE_M` from the origin, horizontally or vertically (the local plane's error
grows with the square of the distance); UNSUPPORTED for another frame. A number that is not
finite where one is needed makes the command a bad message (counted, not acted on), as for every
command.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from companion.mavlink.codec import MessageError
from companion.mavlink.dialect import load_dialect
from companion.mavlink.standard import heading_ned

from .links import Endpoint, statustext
from .streams.position import home_position

__all__ = ["HomePosition", "Home", "MAX_HOME_DISTANCE_M", "on_set_home"]

log = logging.getLogger(__name__)
D = load_dialect()

#: the farthest a home may be from the shared origin, horizontally and vertically [m]
MAX_HOME_DISTANCE_M = 1000.0
#: a link armed this far above its home [m] is in the air (re-armed in flight): the home stays
IN_AIR_ABOVE_HOME_M = 1.0
_GLOBAL_FRAMES = (D.MAV_FRAME_GLOBAL, D.MAV_FRAME_GLOBAL_INT)


@dataclass(frozen=True)
class HomePosition:
    """A home: where (local ENU [m]), the heading (NED yaw [rad], clockwise from north), when it
    was set (flight-controller time [us]) and whether it was given (a place sent with
    MAV_CMD_DO_SET_HOME: arming keeps it)."""

    p_w_m: np.ndarray
    heading_ned_rad: float
    time_us: int
    given: bool = False


class Home:
    """The vehicle's home (:attr:`position`; ``None`` until set) and the rules that set it."""

    def __init__(self):
        self.position: HomePosition | None = None

    def set(self, v, p_w_m, heading_ned_rad: float, why: str, given: bool = False) -> None:
        """Home at ``p_w_m`` (local ENU) with ``heading_ned_rad`` (``given``: a place sent to it),
        sent to every link of vehicle ``v``."""
        self.position = HomePosition(np.array(p_w_m, dtype=float), float(heading_ned_rad), v.fc_time_us, given)
        lat, lon, alt = v.origin.to_geodetic(self.position.p_w_m)
        log.info("link %d at %.2f s: home set (%s): %.7f, %.7f, %.2f m", v.system_id, v.fc_time_s, why, lat, lon, alt)
        msg = home_position(v)
        for ep in v.endpoints:
            ep.port.send(msg)

    def set_here(self, v, why: str) -> bool:
        """Home where vehicle ``v``'s estimate puts it now, with its heading; ``False`` before the
        EKF runs."""
        if not v.fw.initialized:
            return False
        p, _, q = v.streams.estimate()
        self.set(v, p, heading_ned(q), why)
        return True

    def on_tick(self, v) -> None:
        """The first home, once the EKF runs on the ground (disarmed), as PX4 sets it."""
        if self.position is None and not v.fw.armed and v.fw.initialized:
            self.set_here(v, "first estimate")

    def on_armed(self, v) -> None:
        """Home again at arming, where the flight starts; kept when it was given (DO_SET_HOME at a
        place) or when the link armed in the air (re-armed while falling, or carried by its
        neighbours :data:`IN_AIR_ABOVE_HOME_M` above its home): PX4 sets no home in the air."""
        home = self.position
        if home is not None and (home.given or not v.fw.landed(v.fc_time_s)
                                 or v.streams.estimate()[0][2] - home.p_w_m[2] > IN_AIR_ABOVE_HOME_M):
            return
        self.set_here(v, "armed")

    def clear(self) -> None:
        """No home (the origin changed): the next estimate on the ground sets it."""
        self.position = None


def _finite(value: float, what: str) -> float:
    if not math.isfinite(value):
        raise MessageError(f"DO_SET_HOME {what}: not finite ({value!r})")
    return value


def on_set_home(v, ep: Endpoint, msg, ack) -> None:
    """MAV_CMD_DO_SET_HOME ``msg`` (COMMAND_LONG or COMMAND_INT) to vehicle ``v`` from link
    ``ep``, acknowledged with ``ack(ep, msg, result)`` (module docstring)."""
    if _finite(msg.param1, "param1") >= 0.5:  # here, with the vehicle's heading (param4 unused, as PX4)
        ok = v.home.set_here(v, "DO_SET_HOME")
        ack(ep, msg, D.MAV_RESULT_ACCEPTED if ok else D.MAV_RESULT_TEMPORARILY_REJECTED)
        return
    yaw_deg = msg.param4
    if math.isinf(yaw_deg):
        raise MessageError(f"DO_SET_HOME param4: not finite ({yaw_deg!r})")
    heading = None if math.isnan(yaw_deg) else math.radians(yaw_deg)
    if msg.get_type() == "COMMAND_INT":
        if msg.frame not in _GLOBAL_FRAMES:
            statustext(ep, D.MAV_SEVERITY_WARNING, f"Home refused: frame {msg.frame} (use GLOBAL)")
            ack(ep, msg, D.MAV_RESULT_UNSUPPORTED)
            return
        lat, lon, alt = msg.x * 1e-7, msg.y * 1e-7, _finite(msg.z, "z")
    else:
        lat, lon, alt = _finite(msg.param5, "param5"), _finite(msg.param6, "param6"), _finite(msg.param7, "param7")
    reason = None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        reason = f"Home refused: lat/lon {lat:.3f}, {lon:.3f}"
    else:
        p = v.origin.to_enu(lat, lon, alt)
        far = max(math.hypot(p[0], p[1]), abs(p[2]))
        if not far <= MAX_HOME_DISTANCE_M:
            reason = f"Home refused: {far:.0f} m from origin"
    if reason is not None:
        log.warning("link %d: %s", v.system_id, reason)
        statustext(ep, D.MAV_SEVERITY_WARNING, reason)
        ack(ep, msg, D.MAV_RESULT_DENIED)
        return
    if heading is None:  # (the vehicle's, or north before the EKF runs)
        heading = heading_ned(v.streams.estimate()[2]) if v.fw.initialized else 0.0
    v.home.set(v, p, heading, "DO_SET_HOME", given=True)
    ack(ep, msg, D.MAV_RESULT_ACCEPTED)

"""The pose estimate in standard messages (local NED, body FRD, WGS84): ATTITUDE,
LOCAL_POSITION_NED, GLOBAL_POSITION_INT, the shared origin, GPS_GLOBAL_ORIGIN, and the home,
HOME_POSITION (:mod:`..home`). The pose messages carry the control estimate (the EKF's output with
the companion's correction)."""

from __future__ import annotations

import math

from companion.mavlink.dialect import load_dialect
from companion.mavlink.frames import enu_ned, flu_frd, quat_enu_flu_to_ned_frd
from companion.mavlink.standard import euler_zyx, heading_ned

__all__ = ["attitude", "local_position_ned", "global_position_int", "gps_global_origin", "home_position"]

D = load_dialect()


def attitude(v):
    _, _, q = v.streams.estimate()
    roll, pitch, yaw = euler_zyx(quat_enu_flu_to_ned_frd(q))
    w = flu_frd(v.streams.report().omega_b_rad_s)
    return D.MAVLink_attitude_message(v.time_boot_ms, roll, pitch, yaw, *w.tolist())


def local_position_ned(v):
    p, vel, _ = v.streams.estimate()
    return D.MAVLink_local_position_ned_message(v.time_boot_ms, *enu_ned(p).tolist(), *enu_ned(vel).tolist())


def global_position_int(v):
    p, vel, q = v.streams.estimate()
    lat, lon, alt = v.origin.to_geodetic(p)
    vn, ve, vd = enu_ned(vel).tolist()
    hdg = int(round((math.degrees(heading_ned(q)) % 360.0) * 100))
    return D.MAVLink_global_position_int_message(
        v.time_boot_ms, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
        int(round(p[2] * 1000)), int(round(vn * 100)), int(round(ve * 100)), int(round(vd * 100)), hdg,
    )


def gps_global_origin(v):
    o = v.origin
    return D.MAVLink_gps_global_origin_message(int(round(o.lat_deg * 1e7)), int(round(o.lon_deg * 1e7)),
                                               int(round(o.alt_m * 1e3)), v.fc_time_us)


def home_position(v):
    """HOME_POSITION of vehicle ``v`` (``None`` while it has no home): WGS84 and local NED, and the
    heading as a rotation about the down axis (``q``), as PX4 reports it."""
    home = v.home.position
    if home is None:
        return None
    lat, lon, alt = v.origin.to_geodetic(home.p_w_m)
    x, y, z = enu_ned(home.p_w_m).tolist()
    half = 0.5 * home.heading_ned_rad
    return D.MAVLink_home_position_message(int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1e3)),
                                           x, y, z, [math.cos(half), 0.0, 0.0, math.sin(half)], 0.0, 0.0, 0.0,
                                           v.fc_time_us)

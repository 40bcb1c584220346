"""Geodetic origin of the local frames (pure: no MAVLink, no I/O)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["EARTH_RADIUS_M", "GeoOrigin"]

EARTH_RADIUS_M = 6_371_000.0


@dataclass(frozen=True)
class GeoOrigin:
    """WGS84 point at the origin of the local ENU / NED frames.

    Local tangent plane on a spherical earth: centimetre-exact over the few hundred metres of a
    flight. All links, the simulator and the companions must share one origin.
    """

    lat_deg: float = 47.397742
    lon_deg: float = 8.545594
    alt_m: float = 488.0

    def __post_init__(self) -> None:
        if not -89.0 <= self.lat_deg <= 89.0:
            raise ValueError(f"lat_deg must be within +-89 deg, got {self.lat_deg}")
        if not -180.0 <= self.lon_deg <= 180.0:
            raise ValueError(f"lon_deg must be within +-180 deg, got {self.lon_deg}")

    def to_geodetic(self, p_enu_m: np.ndarray) -> tuple[float, float, float]:
        east, north, up = (float(x) for x in p_enu_m)
        lat = self.lat_deg + math.degrees(north / EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))))
        return lat, lon, self.alt_m + up

    def to_enu(self, lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
        north = math.radians(lat_deg - self.lat_deg) * EARTH_RADIUS_M
        east = math.radians(lon_deg - self.lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))
        return np.array([east, north, alt_m - self.alt_m])



"""Geodetic origin of the local frames, the earth's magnetic field and the standard atmosphere
(pure: no MAVLink, no I/O)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "EARTH_RADIUS_M",
    "GeoOrigin",
    "MAG_FIELD_NED_GAUSS",
    "MAG_DECLINATION_RAD",
    "ISA_SEA_LEVEL_HPA",
    "pressure_hpa_at",
    "pressure_altitude_m",
]

EARTH_RADIUS_M = 6_371_000.0
#: Earth magnetic field of the simulated world (NED, gauss; mid-latitude: 0.21 G horizontal,
#: 63 deg inclination): what the simulated magnetometers measure and the firmware's declination.
MAG_FIELD_NED_GAUSS = np.array([0.21, 0.01, 0.42])
#: Its declination (east of true north) [rad]: PX4's EKF2_MAG_DECL for this world, 2.7 deg.
MAG_DECLINATION_RAD = math.atan2(float(MAG_FIELD_NED_GAUSS[1]), float(MAG_FIELD_NED_GAUSS[0]))
#: ICAO standard atmosphere: sea-level pressure [hPa] and the troposphere's pressure-altitude law
#: ``p = p0 (1 - 2.25577e-5 h)^5.25588`` (h [m]), as barometer drivers convert (PX4, ArduPilot).
ISA_SEA_LEVEL_HPA = 1013.25
_ISA_K = 2.25577e-5
_ISA_EXP = 5.25588


def pressure_hpa_at(altitude_m: float) -> float:
    """Static pressure [hPa] of the standard atmosphere at ``altitude_m`` (above mean sea level)."""
    return ISA_SEA_LEVEL_HPA * (1.0 - _ISA_K * altitude_m) ** _ISA_EXP


def pressure_altitude_m(pressure_hpa: float) -> float:
    """Pressure altitude [m] of ``pressure_hpa`` in the standard atmosphere (inverse of
    :func:`pressure_hpa_at`)."""
    return (1.0 - (pressure_hpa / ISA_SEA_LEVEL_HPA) ** (1.0 / _ISA_EXP)) / _ISA_K


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



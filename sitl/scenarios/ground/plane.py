"""The ground plane of a ground robot: tilted ``incline_deg`` about the world y axis, uphill along
+x; its unit normal, uphill and lateral vectors (world frame) and the map of world points to its
in-plane coordinates."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["PlaneFrame"]


class PlaneFrame:
    """The plane's frame (module docstring)."""

    def __init__(self, incline_deg: float):
        a = math.radians(incline_deg)
        self.incline_deg = float(incline_deg)
        self.normal = np.array([-math.sin(a), 0.0, math.cos(a)])
        self.uphill = np.array([math.cos(a), 0.0, math.sin(a)])
        self.lateral = np.array([0.0, 1.0, 0.0])

    def mjcf_euler(self) -> str:
        """The plane's (and a body lying on it, pointing uphill) MJCF ``euler`` [deg]."""
        return f"0 {-self.incline_deg:.9g} 0"

    def above(self, height_m: float) -> np.ndarray:
        """The point ``height_m`` above the world origin along the normal."""
        return height_m * self.normal

    def in_plane(self, p_w: np.ndarray) -> np.ndarray:
        """World points (..., 3) in the plane's coordinates (..., 2): uphill, lateral."""
        p = np.asarray(p_w, dtype=float)
        return np.stack((p @ self.uphill, p @ self.lateral), axis=-1)

    def heading(self, axis_w: np.ndarray) -> float:
        """The heading [rad] in the plane of a world direction (0: uphill)."""
        return math.atan2(float(axis_w @ self.lateral), float(axis_w @ self.uphill))

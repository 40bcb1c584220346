"""Light and sensor response over a flight: the sun behind passing clouds, and a camera's
vignetting, gain drift and tone curve (numpy only; :class:`~sitl.cameras.rig.CameraRig` applies them).

* :class:`GaussMarkov` -- a seeded, slowly varying random signal whose values depend on the seed
  and the time alone (not on when, or how often, it is read);
* :class:`SunSchedule` -- the sun's intensity factor over time (:class:`~sitl.cameras.scene.LightingConfig`);
* :class:`SensorResponse` -- a camera's vignetting, gain drift and tone curve
  (:class:`~sitl.cameras.config.CameraMount`).
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np

from companion.vision.geometry import CameraIntrinsics

from .config import CameraMount
from .scene import LightingConfig

__all__ = ["GaussMarkov", "SunSchedule", "SensorResponse", "vignetting_map", "CLOUD_SOFTNESS"]

#: the width of a cloud's edge in the cloud process's standard deviations (:class:`SunSchedule`)
CLOUD_SOFTNESS = 0.25


class GaussMarkov:
    """A stationary, unit-variance Gauss-Markov signal ``x(t)``, ``t >= 0``, of time constant
    ``time_constant_s``, smoothed by a first-order low-pass of ``smoothing_s`` (0: none) and scaled
    back to unit variance. It is sampled from ``rng`` on a fixed grid of ``step_s`` as time
    advances (the low-pass run in for five of its time constants before ``t = 0``) and linearly
    interpolated between samples."""

    def __init__(self, rng: np.random.Generator, time_constant_s: float, smoothing_s: float = 0.0,
                 step_s: float = 0.05):
        if not (time_constant_s > 0 and smoothing_s >= 0 and step_s > 0):
            raise ValueError("time_constant_s and step_s must be positive, smoothing_s non-negative")
        self.rng, self.h = rng, step_s
        self.a = math.exp(-step_s / time_constant_s)
        self.b = math.sqrt(1.0 - self.a * self.a)
        self.c = math.exp(-step_s / smoothing_s) if smoothing_s > 0 else 0.0
        a, c = self.a, self.c
        var = (1 - c) ** 2 / (1 - c * c) * (1 + a * c) / (1 - a * c)  # the low-pass output's variance
        self.scale = 1.0 / math.sqrt(var)
        self.x = float(rng.standard_normal())
        self.y = self.x
        for _ in range(int(math.ceil(5.0 * smoothing_s / step_s))):
            self._step()
        self.values = [self.y * self.scale]

    def _step(self) -> None:
        self.x = self.a * self.x + self.b * float(self.rng.standard_normal())
        self.y = self.c * self.y + (1.0 - self.c) * self.x

    def at(self, t_s: float) -> float:
        """``x(t_s)`` (``t_s`` < 0: ``x(0)``)."""
        u = max(t_s, 0.0) / self.h
        k = int(u)
        while len(self.values) < k + 2:
            self._step()
            self.values.append(self.y * self.scale)
        f = u - k
        return (1.0 - f) * self.values[k] + f * self.values[k + 1]


class SunSchedule:
    """The sun's intensity over a flight as a factor of its clear-sky intensity:
    ``1 - cloud_depth c(t)``, the cloud shade ``c(t) = Phi((x(t) - q) / CLOUD_SOFTNESS)`` of a
    :class:`GaussMarkov` ``x`` (time constant ``cloud_time_s``, smoothed over ``cloud_edge_s``)
    with ``q`` its ``1 - cloud_cover`` quantile: the sun is more covered than not a fraction
    ``cloud_cover`` of the time. Clear sky (``cloud_cover`` 0): 1 throughout, ``rng`` untouched."""

    def __init__(self, cfg: LightingConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.process = GaussMarkov(rng, cfg.cloud_time_s, cfg.cloud_edge_s) if 0 < cfg.cloud_cover < 1 else None
        self.q = NormalDist().inv_cdf(1.0 - cfg.cloud_cover) if self.process is not None else 0.0
        self._phi = NormalDist().cdf

    def shade(self, t_s: float) -> float:
        """The cloud shade ``c(t_s)`` in [0, 1] (0: clear sun)."""
        if self.process is None:
            return float(self.cfg.cloud_cover >= 1.0)
        return self._phi((self.process.at(t_s) - self.q) / CLOUD_SOFTNESS)

    def factor(self, t_s: float) -> float:
        """The sun's intensity at ``t_s`` over its clear-sky intensity."""
        return 1.0 - self.cfg.cloud_depth * self.shade(t_s)


def vignetting_map(intr: CameraIntrinsics, vignetting: float) -> np.ndarray:
    """The relative illumination of each pixel (height, width, 1), float32: ``cos^4`` of the angle
    of a lens whose corners get ``1 - vignetting`` of the centre's light, centred on the
    principal point (1 everywhere without vignetting)."""
    if not vignetting:
        return np.ones((intr.height_px, intr.width_px, 1), dtype=np.float32)
    u, v = np.meshgrid(np.arange(intr.width_px, dtype=np.float64), np.arange(intr.height_px, dtype=np.float64))
    r2 = (u - intr.cx_px) ** 2 + (v - intr.cy_px) ** 2
    corners = [(x - intr.cx_px) ** 2 + (y - intr.cy_px) ** 2 for x in (0, intr.width_px - 1)
               for y in (0, intr.height_px - 1)]
    tan_corner = math.tan(math.acos((1.0 - vignetting) ** 0.25))
    f2 = max(corners) / tan_corner**2  # the focal length [px^2] for which the corner ray has that angle
    return (1.0 / (1.0 + r2 / f2) ** 2).astype(np.float32)[..., None]


class SensorResponse:
    """One camera's vignetting, gain drift and tone curve (:class:`~sitl.cameras.config.CameraMount`),
    on images of the camera's true intrinsics ``intr``; the gain's signal drawn with ``rng``."""

    def __init__(self, mount: CameraMount, intr: CameraIntrinsics, rng: np.random.Generator):
        self.mount = mount
        self.vmap = vignetting_map(intr, mount.vignetting) if mount.vignetting else None
        self.gain = GaussMarkov(rng, mount.gain_time_s) if mount.gain_std else None

    def gain_at(self, t_s: float) -> float:
        """The sensor's gain at ``t_s`` (1 without a gain drift)."""
        return math.exp(self.mount.gain_std * self.gain.at(t_s)) if self.gain is not None else 1.0

    def expose(self, img: np.ndarray, t_s: float) -> np.ndarray:
        """``img`` (height, width, 3) with the vignetting and the gain at ``t_s``, float32."""
        out = np.asarray(img, dtype=np.float32)
        if self.vmap is not None:
            out = out * self.vmap
        if self.gain is not None:
            out = out * np.float32(self.gain_at(t_s))
        return out

    def tone(self, img: np.ndarray) -> np.ndarray:
        """``img`` clipped to [0, 255] through the tone curve, uint8."""
        v = np.clip(img, 0.0, 255.0)
        if self.mount.gamma != 1.0:
            v = 255.0 * (v / 255.0) ** (1.0 / self.mount.gamma)
        return np.rint(v).astype(np.uint8)

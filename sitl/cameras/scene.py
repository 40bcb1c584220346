"""A scenario's ``[scene]``: what the cameras see around the flight (the ground, the light, clutter).

* :class:`SceneConfig` -- the ground's look (``plain``: one colour; ``checker``: MuJoCo's builtin
  checker of two colours; ``noise``: a texture of the two colours generated from the seed), with a
  period of ``ground_tile_m``, and whether the cameras render shadows;
* :class:`LightingConfig` (``[scene.lighting]``) -- the sun (direction drawn once from the seed,
  intensity dimmed by passing clouds) and the sky's light;
* :class:`ClutterConfig` (``[scene.clutter]``) -- boxes, cylinders and crates printed with
  distractor ArUco markers, placed from the seed in a ring around the flight.

Everything is off by default: a scenario without ``[scene]`` renders as before. Every random draw
comes from the scenario's seed through :func:`scene_rng` (one stream per purpose, apart from the
other sensors'). No OpenCV and no MuJoCo here: the MJCF is :mod:`sitl.cameras.backdrop`'s, the
light over time :mod:`sitl.cameras.photometry`'s.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from companion.configfile import require_nonnegative, require_positive
from companion.vision.dictionaries import ARUCO_DICTIONARY_IDS, check_marker

__all__ = ["LightingConfig", "ClutterConfig", "ClutterItem", "SceneConfig", "scene_rng", "CRATE_PER_MARKER"]

#: the scene's random streams by what they draw (each its own stream of the scenario's seed)
_STREAMS = {"sun": 0, "clouds": 1, "clutter": 2, "ground": 3}
#: a distractor crate's side over its marker's black square (room for the white quiet zone)
CRATE_PER_MARKER = 1.4
#: placement tries per clutter item before it is placed overlapping another
_PLACEMENT_TRIES = 100


def scene_rng(seed: int, what: str) -> np.random.Generator:
    """The random stream of the scene's ``what`` (``"sun"``, ``"clouds"``, ``"clutter"``, ``"ground"``)."""
    return np.random.default_rng([seed, 0x5CE7E, _STREAMS[what]])


def _check_range(obj, name: str, lo: float, hi: float) -> None:
    a, b = getattr(obj, name)
    if not (lo <= a <= b <= hi):
        raise ValueError(f"{name} must be [min, max] with {lo:g} <= min <= max <= {hi:g}, got {[a, b]}")


@dataclass(frozen=True)
class LightingConfig:
    """The scene's light when ``enabled`` (else MuJoCo's default: a light overhead and a headlight
    at the camera). The sun is a directional light whose elevation and azimuth (from the world's x
    axis towards y) are drawn once from the seed, uniformly in ``sun_elevation_deg`` and
    ``sun_azimuth_deg``; its intensity is ``sun_intensity`` in clear sky, times ``1 - cloud_depth
    c(t)`` where the cloud shade ``c(t)`` in [0, 1] covers the sun a fraction ``cloud_cover`` of
    the time, in spells of about ``cloud_time_s``, each edge passing over in about
    ``cloud_edge_s`` (:class:`~sitl.cameras.photometry.SunSchedule`). The sky lights every surface
    evenly with ``sky_ambient`` (the headlight's ambient; its directed light is off). The markers
    are then matte paper, lit by these alone (no light of their own). MuJoCo's lighting saturates:
    a surface lit by more than 1 in all (``sky_ambient`` plus ``sun_intensity`` times the sine of
    the sun's elevation on a level face) shows its own colour, so a clear sky near 1 (0.4 and
    0.7) leaves the clouds their whole effect."""

    enabled: bool = False
    sun_elevation_deg: tuple[float, float] = (35.0, 65.0)
    sun_azimuth_deg: tuple[float, float] = (0.0, 360.0)
    sun_intensity: float = 0.7
    sky_ambient: float = 0.35
    cloud_cover: float = 0.0
    cloud_depth: float = 0.6
    cloud_time_s: float = 10.0
    cloud_edge_s: float = 2.0

    def __post_init__(self) -> None:
        _check_range(self, "sun_elevation_deg", 5.0, 90.0)
        _check_range(self, "sun_azimuth_deg", -360.0, 720.0)
        require_nonnegative(self, "sun_intensity", "sky_ambient", "cloud_edge_s")
        require_positive(self, "cloud_time_s")
        if self.sun_intensity + self.sky_ambient > 2.0:
            raise ValueError(f"sun_intensity + sky_ambient must be at most 2 (beyond, everything lit saturates), "
                             f"got {self.sun_intensity + self.sky_ambient:g}")
        for name in ("cloud_cover", "cloud_depth"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")

    def sun_direction(self, rng: np.random.Generator) -> np.ndarray:
        """The sun's light direction (a unit vector from the sun, world frame), drawn with ``rng``."""
        el = math.radians(rng.uniform(*self.sun_elevation_deg))
        az = math.radians(rng.uniform(*self.sun_azimuth_deg))
        return -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


@dataclass(frozen=True)
class ClutterItem:
    """One clutter object standing on the ground: a ``box``, a ``cylinder`` or a ``crate`` (a box
    with ``marker_id``'s marker, black square ``marker_size_m``, on its top face); centre
    ``pos_w_m``, yaw ``yaw_rad``, half extents ``half_m`` (a cylinder: radius, radius, half
    height), colour ``rgb``."""

    kind: Literal["box", "cylinder", "crate"]
    pos_w_m: tuple[float, float, float]
    yaw_rad: float
    half_m: tuple[float, float, float]
    rgb: tuple[float, float, float]
    marker_id: int = -1
    marker_size_m: float = 0.0

    @property
    def footprint_m(self) -> float:
        """The radius of the smallest vertical cylinder about the centre that holds the object."""
        if self.kind == "cylinder":
            return self.half_m[0]
        return math.hypot(self.half_m[0], self.half_m[1])


@dataclass(frozen=True)
class ClutterConfig:
    """``count`` boxes and cylinders (sides and heights uniform in ``size_m``, random yaw and
    colour) and ``markers`` crates with a distractor marker on top (ids of ``dictionary`` drawn
    without the scenario's own, black squares uniform in ``marker_size_m``, crates 0.05-0.4 m
    high), all standing on the ground in the ring between ``inner_radius_m`` and
    ``outer_radius_m`` about ``center_w_m`` (x, y), entirely inside it, apart from each other
    where they fit (:meth:`place`). They are seen, not touched: no collisions with anything. A
    slung-load scenario checks that the ring's inside holds the formation's whole circle;
    elsewhere keeping the flight inside the ring is the file's job."""

    count: int = 0
    markers: int = 0
    dictionary: str = "DICT_4X4_50"
    marker_size_m: tuple[float, float] = (0.15, 0.35)
    size_m: tuple[float, float] = (0.2, 1.0)
    center_w_m: tuple[float, float] = (0.0, 0.0)
    inner_radius_m: float = 4.0
    outer_radius_m: float = 10.0

    def __post_init__(self) -> None:
        require_nonnegative(self, "count", "markers")
        require_positive(self, "inner_radius_m")
        check_marker(self.dictionary)
        if self.markers >= ARUCO_DICTIONARY_IDS[self.dictionary]:
            raise ValueError(f"markers: {self.dictionary} has {ARUCO_DICTIONARY_IDS[self.dictionary]} ids, got "
                             f"{self.markers} distractors")
        _check_range(self, "size_m", 0.01, 5.0)
        _check_range(self, "marker_size_m", 0.01, 2.0)
        widest = 2.0 * max(math.sqrt(0.5) * self.size_m[1], 0.5 * math.sqrt(2.0) * CRATE_PER_MARKER
                           * self.marker_size_m[1])
        if self.outer_radius_m - self.inner_radius_m <= widest:
            raise ValueError(f"outer_radius_m must exceed inner_radius_m by more than the widest item "
                             f"({widest:.2f} m), got {self.outer_radius_m:g} and {self.inner_radius_m:g}")

    @property
    def active(self) -> bool:
        return bool(self.count or self.markers)

    def place(self, rng: np.random.Generator, exclude_ids: tuple[int, ...] = ()) -> tuple[ClutterItem, ...]:
        """The items, drawn with ``rng`` (class docstring): the distractor ids first (never one of
        ``exclude_ids``), then each item's size, colour and yaw, then its place: uniform over the
        part of the ring its footprint fits in, redrawn while it overlaps an earlier item (at most
        a hundred tries, then left overlapping)."""
        free = np.setdiff1d(np.arange(ARUCO_DICTIONARY_IDS[self.dictionary]), np.asarray(exclude_ids, dtype=int))
        if self.markers > len(free):
            raise ValueError(f"markers: {len(free)} ids of {self.dictionary} are free, {self.markers} asked")
        ids = rng.choice(free, size=self.markers, replace=False) if self.markers else ()
        items: list[ClutterItem] = []
        for j in range(self.count + self.markers):
            rgb = colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.2, 0.8), rng.uniform(0.3, 0.9))
            yaw = rng.uniform(0.0, 2.0 * math.pi)
            if j < self.count:
                kind = "box" if rng.random() < 0.5 else "cylinder"
                w, d, h = rng.uniform(*self.size_m, size=3)
                half = (0.5 * w, 0.5 * (w if kind == "cylinder" else d), 0.5 * h)
                item = ClutterItem(kind, (0.0, 0.0, half[2]), yaw, half, rgb)
            else:
                size = rng.uniform(*self.marker_size_m)
                h = rng.uniform(0.05, 0.4)
                half = (0.5 * CRATE_PER_MARKER * size, 0.5 * CRATE_PER_MARKER * size, 0.5 * h)
                item = ClutterItem("crate", (0.0, 0.0, half[2]), yaw, half, rgb, int(ids[j - self.count]), size)
            r0, r1 = self.inner_radius_m + item.footprint_m, self.outer_radius_m - item.footprint_m
            for _ in range(_PLACEMENT_TRIES):
                r = math.sqrt(rng.uniform(r0 * r0, r1 * r1))
                a = rng.uniform(0.0, 2.0 * math.pi)
                xy = (self.center_w_m[0] + r * math.cos(a), self.center_w_m[1] + r * math.sin(a))
                if all(math.dist(xy, o.pos_w_m[:2]) > item.footprint_m + o.footprint_m for o in items):
                    break
            items.append(ClutterItem(item.kind, (xy[0], xy[1], item.pos_w_m[2]), item.yaw_rad, item.half_m,
                                     tuple(float(c) for c in item.rgb), item.marker_id, item.marker_size_m))
        return tuple(items)


@dataclass(frozen=True)
class SceneConfig:
    """What the cameras see around the flight (module docstring). ``ground``: ``plain`` colours
    the ground plane ``ground_rgb``; ``checker`` and ``noise`` texture it with ``ground_rgb`` and
    ``ground_rgb2``, repeating every ``ground_tile_m``. ``shadows``: the cameras render shadows
    (the sun's, with ``[scene.lighting]``; they cost render time on the CPU)."""

    ground: Literal["plain", "checker", "noise"] = "plain"
    ground_rgb: tuple[float, float, float] = (0.35, 0.4, 0.35)
    ground_rgb2: tuple[float, float, float] = (0.25, 0.3, 0.22)
    ground_tile_m: float = 4.0
    shadows: bool = False
    lighting: LightingConfig = field(default_factory=LightingConfig)
    clutter: ClutterConfig = field(default_factory=ClutterConfig)

    def __post_init__(self) -> None:
        require_positive(self, "ground_tile_m")
        for name in ("ground_rgb", "ground_rgb2"):
            if not all(0.0 <= c <= 1.0 for c in getattr(self, name)):
                raise ValueError(f"{name}: each component in [0, 1], got {list(getattr(self, name))}")

    @property
    def active(self) -> bool:
        """Whether the scene differs from the default one (else the model is left as built)."""
        return self != SceneConfig()

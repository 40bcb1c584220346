"""The ``[[cameras]]`` and ``[[markers]]`` of a scenario (:mod:`sitl.cameras.rig` renders them).

No OpenCV and no MuJoCo here: scenarios load, and are validated, on any install.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from companion.configfile import require_nonnegative, require_positive
from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat
from companion.vision.dictionaries import check_marker
from companion.vision.geometry import CameraIntrinsics, frame_from_axes

__all__ = ["CameraMount", "MarkerMount", "link_of", "placement_error"]


def link_of(body: str) -> int | None:
    """The 0-based link a body name is (``link<i>``), else ``None`` (the world, a load)."""
    m = re.fullmatch(r"link(\d+)", body)
    return int(m.group(1)) - 1 if m else None


def placement_error(rng: np.random.Generator, std_m: float, std_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Where a mount really sits against where it is said to: a body-frame offset [m] of
    ``N(0, std_m)`` per axis and a body-frame rotation ``Exp(N(0, std_deg) per axis)`` that turns
    the nominal orientation into the true one (``rng`` untouched when both are 0)."""
    if not (std_m or std_deg):
        return np.zeros(3), np.eye(3)
    dp, phi = std_m * rng.standard_normal(3), np.radians(std_deg) * rng.standard_normal(3)
    return dp, quat_to_rotmat(quat_from_rotvec(phi))


@dataclass(frozen=True)
class CameraMount:
    """A camera on ``body``: at ``pos_b_m``, looking along ``optical_axis_b`` with the image's right
    along ``image_right_b`` (body frame; orthogonal), ``width_px`` x ``height_px`` with vertical
    field of view ``fovy_deg`` (square pixels, principal point at the centre) and OpenCV
    distortion ``dist_coeffs`` (k1, k2, p1, p2[, k3]; empty: none), at ``rate_hz`` (a whole divisor
    of the physics rate), delivered ``latency_s`` after capture, with Gaussian pixel noise of
    ``noise_std_dn`` grey levels and, if ``exposure_s`` > 0, motion blur: the mean of
    ``blur_samples`` renders spread over the exposure. ``vehicle``: the vehicle the frames are
    attributed to (0-based; -1: the link the body is, ``link<i>`` -> i - 1, else 0). Fleet mode
    publishes the frames over Zenoh (:mod:`sitl.cameras.stream`) with the image as ``wire_format``
    (``png``: lossless; ``raw``: no encoding; ``jpeg``: lossy, ``wire_quality`` 1-100).

    A mount error: the camera really sits ``mount_std_m`` per axis and ``mount_std_deg`` per
    axis (a rotation on the body side) off where ``pos_b_m`` and the axes say, drawn once from the
    scenario's seed (:meth:`true_mount`); everything that estimates takes the nominal mount.

    A calibration error: the camera's true intrinsics are drawn once from the scenario's seed
    around the nominal ones the frames carry (what the estimator believes): the focal lengths
    scaled by ``1 + N(0, calib_focal_std_frac)``, the principal point moved by ``N(0,
    calib_principal_std_px)`` per axis, each distortion coefficient scaled by ``1 + N(0,
    calib_dist_std_frac)`` (:meth:`true_intrinsics`). ``drop_probability``: each frame is lost
    before delivery with this probability (seeded; counted).

    Latency jitter: each frame is delivered ``latency_s`` plus a seeded, never negative jitter
    after capture (:meth:`latency_jitter_draw`): uniform in ``[0, latency_jitter_s]``
    (``latency_jitter_dist = "uniform"``) or the magnitude of a normal of standard deviation
    ``latency_jitter_s`` cut at three of them (``"halfnormal"``: mostly short, a tail of late
    frames). A camera's frames stay in capture order (one link per camera: a frame held back
    holds back the ones behind it); frames of different cameras may overtake each other. The
    frame keeps its true capture time.

    The sensor's response (:mod:`sitl.cameras.photometry`), applied to the image through the
    lens, in this order: ``vignetting``, the fraction of light lost in the image's corners (a
    cos^4-shaped fall-off from the centre; 0: none); a gain of ``exp(gain_std * x(t))``, ``x`` a
    seeded unit-variance Gauss-Markov process of time constant ``gain_time_s`` (exposure and gain
    control drifting: the whole image brighter or darker over seconds; 0: none); the pixel noise;
    then the tone curve ``255 (v / 255) ** (1 / gamma)`` (1: linear)."""

    name: str
    body: str = "link1"
    pos_b_m: tuple[float, float, float] = (0.0, 0.0, -0.05)
    optical_axis_b: tuple[float, float, float] = (0.0, 0.0, -1.0)
    image_right_b: tuple[float, float, float] = (0.0, -1.0, 0.0)
    width_px: int = 640
    height_px: int = 480
    fovy_deg: float = 60.0
    dist_coeffs: tuple[float, ...] = ()
    rate_hz: float = 10.0
    latency_s: float = 0.05
    noise_std_dn: float = 2.0
    exposure_s: float = 0.0
    blur_samples: int = 3
    vehicle: int = -1
    wire_format: Literal["raw", "png", "jpeg"] = "png"
    wire_quality: int = 90
    calib_focal_std_frac: float = 0.0
    calib_principal_std_px: float = 0.0
    calib_dist_std_frac: float = 0.0
    drop_probability: float = 0.0
    latency_jitter_s: float = 0.0
    latency_jitter_dist: Literal["uniform", "halfnormal"] = "uniform"
    vignetting: float = 0.0
    gain_std: float = 0.0
    gain_time_s: float = 3.0
    gamma: float = 1.0
    mount_std_m: float = 0.0
    mount_std_deg: float = 0.0

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[A-Za-z0-9_]+", self.name):
            raise ValueError(f"name: letters, digits and '_' only, got {self.name!r}")
        frame_from_axes(self.optical_axis_b, self.image_right_b)
        self.intrinsics()  # size, field of view and distortion checked there
        require_positive(self, "rate_hz", "gain_time_s", "gamma")
        require_nonnegative(self, "latency_s", "noise_std_dn", "exposure_s", "calib_focal_std_frac",
                            "calib_principal_std_px", "calib_dist_std_frac", "latency_jitter_s", "gain_std",
                            "mount_std_m", "mount_std_deg")
        if not 0.0 <= self.vignetting < 1.0:
            raise ValueError(f"vignetting must be in [0, 1), got {self.vignetting}")
        if self.gain_std > 1.0:
            raise ValueError(f"gain_std must be at most 1 (a factor e either way), got {self.gain_std}")
        if not 0.2 <= self.gamma <= 5.0:
            raise ValueError(f"gamma must be in [0.2, 5], got {self.gamma}")
        if not 0.0 <= self.drop_probability < 1.0:
            raise ValueError(f"drop_probability must be in [0, 1), got {self.drop_probability}")
        if self.calib_focal_std_frac >= 0.2:
            raise ValueError(f"calib_focal_std_frac must be below 0.2 (a calibration, not a guess), "
                             f"got {self.calib_focal_std_frac}")
        if self.exposure_s > 0 and self.blur_samples < 2:
            raise ValueError(f"blur_samples must be >= 2 with an exposure, got {self.blur_samples}")
        if not 1 <= self.wire_quality <= 100:
            raise ValueError(f"wire_quality must be in 1..100, got {self.wire_quality}")
        if self.exposure_s >= 1.0 / self.rate_hz:
            raise ValueError(f"exposure_s must be shorter than the frame period {1.0 / self.rate_hz:g} s")

    def true_mount(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Where the camera really is on its body, ``(pos_b_m, R_b_c)``, drawn with ``rng``
        (:func:`placement_error`; the configured mount without a mount error)."""
        dp, R = placement_error(rng, self.mount_std_m, self.mount_std_deg)
        return np.asarray(self.pos_b_m, dtype=float) + dp, R @ self.R_b_c()

    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics.from_fov(self.width_px, self.height_px, self.fovy_deg, self.dist_coeffs)

    @property
    def calibration_error(self) -> bool:
        return bool(self.calib_focal_std_frac or self.calib_principal_std_px or self.calib_dist_std_frac)

    def true_intrinsics(self, rng: np.random.Generator) -> CameraIntrinsics:
        """The camera's true intrinsics, drawn with ``rng`` around :meth:`intrinsics` (class
        docstring); the nominal ones when there is no calibration error (``rng`` untouched)."""
        nom = self.intrinsics()
        if not self.calibration_error:
            return nom
        f, c, d = rng.standard_normal(2), rng.standard_normal(2), rng.standard_normal(len(nom.dist_coeffs))
        return replace(nom, fx_px=nom.fx_px * (1.0 + self.calib_focal_std_frac * f[0]),
                       fy_px=nom.fy_px * (1.0 + self.calib_focal_std_frac * f[1]),
                       cx_px=nom.cx_px + self.calib_principal_std_px * c[0],
                       cy_px=nom.cy_px + self.calib_principal_std_px * c[1],
                       dist_coeffs=tuple(k * (1.0 + self.calib_dist_std_frac * e) for k, e in zip(nom.dist_coeffs, d)))

    @property
    def photometric(self) -> bool:
        """Whether the sensor's response does anything (vignetting, gain drift or a tone curve)."""
        return bool(self.vignetting or self.gain_std or self.gamma != 1.0)

    def latency_jitter_draw(self, rng: np.random.Generator) -> float:
        """One frame's delivery jitter [s], drawn with ``rng`` (class docstring): never negative,
        never above ``3 latency_jitter_s``; 0 without jitter (``rng`` untouched)."""
        s = self.latency_jitter_s
        if not s:
            return 0.0
        if self.latency_jitter_dist == "uniform":
            return s * float(rng.random())
        return min(abs(s * float(rng.standard_normal())), 3.0 * s)

    @property
    def max_latency_s(self) -> float:
        """The longest a frame takes from capture to delivery: ``latency_s`` plus the largest
        jitter :meth:`latency_jitter_draw` can give."""
        cap = 1.0 if self.latency_jitter_dist == "uniform" else 3.0
        return self.latency_s + cap * self.latency_jitter_s

    def R_b_c(self) -> np.ndarray:
        """Camera (OpenCV axes) to body rotation, as configured."""
        return frame_from_axes(self.optical_axis_b, self.image_right_b)

    def vehicle_index(self) -> int:
        if self.vehicle >= 0:
            return self.vehicle
        link = link_of(self.body)
        return 0 if link is None else link


@dataclass(frozen=True)
class MarkerMount:
    """An ArUco marker ``id`` of ``dictionary`` on ``body``, its centre at ``pos_b_m``, its face
    normal (marker z) ``normal_b`` and its right (marker x) ``right_b`` (body frame; orthogonal);
    ``size_m`` is the side of the black square (the length PnP takes); a white quiet zone of
    ``quiet_zone_bits`` bits surrounds it. A mount error (``mount_std_m``, ``mount_std_deg``) as
    :class:`CameraMount`'s: the marker really sits that far off its configured mount
    (:meth:`true_mount`)."""

    id: int
    body: str = "world"
    dictionary: str = "DICT_4X4_50"
    size_m: float = 0.2
    pos_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal_b: tuple[float, float, float] = (0.0, 0.0, 1.0)
    right_b: tuple[float, float, float] = (1.0, 0.0, 0.0)
    quiet_zone_bits: int = 1
    mount_std_m: float = 0.0
    mount_std_deg: float = 0.0

    def __post_init__(self) -> None:
        require_positive(self, "size_m")
        require_nonnegative(self, "quiet_zone_bits", "mount_std_m", "mount_std_deg")
        check_marker(self.dictionary, self.id)
        frame_from_axes(self.normal_b, self.right_b)

    def R_b_m(self) -> np.ndarray:
        """Marker to body rotation, as configured."""
        return frame_from_axes(self.normal_b, self.right_b)

    def true_mount(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Where the marker really is on its body, ``(pos_b_m, R_b_m)``, drawn with ``rng``
        (:func:`placement_error`; the configured mount without a mount error)."""
        dp, R = placement_error(rng, self.mount_std_m, self.mount_std_deg)
        return np.asarray(self.pos_b_m, dtype=float) + dp, R @ self.R_b_m()

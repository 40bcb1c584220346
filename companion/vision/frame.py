"""One camera image with a typed, versioned header: what a camera delivers to the vision pipeline.

The SITL's cameras (:mod:`sitl.camera`) produce :class:`CameraFrame`; on hardware a
``cv2.VideoCapture`` source does (:mod:`.node`), and the Zenoh wire (``<prefix>/camera/<vehicle>/image``,
:mod:`.camera_wire`) carries the header's fields with an encoded image. The header carries everything a consumer
needs without the image: which camera, which vehicle, the sequence number, the capture time on
the producer's clock (the simulation clock in the SITL; mid-exposure), the time the frame became
available (capture plus the camera's latency), the image's size and encoding, and the
intrinsics the image was taken with.

numpy only (no OpenCV).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .geometry import CameraIntrinsics

__all__ = ["CAMERA_FRAME_VERSION", "CameraFrameHeader", "CameraFrame"]

#: version of :class:`CameraFrameHeader`'s layout; a consumer rejects frames of other versions
CAMERA_FRAME_VERSION = 1

#: image encodings: raw 8-bit RGB or grey, row-major, no padding
Encoding = Literal["rgb8", "mono8"]

_CHANNELS = {"rgb8": 3, "mono8": 1}


@dataclass(frozen=True)
class CameraFrameHeader:
    """Metadata of one frame (see the module docstring). ``vehicle`` is 0-based (link index in a
    skeleton, vehicle index in a fleet)."""

    camera: str
    vehicle: int
    seq: int
    t_capture_s: float
    t_available_s: float
    width_px: int
    height_px: int
    encoding: Encoding
    intrinsics: CameraIntrinsics
    version: int = CAMERA_FRAME_VERSION

    def __post_init__(self) -> None:
        if self.version != CAMERA_FRAME_VERSION:
            raise ValueError(f"version: expected {CAMERA_FRAME_VERSION}, got {self.version}")
        if not self.camera:
            raise ValueError("camera: empty name")
        if self.vehicle < 0 or self.seq < 0:
            raise ValueError(f"vehicle and seq must be >= 0, got {self.vehicle}, {self.seq}")
        if not (math.isfinite(self.t_capture_s) and math.isfinite(self.t_available_s)):
            raise ValueError("t_capture_s and t_available_s must be finite")
        if self.t_available_s < self.t_capture_s:
            raise ValueError(f"t_available_s ({self.t_available_s}) before t_capture_s ({self.t_capture_s})")
        if self.encoding not in _CHANNELS:
            raise ValueError(f"encoding: one of {sorted(_CHANNELS)}, got {self.encoding!r}")
        if (self.width_px, self.height_px) != (self.intrinsics.width_px, self.intrinsics.height_px):
            raise ValueError(f"image {self.width_px}x{self.height_px} does not match the intrinsics' "
                             f"{self.intrinsics.width_px}x{self.intrinsics.height_px}")

    @property
    def latency_s(self) -> float:
        return self.t_available_s - self.t_capture_s


@dataclass(frozen=True)
class CameraFrame:
    """A header and its image: ``(height, width, 3)`` uint8 RGB for ``rgb8``, ``(height, width)``
    for ``mono8``. ``ValueError`` if the image does not fit the header."""

    header: CameraFrameHeader
    image: np.ndarray

    def __post_init__(self) -> None:
        h = self.header
        img = self.image
        shape = (h.height_px, h.width_px) + ((3,) if _CHANNELS[h.encoding] == 3 else ())
        if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.shape != shape:
            got = (getattr(img, "shape", None), getattr(img, "dtype", None))
            raise ValueError(f"image: expected uint8 {shape} for {h.encoding}, got {got}")

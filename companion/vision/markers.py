"""ArUco markers: dictionaries, marker images (the SITL's textures), detection (OpenCV).

The detector is OpenCV's ``cv2.aruco.ArucoDetector`` with corner refinement (sub-pixel by
default): the report's markers (sec. III) are found the same way. Corners come in ArUco's order
(top-left, top-right, bottom-right, bottom-left of the printed marker), the order of
:func:`marker_object_points`; with a distorted camera they are undistorted to the pinhole
pixels of the same camera matrix, so PnP (:mod:`.pnp`) runs without distortion.
"""

from __future__ import annotations

from dataclasses import dataclass
import cv2
import numpy as np

from .config import DetectorConfig
from .dictionaries import ARUCO_DICTIONARY_IDS, check_marker
from .geometry import CameraIntrinsics

__all__ = [
    "DICTIONARIES",
    "DetectorConfig",
    "MarkerDetection",
    "aruco_dictionary",
    "marker_image",
    "marker_object_points",
    "make_detector",
    "detect_markers",
]

#: the predefined ArUco dictionaries by name (``DICT_4X4_50`` ...)
DICTIONARIES = tuple(ARUCO_DICTIONARY_IDS)

_REFINEMENT = {
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """A predefined dictionary by name; ``ValueError`` listing the names for an unknown one."""
    check_marker(name)
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def marker_image(dictionary: str, marker_id: int, bit_px: int = 32, quiet_zone_bits: int = 1) -> tuple[np.ndarray, float]:
    """A printable marker: uint8 grey image with a white quiet zone of ``quiet_zone_bits`` around
    the black-bordered code, ``bit_px`` pixels per bit. Returns ``(image, fraction)``, ``fraction``
    the side of the black square (the marker length PnP uses) over the image's side."""
    check_marker(dictionary, marker_id)
    d = aruco_dictionary(dictionary)
    if bit_px < 1 or quiet_zone_bits < 0:
        raise ValueError(f"bit_px must be >= 1 and quiet_zone_bits >= 0, got {bit_px}, {quiet_zone_bits}")
    bits = d.markerSize + 2  # the code plus its one-bit black border
    code = cv2.aruco.generateImageMarker(d, int(marker_id), bits * bit_px, borderBits=1)
    pad = quiet_zone_bits * bit_px
    img = cv2.copyMakeBorder(code, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    return img, bits / (bits + 2 * quiet_zone_bits)


def marker_object_points(length_m: float) -> np.ndarray:
    """The marker's corners in its own frame (4, 3), in ArUco's order (what IPPE square expects)."""
    h = 0.5 * float(length_m)
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class MarkerDetection:
    """One detected marker: its id and its corners (4, 2) in undistorted pixels, ArUco's order."""

    marker_id: int
    corners_px: np.ndarray

    @property
    def side_px(self) -> float:
        """Mean side length in pixels (the marker's size in the image)."""
        c = self.corners_px
        return float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)))


def make_detector(cfg: DetectorConfig) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = _REFINEMENT[cfg.corner_refinement]
    params.cornerRefinementWinSize = int(cfg.refinement_window_px)
    return cv2.aruco.ArucoDetector(aruco_dictionary(cfg.dictionary), params)


def _grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    raise ValueError(f"image: expected (h, w) grey or (h, w, 3) RGB, got shape {image.shape}")


def detect_markers(image: np.ndarray, detector: cv2.aruco.ArucoDetector,
                   intrinsics: CameraIntrinsics | None = None) -> tuple[MarkerDetection, ...]:
    """The markers in ``image`` (uint8 RGB or grey), sorted by id; corners undistorted with
    ``intrinsics`` when it has distortion."""
    corners, ids, _ = detector.detectMarkers(_grey(image))
    if ids is None:
        return ()
    out = []
    for c, i in zip(corners, ids.ravel()):
        pts = np.asarray(c, dtype=float).reshape(4, 2)
        if intrinsics is not None and intrinsics.distorted:
            pts = cv2.undistortPoints(pts.reshape(-1, 1, 2), intrinsics.K, intrinsics.dist, P=intrinsics.K).reshape(4, 2)
        out.append(MarkerDetection(int(i), pts))
    return tuple(sorted(out, key=lambda d: d.marker_id))

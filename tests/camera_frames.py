"""A camera frame with a marker in it, for the tests of the camera wire and the vision node."""

from __future__ import annotations

import numpy as np

from companion.vision.frame import CameraFrame, CameraFrameHeader
from companion.vision.geometry import CameraIntrinsics


def marker_frame(vehicle: int = 0, seq: int = 0, encoding: str = "rgb8", side_px: int = 96) -> CameraFrame:
    """A 320x240 frame with ArUco marker 7 (DICT_4X4_50) pasted fronto-parallel at the centre
    (needs OpenCV: the ``vision`` extra)."""
    import cv2

    from companion.vision.markers import marker_image

    img, _ = marker_image("DICT_4X4_50", 7, bit_px=16)
    img = cv2.resize(img, (side_px, side_px), interpolation=cv2.INTER_AREA)
    canvas = np.full((240, 320), 128, np.uint8)
    y0, x0 = 120 - side_px // 2, 160 - side_px // 2
    canvas[y0 : y0 + side_px, x0 : x0 + side_px] = img
    image = canvas if encoding == "mono8" else np.repeat(canvas[:, :, None], 3, axis=2)
    intr = CameraIntrinsics.from_fov(320, 240, 60.0, (0.01, -0.002, 0.0, 0.0))
    h = CameraFrameHeader(f"cam{vehicle + 1}", vehicle, seq, 1.25 + seq, 1.30 + seq, 320, 240, encoding, intr)
    return CameraFrame(h, image)

"""A batch flight's camera frames kept as JPEG (``camera_frames.npz`` in the run folder), for
``run.mcap``'s image channels (:mod:`companion.recording.mcap_log`).

:class:`FrameArchive` is a frame consumer of :class:`~sitl.cameras.flight.FlightCameras`: every
delivered frame is JPEG-encoded (OpenCV, ``quality``) with its capture time and camera. The file
holds ``frame_t`` (K,) capture times [s], ``frame_camera`` (K,) indices into ``frame_names``,
``frame_offsets`` (K + 1,) byte offsets into ``frame_jpeg`` (the encoded frames back to back).
"""

from __future__ import annotations

import numpy as np

__all__ = ["FrameArchive", "FRAMES_NAME", "JPEG_QUALITY"]

FRAMES_NAME = "camera_frames.npz"
JPEG_QUALITY = 80


class FrameArchive:
    """The JPEG frames of the cameras named ``names`` (in the scenario's order)."""

    def __init__(self, names: list[str], quality: int = JPEG_QUALITY):
        self.names = list(names)
        self.quality = int(quality)
        self.t: list[float] = []
        self.camera: list[int] = []
        self.jpeg: list[bytes] = []

    def on_frame(self, captured) -> None:
        """A delivered frame (:class:`~sitl.cameras.rig.CapturedFrame`), encoded and kept."""
        import cv2

        image = captured.frame.image
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        if not ok:
            return
        self.t.append(float(captured.frame.header.t_capture_s))
        self.camera.append(int(captured.camera_index))
        self.jpeg.append(data.tobytes())

    def arrays(self) -> dict[str, np.ndarray]:
        offsets = np.concatenate(([0], np.cumsum([len(b) for b in self.jpeg], dtype=np.int64)))
        return {"frame_t": np.asarray(self.t, dtype=float), "frame_camera": np.asarray(self.camera, dtype=np.int64),
                "frame_offsets": offsets.astype(np.int64), "frame_names": np.asarray(self.names, dtype=np.str_),
                "frame_jpeg": np.frombuffer(b"".join(self.jpeg), dtype=np.uint8)}

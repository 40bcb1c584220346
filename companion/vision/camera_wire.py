"""Camera frames over Zenoh: ``<prefix>/camera/<vehicle>/image``, vehicles 1-based in keys.

:class:`CameraPublisher` puts :func:`~.frame_codec.encode_frame` payloads on a vehicle's key
(the SITL harness does, for every rendered frame; on an onboard computer the camera's own
process would). :class:`CameraSubscriber` listens on ``<prefix>/camera/*/image``; Zenoh calls
back on its own threads, the callback only queues the bytes and their key
(:class:`~companion.fleetnet.payload_queue.PayloadQueue`), and :meth:`drain`
decodes in the caller's thread: valid frames whose header's vehicle matches the key come out as
``("frame", CameraFrame, key)``, anything else as ``("error", reason, key)`` (counted, never
applied). The caller then runs the same pipeline on them as the SITL does
(:class:`~.load_pipeline.LoadVisionPipeline`).

Both take an open ``zenoh.Session`` (the daemon's, or a test's loopback session): this module
opens nothing and owns no clock. ``zenoh`` is the ``distributed`` extra; OpenCV (PNG/JPEG) the
``vision`` extra.
"""

from __future__ import annotations

import logging

from companion.fleetnet.payload_queue import PayloadQueue

from .frame import CameraFrame
from .frame_codec import FrameCodecError, ImageFormat, decode_frame, encode_frame

__all__ = ["camera_key", "camera_pattern", "vehicle_of_key", "CameraPublisher", "CameraSubscriber"]

log = logging.getLogger(__name__)


def camera_key(prefix: str, vehicle: int) -> str:
    """Where 0-based ``vehicle``'s camera frames are published."""
    return f"{prefix}/camera/{vehicle + 1}/image"


def camera_pattern(prefix: str) -> str:
    return f"{prefix}/camera/*/image"


def vehicle_of_key(prefix: str, key: str) -> int | None:
    """0-based vehicle of a ``<prefix>/camera/<v>/image`` key, ``None`` if it is not one."""
    head = f"{prefix}/camera/"
    if not key.startswith(head) or not key.endswith("/image"):
        return None
    chunk = key[len(head) : -len("/image")]
    return int(chunk) - 1 if chunk.isdigit() and int(chunk) >= 1 else None


class CameraPublisher:
    """Publishes one vehicle's frames (``fmt``: the image encoding on the wire)."""

    def __init__(self, session, prefix: str, vehicle: int, fmt: ImageFormat = "png", quality: int = 90):
        import zenoh

        self.key = camera_key(prefix, vehicle)
        self.vehicle = vehicle
        self.fmt, self.quality = fmt, quality
        # camera frames may be dropped under congestion (the next one supersedes them)
        self._pub = session.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.DROP,
                                              priority=zenoh.Priority.DATA)
        self.sent = 0
        self.bytes_sent = 0

    @property
    def matched(self) -> bool:
        """Whether a subscriber matches this key now (Zenoh's matching status)."""
        return bool(self._pub.matching_status.matching)

    def publish(self, frame: CameraFrame) -> int:
        """Encode and put one frame; returns the payload's size in bytes."""
        if frame.header.vehicle != self.vehicle:
            raise ValueError(f"frame of vehicle {frame.header.vehicle} on vehicle {self.vehicle}'s key")
        payload = encode_frame(frame, self.fmt, self.quality)
        self._pub.put(payload)
        self.sent += 1
        self.bytes_sent += len(payload)
        return len(payload)

    def close(self) -> None:
        self._pub.undeclare()


class CameraSubscriber:
    """Receives every vehicle's frames under ``prefix`` (module docstring)."""

    def __init__(self, session, prefix: str):
        self.prefix = prefix
        self._payloads = PayloadQueue()
        self._sub = session.declare_subscriber(camera_pattern(prefix), self._payloads.on_sample)
        self.errors = 0
        self.frames = 0

    def drain(self) -> list[tuple[str, object, str]]:
        """Decode what arrived: ``("frame", CameraFrame, key)`` or ``("error", reason, key)``."""
        out = []
        for payload, key in self._payloads.take():
            vehicle = vehicle_of_key(self.prefix, key)
            try:
                frame = decode_frame(payload)
            except FrameCodecError as exc:
                self.errors += 1
                log.debug("%s: %s", key, exc)
                out.append(("error", str(exc), key))
                continue
            if frame.header.vehicle != vehicle:
                self.errors += 1
                out.append(("error", f"frame of vehicle {frame.header.vehicle} does not belong on this key", key))
                continue
            self.frames += 1
            out.append(("frame", frame, key))
        return out

    def close(self) -> None:
        self._sub.undeclare()

"""The vision consumer (``python -m companion.vision``): camera frames in, marker poses and a log out.

* :class:`VisionNode` (the core: no sockets, no threads; its clock is injected) runs the marker
  pipeline of batch mode on every frame -- ArUco detection with corner refinement, then PnP, the
  IPPE ambiguity and the covariance (:mod:`.pnp`), one :class:`~.pnp.MarkerPipeline` per
  ``(vehicle, camera)`` for its continuity -- times detection and PnP apart, and counts frames,
  detections and rejected payloads. Each frame gives a :class:`FrameRecord`.
* Sources: :class:`ZenohFrames` (a Zenoh session and a
  :class:`~.camera_wire.CameraSubscriber` on ``<prefix>/camera/*/image``: the SITL harness's
  frames, or an onboard camera process's) and :class:`VideoCaptureFrames` (``cv2.VideoCapture``:
  a camera device, a file or a stream URL on this computer).
* :func:`run_node`: the loop; writes ``vision_frames.jsonl`` (one line per frame, flushed: what a
  killed consumer leaves is readable) and, at the end, ``vision_summary.json``; with
  ``[[neighbours]]`` it publishes each frame's neighbour poses, with ``[load]`` its load
  observations (:mod:`.message_wire`).

OpenCV (the ``vision`` extra) through :mod:`.pnp`, ``zenoh`` (the ``distributed`` extra) for the
Zenoh source only; neither belongs to the onboard base install, and both are imported when a
node is made, not when this module is.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import PipelineConfig
from .frame import CameraFrame, CameraFrameHeader
from .node_config import VideoCaptureSource, VisionNodeSetup, ZenohCameraSource, fleet_credentials

__all__ = ["FrameRecord", "VisionNode", "ZenohFrames", "VideoCaptureFrames", "open_source", "run_node",
           "read_frame_log", "FRAMES_FILE", "SUMMARY_FILE"]

log = logging.getLogger(__name__)

FRAMES_FILE = "vision_frames.jsonl"
SUMMARY_FILE = "vision_summary.json"


@dataclass(frozen=True)
class FrameRecord:
    """One processed frame: its header's identity and stamps, the markers detected, the detection
    and PnP times [s] and the marker poses (:class:`~.pnp.MarkerPose`, camera frame)."""

    camera: str
    vehicle: int
    seq: int
    t_capture_s: float
    t_available_s: float
    detections: int
    detect_s: float
    pnp_s: float
    poses: tuple

    def to_json(self) -> dict:
        return {
            "camera": self.camera, "vehicle": self.vehicle, "seq": self.seq, "t_capture_s": self.t_capture_s,
            "t_available_s": self.t_available_s, "detections": self.detections,
            "detect_ms": round(1e3 * self.detect_s, 4), "pnp_ms": round(1e3 * self.pnp_s, 4),
            "poses": [{"id": p.marker_id, "method": p.method, "t_cm_m": [float(x) for x in p.t_cm_m],
                       "q_cm_wxyz": [float(x) for x in p.q_cm_wxyz], "cov": [float(x) for x in np.ravel(p.cov)],
                       "reproj_rms_px": p.reproj_rms_px, "side_px": p.side_px, "ambiguous": bool(p.ambiguous)}
                      for p in self.poses],
        }


def _stats_ms(values: list[float]) -> dict | None:
    if not values:
        return None
    a = 1e3 * np.asarray(values)
    return {"mean": round(float(a.mean()), 3), "p50": round(float(np.percentile(a, 50)), 3),
            "p95": round(float(np.percentile(a, 95)), 3), "max": round(float(a.max()), 3)}


class VisionNode:
    """The pipeline on frames, with counters (module docstring). ``clock``: seconds, for the timings."""

    def __init__(self, cfg: PipelineConfig, clock: Callable[[], float] = time.perf_counter):
        from .markers import detect_markers  # OpenCV: the vision extra
        from .pnp import MarkerPipeline, configured_pose

        self._detect, self._estimate, self._pipeline = detect_markers, configured_pose, MarkerPipeline
        self.cfg = cfg
        self.clock = clock
        self._pipes: dict[tuple[int, str], object] = {}
        self.frames: dict[str, int] = {}
        self.detected: dict[str, int] = {}
        self.poses = 0
        self.rejected = 0
        self.reject_reasons: dict[str, int] = {}
        self.detect_s: list[float] = []
        self.pnp_s: list[float] = []

    def on_frame(self, frame: CameraFrame) -> FrameRecord:
        """Detect and estimate every configured marker of one frame."""
        h = frame.header
        pipe = self._pipes.get((h.vehicle, h.camera))
        if pipe is None:
            pipe = self._pipes[(h.vehicle, h.camera)] = self._pipeline(self.cfg)
        cfg = self.cfg
        w0 = self.clock()
        dets = self._detect(frame.image, pipe.detector, h.intrinsics)
        if cfg.ids:
            dets = tuple(d for d in dets if d.marker_id in cfg.ids)
        w1 = self.clock()
        poses = []
        for d in dets:
            pose = self._estimate(d, h.intrinsics, cfg, pipe.method, pipe.previous)
            if pose is not None:
                pipe.previous[d.marker_id] = pose
                poses.append(pose)
        w2 = self.clock()
        self.frames[h.camera] = self.frames.get(h.camera, 0) + 1
        if dets:
            self.detected[h.camera] = self.detected.get(h.camera, 0) + 1
        self.poses += len(poses)
        self.detect_s.append(w1 - w0)
        self.pnp_s.append(w2 - w1)
        return FrameRecord(h.camera, h.vehicle, h.seq, h.t_capture_s, h.t_available_s, len(dets), w1 - w0, w2 - w1,
                           tuple(poses))

    def on_rejected(self, reason: str) -> None:
        """A payload or frame that was not a valid frame (counted by its reason's first words)."""
        self.rejected += 1
        kind = reason.split(":", 1)[0][:40]
        self.reject_reasons[kind] = self.reject_reasons.get(kind, 0) + 1

    def summary(self) -> dict:
        n = sum(self.frames.values())
        total = [d + p for d, p in zip(self.detect_s, self.pnp_s)]
        return {
            "frames": dict(self.frames),
            "frames_total": n,
            "frames_detected": sum(self.detected.values()),
            "detection_rate": {c: self.detected.get(c, 0) / k for c, k in self.frames.items()},
            "poses": self.poses,
            "rejected_payloads": self.rejected,
            "rejected_reasons": dict(self.reject_reasons),
            "method": self.cfg.method,
            "detect_ms": _stats_ms(self.detect_s),
            "pnp_ms": _stats_ms(self.pnp_s),
            "detect_pnp_ms": _stats_ms(total),
        }


class ZenohFrames:
    """Frames from ``<prefix>/camera/*/image`` over a Zenoh session this object opens (peer mode;
    with ``cfg.fleet``, presenting ``cfg.group``'s credentials of that fleet:
    :func:`~.node_config.fleet_credentials`). ``file``: the consumer's config, for the errors."""

    kind = "zenoh"

    def __init__(self, cfg: ZenohCameraSource, file: str = "<config>"):
        env = cfg.runtime_env()
        if env and "ZENOH_RUNTIME" not in os.environ:  # before the first session of this process
            os.environ["ZENOH_RUNTIME"] = env
        import zenoh

        from companion.fleetnet.bus import peer_config

        from .camera_wire import CameraSubscriber, vehicle_of_key

        self.cfg = cfg
        self._vehicle_of_key = vehicle_of_key
        self.session = zenoh.open(peer_config(cfg.listen, cfg.connect, fleet_credentials(cfg, file),
                                              cfg.multicast_scouting, file))
        try:
            self.subscriber = CameraSubscriber(self.session, cfg.prefix)
        except BaseException:
            self.session.close()
            raise
        log.info("subscribed to %s/camera/*/image (connect %s, listen %s%s)", cfg.prefix, list(cfg.connect),
                 list(cfg.listen), f"; group {cfg.group}'s credentials of {cfg.fleet}" if cfg.fleet else "")

    def poll(self, timeout_s: float) -> list[tuple[str, object]]:
        """What arrived: ``("frame", CameraFrame)`` or ``("error", reason)``; waits up to ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            out = []
            for kind, item, key in self.subscriber.drain():
                if kind == "frame" and self.cfg.vehicles and item.header.vehicle + 1 not in self.cfg.vehicles:
                    continue
                out.append((kind, item if kind == "frame" else f"{item} ({key})"))
            if out or time.monotonic() >= deadline:
                return out
            time.sleep(0.002)

    def close(self) -> None:
        from companion.fleetnet.bus import close_session

        try:
            self.subscriber.close()
        finally:
            close_session(self.session, "the camera source's session")


class VideoCaptureFrames:
    """Frames from ``cv2.VideoCapture`` (:class:`~.node_config.VideoCaptureSource`). ``clock``:
    the monotonic clock that stamps a device's frames."""

    kind = "video"

    def __init__(self, cfg: VideoCaptureSource, clock: Callable[[], float] = time.monotonic):
        import cv2

        cfg.check_source()
        self._cv2 = cv2
        self.cfg = cfg
        self.clock = clock
        self.intrinsics = cfg.intrinsics()
        self.device = cfg.device >= 0
        self.cap = cv2.VideoCapture(cfg.device if self.device else cfg.url)
        if not self.cap.isOpened():
            self.cap.release()
            raise OSError(f"cv2.VideoCapture could not open {'device ' + str(cfg.device) if self.device else cfg.url}")
        if self.device:
            self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, cfg.width_px)
            self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, cfg.height_px)
            if cfg.fps:
                self.cap.set(cv2.CAP_PROP_FPS, cfg.fps)
        self.seq = 0
        self.ended = False
        self.t_prev = -1.0
        log.info("reading %s (%s x %s, camera %s of vehicle %d)", f"device {cfg.device}" if self.device else cfg.url,
                 cfg.width_px, cfg.height_px, cfg.camera, cfg.vehicle)

    def poll(self, timeout_s: float) -> list[tuple[str, object]]:
        """The next frame (``[]`` and :attr:`ended` at the end of the stream); a frame that does not
        fit the calibration (size, type) is ``("error", reason)``."""
        if self.ended:
            return []
        if self.cfg.max_frames and self.seq >= self.cfg.max_frames:
            self.ended = True
            return []
        ok, img = self.cap.read()
        t_read = self.clock()
        if not ok or img is None:
            self.ended = True
            return []
        seq = self.seq
        self.seq += 1
        cfg, cv2 = self.cfg, self._cv2
        if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
            return [("error", f"frame {seq}: unsupported image {img.dtype} {img.shape}")]
        if img.shape[:2] != (cfg.height_px, cfg.width_px):
            return [("error", f"size: frame {seq} is {img.shape[1]}x{img.shape[0]}, the calibration "
                              f"{cfg.width_px}x{cfg.height_px}")]
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGB)
        if self.device:
            t = t_read
        else:
            t = self.cap.get(cv2.CAP_PROP_POS_MSEC) * 1e-3
            if not (np.isfinite(t) and t > self.t_prev):  # a stream without positions: this computer's clock
                t = t_read
        self.t_prev = t
        header = CameraFrameHeader(cfg.camera, cfg.vehicle - 1, seq, t, t, cfg.width_px, cfg.height_px, "rgb8", self.intrinsics)
        return [("frame", CameraFrame(header, np.ascontiguousarray(img)))]

    def close(self) -> None:
        self.cap.release()


def open_source(setup: VisionNodeSetup, file: str = "<config>"):
    """The configured source, opened (``file``: the config's, for the errors)."""
    return ZenohFrames(setup.zenoh, file) if setup.source == "zenoh" else VideoCaptureFrames(setup.video)


def run_node(setup: VisionNodeSetup, out_dir: Path, stop: Callable[[], bool] = lambda: False,
             duration_s: float | None = None, drain_s: float = 0.5, drain_max_s: float = 5.0, source=None,
             clock: Callable[[], float] = time.monotonic, publish: Callable | None = None,
             match_timeout_s: float = 5.0) -> dict:
    """Process frames until ``stop()``, ``duration_s`` of wall time, the end of a video or
    ``idle_timeout_s`` without frames; writes the frame log and the summary into ``out_dir`` and
    returns the summary. After ``stop()``, a Zenoh source is drained until nothing has arrived
    for ``drain_s`` (the frames in flight when the publisher stopped), at most ``drain_max_s``.
    ``clock`` (monotonic seconds) times all of these. With ``setup.neighbours`` or ``setup.load``,
    each frame's neighbour poses and load observations go to ``publish(name, msg)`` (``name``:
    ``("neighbour", observer)`` or ``("load", vehicle)``, 0-based; default: a
    :class:`~.message_wire.MessagePublisher` on the Zenoh source's session, waited for until a
    companion subscribes to every key, at most ``match_timeout_s``, before the first frame)."""
    from companion.fleetnet.keys import load_key, neighbour_key

    from .message_wire import MessagePublisher, load_observations, neighbour_poses

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    node = VisionNode(setup.pipeline)
    src = open_source(setup) if source is None else source
    cameras = {(n.camera, n.marker_id): n for n in setup.neighbours}
    prefix = setup.zenoh.prefix
    keys = {("neighbour", n.observer - 1): neighbour_key(prefix, n.observer - 1) for n in setup.neighbours}
    if setup.load is not None:
        keys.update({("load", c.vehicle - 1): load_key(prefix, c.vehicle - 1) for c in setup.load.cameras})
    publisher = None
    if keys and publish is None:
        publisher = MessagePublisher(src.session, keys)
        publish = publisher.publish
        # the frames wait in the source's queue while the companions' subscriptions reach this session
        deadline = clock() + match_timeout_s
        while not publisher.matched and clock() < deadline and not stop():
            time.sleep(0.01)
        if not publisher.matched:
            log.warning("no companion takes every key of the consumer's measurements yet (%s): publishing anyway",
                        ", ".join(sorted(set(keys.values()))))
    sent = {"published": 0, "wrong_vehicle": 0}
    sent_load = {"published": 0, "wrong_vehicle": 0}
    wall0 = clock()
    last_frame = wall0
    reason = "stopped"
    try:
        with open(out_dir / FRAMES_FILE, "w", buffering=1) as fh:
            draining_since = None
            while True:
                now = clock()
                if draining_since is None and stop():
                    draining_since = now
                    if src.kind != "zenoh":
                        break
                if draining_since is not None and (now - max(draining_since, last_frame) >= drain_s
                                                   or now - draining_since >= drain_max_s):
                    break
                if duration_s is not None and now - wall0 >= duration_s:
                    reason = "duration"
                    break
                if setup.idle_timeout_s and now - last_frame >= setup.idle_timeout_s:
                    reason = "idle"
                    break
                events = src.poll(0.05)
                if not events and getattr(src, "ended", False):
                    reason = "end of stream"
                    break
                for kind, item in events:
                    if kind == "error":
                        node.on_rejected(str(item))
                        if node.rejected <= 5 or node.rejected % 100 == 0:  # a flood stays quiet
                            log.warning("rejected #%d: %s", node.rejected, item)
                        continue
                    last_frame = clock()
                    record = node.on_frame(item)
                    fh.write(json.dumps(record.to_json()) + "\n")
                    if cameras:
                        poses, wrong = neighbour_poses(record, cameras)
                        sent["wrong_vehicle"] += wrong
                        for pose in poses:
                            publish(("neighbour", pose.observer), pose)
                            sent["published"] += 1
                    if setup.load is not None:
                        observations, wrong = load_observations(record, setup.load)
                        sent_load["wrong_vehicle"] += wrong
                        for obs in observations:
                            publish(("load", obs.vehicle), obs)
                            sent_load["published"] += 1
    finally:
        if publisher is not None:
            publisher.close()
        src.close()
    wall = clock() - wall0
    summary = {"name": setup.name, "source": setup.source, "ended_by": reason, "wall_s": round(wall, 3), **node.summary()}
    summary["frames_per_s"] = round(summary["frames_total"] / wall, 3) if wall > 0 else None
    if cameras:
        summary["neighbour_poses"] = sent
    if setup.load is not None:
        summary["load_observations"] = sent_load
    (out_dir / SUMMARY_FILE).write_text(json.dumps(summary, indent=2) + "\n")
    log.info("%d frames (%d with a marker), %d rejected; detection + PnP %s ms per frame; ended by %s",
             summary["frames_total"], summary["frames_detected"], summary["rejected_payloads"],
             (summary["detect_pnp_ms"] or {}).get("mean"), reason)
    return summary


def read_frame_log(path: Path) -> list[dict]:
    """The records of a ``vision_frames.jsonl`` (a truncated last line, from a killed consumer, is skipped)."""
    out = []
    for line in Path(path).read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out

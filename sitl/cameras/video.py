"""Video of a flight (``python -m sitl fly --video PATH``): an MP4 from a chase camera, with a
picture-in-picture of one onboard camera and the detected markers' axes when the scenario has cameras.

The chase camera is a MuJoCo free camera looking at the model's centre of mass from a fixed
azimuth and elevation (it follows the flight, it does not turn with it). Frames are rendered
offscreen (:mod:`sitl.cameras.rendering`: a headless backend, osmesa on the CPU) at the video's rate of
*simulation* time (``fps`` frames per simulated second, at the nearest physics tick), not at
every physics step, so the file plays at real-time speed; each frame costs one render. The onboard inset is the newest frame that
camera has delivered (its rate and latency: what the companion sees), annotated with the markers
the companion's pipeline (:class:`~companion.vision.pnp.MarkerPipeline`) found in it: outline,
id and the estimated axes (x red, y green, z blue, as the report's Fig. 2).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import mujoco
import numpy as np

from companion.vision.config import DetectorConfig, PipelineConfig
from companion.vision.pnp import MarkerPipeline

from .rig import CameraRig, fast_renderer
from .rendering import require_rendering
from .config import MarkerMount

__all__ = ["VideoConfig", "VideoRecorder", "pipeline_config"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VideoConfig:
    """The video: ``fps`` frames per simulated second, size, the chase camera's azimuth and
    elevation [deg] and distance [m] (``None``: from the model's size), the onboard camera shown
    in the inset (``None``: the first), the inset's width as a fraction of the frame's, and
    shadows and reflections (off: they cost most of a CPU render, :func:`~sitl.cameras.rig.fast_renderer`)."""

    fps: float = 30.0
    width_px: int = 640
    height_px: int = 480
    azimuth_deg: float = 135.0
    elevation_deg: float = -20.0
    distance_m: float | None = None
    pip_camera: str | None = None
    pip_fraction: float = 0.38
    shadows: bool = False

    def __post_init__(self) -> None:
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        if self.width_px < 16 or self.height_px < 16:
            raise ValueError(f"video size must be at least 16x16, got {self.width_px}x{self.height_px}")
        if not 0 < self.pip_fraction <= 1:
            raise ValueError(f"pip_fraction must be in (0, 1], got {self.pip_fraction}")


def pipeline_config(markers: tuple[MarkerMount, ...]) -> PipelineConfig:
    """The companion pipeline's config for a scenario's markers (their dictionary and sizes)."""
    if not markers:
        return PipelineConfig()
    dictionaries = {m.dictionary for m in markers}
    if len(dictionaries) > 1:
        log.warning("markers of several dictionaries (%s): the pipeline looks for %s only",
                    ", ".join(sorted(dictionaries)), markers[0].dictionary)
    return PipelineConfig(detector=DetectorConfig(dictionary=markers[0].dictionary),
                          marker_length_m=markers[0].size_m,
                          marker_lengths_m={str(m.id): m.size_m for m in markers})


def annotate(image_rgb: np.ndarray, intr, poses, detections=()) -> np.ndarray:
    """A BGR copy of ``image_rgb`` with the detected markers' outlines and estimated axes."""
    out = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR)
    for d in detections:
        pts = d.corners_px
        if intr.distorted:  # corners are undistorted; draw them where the image has them
            norm = cv2.undistortPoints(pts.reshape(-1, 1, 2), intr.K, np.zeros(5)).reshape(-1, 2)
            pts, _ = cv2.projectPoints(np.column_stack((norm, np.ones(len(norm)))), np.zeros(3), np.zeros(3),
                                       intr.K, intr.dist)
        cv2.polylines(out, [np.rint(pts.reshape(-1, 2)).astype(np.int32)], True, (0, 255, 255), 1, cv2.LINE_AA)
    for p in poses:
        rvec, _ = cv2.Rodrigues(p.R_cm)
        length = 0.6 * max(p.side_px, 1.0) * p.t_cm_m[2] / intr.fx_px
        cv2.drawFrameAxes(out, intr.K, intr.dist, rvec, p.t_cm_m, length, 2)
        c = intr.K @ (p.t_cm_m / p.t_cm_m[2])
        cv2.putText(out, f"id {p.marker_id}", (int(c[0]) + 5, int(c[1]) - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 255, 255), 1, cv2.LINE_AA)
    return out


class VideoRecorder:
    """Writes ``path`` (MP4, ``mp4v``) from the chase camera, with the onboard inset when ``rig``
    has cameras. Call :meth:`on_tick` at every physics tick after the kinematics (as
    :class:`~sitl.cameras.rig.CameraRig`); :meth:`close` finishes the file and frees the renderer."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, path: str | Path, dt_s: float,
                 cfg: VideoConfig = VideoConfig(), rig: CameraRig | None = None,
                 markers: tuple[MarkerMount, ...] = (), title: str = ""):
        require_rendering()
        self.model, self.data, self.dt, self.cfg, self.rig = model, data, dt_s, cfg, rig
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.title = title
        off = model.vis.global_
        if cfg.width_px > off.offwidth or cfg.height_px > off.offheight:
            raise ValueError(f"video {cfg.width_px}x{cfg.height_px} is larger than the model's offscreen buffer "
                             f"{off.offwidth}x{off.offheight}")
        self.writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), cfg.fps,
                                      (cfg.width_px, cfg.height_px))
        if not self.writer.isOpened():
            raise RuntimeError(f"cannot open {self.path} for writing (OpenCV's mp4v encoder)")
        self.renderer = fast_renderer(model, cfg.height_px, cfg.width_px, shadows=cfg.shadows)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.azimuth = cfg.azimuth_deg
        self.camera.elevation = cfg.elevation_deg
        self.camera.distance = cfg.distance_m if cfg.distance_m is not None else self._distance()
        self.pip_index = None
        if rig is not None and rig.cameras:
            names = [c.mount.name for c in rig.cameras]
            if cfg.pip_camera is not None and cfg.pip_camera not in names:
                raise ValueError(f"pip_camera: no camera {cfg.pip_camera!r} (cameras: {', '.join(names)})")
            self.pip_index = names.index(cfg.pip_camera) if cfg.pip_camera is not None else 0
            self.pipeline = MarkerPipeline(pipeline_config(markers))
        self._pip_cache: tuple[int, np.ndarray] | None = None
        self.frames = 0
        self.next_tick: int | None = None
        self.render_s = 0.0

    def _distance(self) -> float:
        """A distance that frames the bodies' spread at the start (at least 3 m)."""
        x = self.data.xpos[1:]
        spread = float(np.max(np.linalg.norm(x - x.mean(axis=0), axis=1))) if len(x) else 1.0
        return max(3.0, 3.0 * spread + 2.0)

    def _pip(self) -> np.ndarray | None:
        f = self.rig.latest.get(self.pip_index) if self.rig is not None else None
        if f is None:
            return None
        seq = f.frame.header.seq
        if self._pip_cache is None or self._pip_cache[0] != seq:
            intr = f.frame.header.intrinsics
            dets, poses = self.pipeline.measure(f.frame.image, intr)
            img = annotate(f.frame.image, intr, poses, dets)
            cv2.putText(img, f"{f.frame.header.camera} t={f.frame.header.t_capture_s:.2f}s", (6, 18),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
            w = int(self.cfg.width_px * self.cfg.pip_fraction)
            h = int(round(w * img.shape[0] / img.shape[1]))
            self._pip_cache = (seq, cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA))
        return self._pip_cache[1]

    def on_tick(self, k: int, t_s: float) -> None:
        if self.next_tick is None:
            self.next_tick = k
            self._k0 = k
        if k < self.next_tick:
            return
        w0 = time.perf_counter()
        self.camera.lookat[:] = self.data.subtree_com[0]
        self.renderer.update_scene(self.data, camera=self.camera)
        frame = cv2.cvtColor(self.renderer.render(), cv2.COLOR_RGB2BGR)
        pip = self._pip() if self.pip_index is not None else None
        if pip is not None:
            h, w = pip.shape[:2]
            x0 = frame.shape[1] - w - 8
            frame[8:8 + h, x0:x0 + w] = pip
            cv2.rectangle(frame, (x0 - 1, 7), (x0 + w, 8 + h), (255, 255, 255), 1)
        cv2.putText(frame, f"{self.title}  t = {t_s:6.2f} s", (8, frame.shape[0] - 10), cv2.FONT_HERSHEY_SIMPLEX,
                    0.5, (255, 255, 255), 1, cv2.LINE_AA)
        self.writer.write(frame)
        self.render_s += time.perf_counter() - w0
        self.frames += 1
        self.next_tick = self._k0 + int(round(self.frames / (self.cfg.fps * self.dt)))

    def stats(self) -> dict:
        return {"path": str(self.path), "frames": self.frames, "fps": self.cfg.fps,
                "size_px": [self.cfg.width_px, self.cfg.height_px],
                "ms_per_frame": 1e3 * self.render_s / self.frames if self.frames else None}

    def close(self) -> None:
        if self.writer is not None:
            self.writer.release()
            self.writer = None
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None

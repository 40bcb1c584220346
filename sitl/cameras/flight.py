"""A batch flight's cameras, vision log and video, as tick hooks of :class:`~sitl.runner.BatchRunner`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sitl.watch import announce

__all__ = ["FlightCameras"]


class FlightCameras:
    """The cameras (:class:`~sitl.cameras.rig.CameraRig`), the vision log and the video of one
    flight, as tick hooks of the runner; closes their renderers and the video file on exit.

    Every delivered frame goes to the vision log (:class:`~sitl.cameras.vision_log.VisionLog`)
    and then to each of ``consumers`` (a scenario's own estimator). Nothing is rendered (nor
    OpenCV imported) for a scenario without cameras and without ``video``."""

    def __init__(self, runner, video: Path | None, consumers=()):
        self.runner, self.video_path = runner, video
        #: called with every delivered frame after the vision log (a live view adds itself)
        self.consumers = list(consumers)
        self.rig = self.log = self.video = None
        #: every delivered frame as JPEG (:class:`~sitl.cameras.frame_archive.FrameArchive`), with cameras
        self.frames = None

    def __enter__(self) -> FlightCameras:
        sc, runner = self.runner.scenario, self.runner
        if not sc.cameras and self.video_path is None:
            return self
        from .frame_archive import FrameArchive
        from .rig import CameraRig  # OpenCV and rendering only for these flights
        from .video import VideoRecorder
        from .vision_log import VisionLog

        model, data = runner.model.model, runner.model.data
        try:
            if sc.cameras:
                self.rig = CameraRig(model, data, sc.cameras, sc.markers, runner.dt, sc.seed, scene=sc.scene)
                self.log = VisionLog(sc.markers)
                self.frames = FrameArchive([c.name for c in sc.cameras])
                runner.tick_hooks.append(self._cameras)
                announce(self)
            if self.video_path is not None:
                self.video = VideoRecorder(model, data, self.video_path, runner.dt, rig=self.rig, markers=sc.markers,
                                           title=sc.name)
                runner.tick_hooks.append(self.video.on_tick)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _cameras(self, k: int, t: float) -> None:
        self.rig.on_tick(k, t)
        for frame in self.rig.poll(t):
            self.log.on_frame(frame)
            self.frames.on_frame(frame)
            for consumer in self.consumers:
                consumer(frame)

    def save_frames(self, out_dir) -> None:
        """The frames as ``camera_frames.npz`` in ``out_dir`` (nothing without cameras)."""
        if self.frames is not None:
            from .frame_archive import FRAMES_NAME

            np.savez(Path(out_dir) / FRAMES_NAME, **self.frames.arrays())

    def metrics(self) -> dict:
        out = {}
        if self.log is not None:
            out["vision"] = self.log.metrics()
            out["vision"]["render_ms_per_frame"] = 1e3 * self.rig.render_s / self.rig.renders if self.rig.renders else None
            out["vision"]["frames_dropped"] = dict(self.rig.dropped)
        if self.video is not None:
            out["video"] = self.video.stats()
        return out

    def __exit__(self, *exc) -> None:
        for hook in (self._cameras, getattr(self.video, "on_tick", None)):
            if hook in self.runner.tick_hooks:
                self.runner.tick_hooks.remove(hook)
        if self.video is not None:
            self.video.close()
        if self.rig is not None:
            self.rig.close()

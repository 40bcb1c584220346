"""Camera frame in, eq. 4 measurement of the slung load out (the report's sec. III-IV).

One :class:`LoadVisionPipeline` serves every carrying vehicle's camera: a frame
(:class:`~companion.vision.frame.CameraFrame`, from the SITL's renderer, a Zenoh subscriber or a
``cv2.VideoCapture`` on the onboard computer) goes through the marker pipeline
(:class:`~companion.vision.pnp.MarkerPipeline`: ArUco detection with corner refinement, PnP,
the IPPE ambiguity, a covariance per detection); the load's marker pose becomes the vehicle's
position in the load frame with its covariance
(:func:`~companion.load.model.observation_from_pnp`, eq. 4), stamped with the frame's
capture time. The filters (:mod:`.filter`) take it from there.

Pure: no sockets, clocks or threads (the caller times it if it wants to). OpenCV through
:mod:`companion.vision.pnp` (the ``vision`` extra).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from companion.vision.frame import CameraFrame
from companion.vision.pnp import MarkerPipeline, MarkerPose, PipelineConfig

from .measurements import observation_from_pnp
from .model import LoadObservation, Pose3

__all__ = ["LoadVisionResult", "LoadVisionPipeline"]


@dataclass(frozen=True)
class LoadVisionResult:
    """What one frame gave: the number of markers detected, the load marker's PnP pose (``None``:
    not seen) and eq. 4's observation from it (``None`` likewise)."""

    detections: int
    pose: MarkerPose | None
    observation: LoadObservation | None


class LoadVisionPipeline:
    """Frames of the carrying vehicles' cameras -> :class:`~.load_model.LoadObservation`.

    ``cameras_in_body``: by camera name, the camera's pose in its vehicle's body frame (OpenCV
    camera axes); the frame header's ``vehicle`` says which vehicle (cable) it belongs to.
    ``marker_id`` and ``marker_in_load``: the load's marker and its pose in the load's body frame.
    One :class:`~.pnp.MarkerPipeline` per camera keeps each camera's continuity for the IPPE
    ambiguity."""

    def __init__(self, cfg: PipelineConfig, cameras_in_body: Mapping[str, Pose3], marker_id: int,
                 marker_in_load: Pose3):
        if not cameras_in_body:
            raise ValueError("cameras_in_body: at least one camera")
        self.cfg = cfg
        self.cameras_in_body = dict(cameras_in_body)
        self.marker_id = int(marker_id)
        self.marker_in_load = marker_in_load
        self._pipes = {name: MarkerPipeline(cfg) for name in self.cameras_in_body}

    def on_frame(self, frame: CameraFrame) -> LoadVisionResult:
        """Detect, estimate and convert one frame (``ValueError`` for a camera it does not know)."""
        h = frame.header
        pipe = self._pipes.get(h.camera)
        if pipe is None:
            raise ValueError(f"frame of camera {h.camera!r}; known: {', '.join(self._pipes)}")
        dets, poses = pipe.measure(frame.image, h.intrinsics)
        pose = next((p for p in poses if p.marker_id == self.marker_id), None)
        if pose is None:
            return LoadVisionResult(len(dets), None, None)
        obs = observation_from_pnp(h.vehicle, h.t_capture_s, pose.R_cm, pose.t_cm_m, pose.cov,
                                   self.cameras_in_body[h.camera], self.marker_in_load)
        return LoadVisionResult(len(dets), pose, obs)

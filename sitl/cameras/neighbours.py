"""Chain cameras seeing their neighbours' markers, fed to the companion's step (batch mode).

A scenario puts a camera on link ``i`` (``body = "link<i>"``) and a marker on a neighbouring link
(``body = "link<i+1>"`` or ``"link<i-1>"``). Each delivered frame of such a camera goes through
the companion's marker pipeline (one per camera, so its continuity state is that camera's); each
neighbour marker's pose, with the covariance its reprojection geometry gives
(:func:`companion.vision.pnp.pose_covariance`), becomes a
:class:`~companion.estimation.neighbour.NeighbourMeasurement` for the engine that steps both links
(:meth:`companion.engine.CompanionEngine.on_neighbour`), stamped with the frame's capture time on
the simulation clock (the links' clock in batch mode). Markers on the ground or elsewhere are left
to the other consumers. :meth:`NeighbourCameras.metrics` counts frames, poses and the poses'
errors against the truth at capture.
"""

from __future__ import annotations

import numpy as np

from companion.estimation.neighbour import NeighbourMeasurement, NeighbourView
from companion.estimation.so3 import quat_to_rotvec, rotmat_to_quat
from companion.vision.geometry import geodesic_angle_rad
from companion.vision.node_config import NeighbourCamera
from companion.vision.pnp import MarkerPipeline

from .config import CameraMount, MarkerMount, link_of
from .rig import CapturedFrame
from .video import pipeline_config

__all__ = ["neighbour_views", "neighbour_cameras", "NeighbourCameras"]


def neighbour_views(cameras: tuple[CameraMount, ...], markers: tuple[MarkerMount, ...]
                    ) -> dict[str, dict[int, tuple[int, int, NeighbourView]]]:
    """By camera name, the markers it may see on a neighbouring link: marker id -> ``(observer
    link, observed link, view)`` (0-based links)."""
    out: dict[str, dict[int, tuple[int, int, NeighbourView]]] = {}
    for cam in cameras:
        i = link_of(cam.body)
        if i is None:
            continue
        for mk in markers:
            j = link_of(mk.body)
            if j is not None and abs(i - j) == 1:
                view = NeighbourView(np.asarray(cam.pos_b_m, dtype=float), cam.R_b_c(),
                                     np.asarray(mk.pos_b_m, dtype=float), mk.R_b_m())
                out.setdefault(cam.name, {})[mk.id] = (i, j, view)
    return out


def neighbour_cameras(cameras: tuple[CameraMount, ...], markers: tuple[MarkerMount, ...]) -> tuple[NeighbourCamera, ...]:
    """The vision consumer's ``[[neighbours]]`` list of these mounts (fleet mode: the consumer
    publishes what :func:`neighbour_views` would feed the engines in batch mode)."""
    return tuple(NeighbourCamera(name, i + 1, j + 1, marker_id, tuple(map(float, view.camera_pos_b_m)),
                                 tuple(map(float, rotmat_to_quat(view.R_b_c))), tuple(map(float, view.marker_pos_b_m)),
                                 tuple(map(float, rotmat_to_quat(view.R_b_m))))
                 for name, views in neighbour_views(cameras, markers).items()
                 for marker_id, (i, j, view) in sorted(views.items()))


class NeighbourCameras:
    """The consumer (a :class:`~sitl.cameras.flight.FlightCameras` consumer): ``engines`` are the
    runner's companion engines (each measurement goes to the one whose links hold both links)."""

    def __init__(self, cameras: tuple[CameraMount, ...], markers: tuple[MarkerMount, ...], engines):
        self.views = neighbour_views(cameras, markers)
        cfg = pipeline_config(markers)
        self.pipelines = {name: MarkerPipeline(cfg) for name in self.views}
        self.engines = list(engines)
        self.frames = 0
        #: (t_capture, observer, observed, pos err [m], att err [deg], range [m], NEES of the pose's covariance)
        self.rows: list[tuple] = []
        self.no_engine = 0

    def __bool__(self) -> bool:
        return bool(self.views)

    def _engine_rows(self, i: int, j: int):
        for engine in self.engines:
            rows = {lk.index: lk.row for lk in engine.links}
            if i in rows and j in rows:
                return engine, rows[i], rows[j]
        return None

    def on_frame(self, f: CapturedFrame) -> None:
        h = f.frame.header
        views = self.views.get(h.camera)
        if not views:
            return
        self.frames += 1
        for pose in self.pipelines[h.camera](f.frame.image, h.intrinsics):
            if pose.marker_id not in views:
                continue
            i, j, view = views[pose.marker_id]
            R_true, t_true = f.truth.marker_in_camera(pose.marker_id)
            err = np.r_[quat_to_rotvec(rotmat_to_quat(pose.R_cm @ R_true.T)), pose.t_cm_m - t_true]
            self.rows.append((h.t_capture_s, i, j, float(np.linalg.norm(pose.t_cm_m - t_true)),
                              float(np.degrees(geodesic_angle_rad(pose.R_cm, R_true))), float(np.linalg.norm(t_true)),
                              float(err @ np.linalg.solve(pose.cov, err))))
            target = self._engine_rows(i, j)
            if target is None:
                self.no_engine += 1
                continue
            engine, ri, rj = target
            engine.on_neighbour(h.t_capture_s, NeighbourMeasurement(ri, rj, pose.R_cm, pose.t_cm_m, pose.cov, view))

    def metrics(self) -> dict:
        """``metrics.json``'s ``neighbour_cameras``: frames, poses of neighbour markers, their
        errors (RMS, max) against the truth at capture and the mean NEES of their covariances (6
        degrees of freedom: about 6 when the covariance is right), those no engine could take, and
        each engine's count of what its steps did with them."""
        r = np.array(self.rows, dtype=float).reshape(-1, 7)
        out = {"frames": self.frames, "poses": int(r.shape[0]), "no_engine": self.no_engine}
        if r.shape[0]:
            out.update(pos_err_rms_m=float(np.sqrt(np.mean(r[:, 3] ** 2))), pos_err_max_m=float(r[:, 3].max()),
                       att_err_rms_deg=float(np.sqrt(np.mean(r[:, 4] ** 2))), att_err_max_deg=float(r[:, 4].max()),
                       range_mean_m=float(r[:, 5].mean()), pose_nees_mean=float(r[:, 6].mean()))
        out["steps"] = [e.summary()["neighbour_measurements"] for e in self.engines]
        return out

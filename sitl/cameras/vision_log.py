"""The vision measurement of a flight: every delivered camera frame through the companion's
pipeline, every PnP method, errors against the ground truth at capture.

For each frame (:class:`~sitl.cameras.rig.CapturedFrame`) the markers are detected once and each PnP
method of :data:`~companion.vision.pnp.PNP_METHODS` estimates every detected marker's pose in the
camera frame, with the continuity state of that method and that camera for the IPPE ambiguity
(as the companion's pipeline keeps one per camera: another camera's previous pose of the same
marker is another pose). Errors follow the report:
eq. 2 (translation error; its norm here) and eq. 3 (geodesic angle). The detection and PnP
times are wall-clock per frame (noisy on a shared machine). :meth:`VisionLog.metrics` gives
``metrics.json``'s ``vision`` entry; :meth:`VisionLog.arrays` the per-detection series.
"""

from __future__ import annotations

import time

import numpy as np

from companion.vision.geometry import geodesic_angle_rad, translation_error_m
from companion.vision.markers import detect_markers
from companion.vision.pnp import PNP_METHODS, MarkerPipeline, configured_pose

from .rig import CapturedFrame
from .config import MarkerMount
from .video import pipeline_config

__all__ = ["VisionLog"]


class VisionLog:
    """Runs the pipeline on delivered frames and records errors (see the module docstring)."""

    def __init__(self, markers: tuple[MarkerMount, ...], methods: tuple[str, ...] = tuple(PNP_METHODS)):
        self.cfg = pipeline_config(markers)
        self.methods = methods
        self.detector = MarkerPipeline(self.cfg, method=methods[0]).detector
        self.previous: dict[tuple[str, str], dict] = {}  # (method, camera) -> marker id -> its last pose
        self.frames: dict[str, int] = {}
        self.detected: dict[str, int] = {}
        self.detect_s: list[float] = []
        self.pnp_s: dict[str, list[float]] = {m: [] for m in methods}
        self.rows: list[tuple] = []  # (t_capture, camera index, id, method index, pos err, att err, range, side, amb)

    def on_frame(self, f: CapturedFrame) -> None:
        h = f.frame.header
        self.frames[h.camera] = self.frames.get(h.camera, 0) + 1
        w0 = time.perf_counter()
        dets = detect_markers(f.frame.image, self.detector, h.intrinsics)
        dets = tuple(d for d in dets if d.marker_id in f.truth.markers)
        self.detect_s.append(time.perf_counter() - w0)
        if dets:
            self.detected[h.camera] = self.detected.get(h.camera, 0) + 1
        for j, method in enumerate(self.methods):
            previous = self.previous.setdefault((method, h.camera), {})
            w0 = time.perf_counter()
            poses = []
            for d in dets:
                pose = configured_pose(d, h.intrinsics, self.cfg, method, previous)
                if pose is not None:
                    previous[d.marker_id] = pose
                    poses.append(pose)
            self.pnp_s[method].append(time.perf_counter() - w0)
            for p in poses:
                R_true, t_true = f.truth.marker_in_camera(p.marker_id)
                self.rows.append((h.t_capture_s, f.camera_index, p.marker_id, j,
                                  float(np.linalg.norm(translation_error_m(p.t_cm_m, t_true))),
                                  float(np.degrees(geodesic_angle_rad(p.R_cm, R_true))),
                                  float(np.linalg.norm(t_true)), p.side_px, p.ambiguous))

    def arrays(self) -> dict[str, np.ndarray]:
        r = np.array(self.rows, dtype=float).reshape(-1, 9)
        return {"vision_t": r[:, 0], "vision_camera": r[:, 1].astype(int), "vision_marker": r[:, 2].astype(int),
                "vision_method": r[:, 3].astype(int), "vision_pos_err_m": r[:, 4], "vision_att_err_deg": r[:, 5],
                "vision_range_m": r[:, 6], "vision_side_px": r[:, 7], "vision_ambiguous": r[:, 8].astype(bool),
                "vision_methods": np.array(self.methods)}

    def metrics(self) -> dict:
        a = self.arrays()
        n_frames = sum(self.frames.values())
        per_method = {}
        for j, m in enumerate(self.methods):
            sel = a["vision_method"] == j
            pe, ae = a["vision_pos_err_m"][sel], a["vision_att_err_deg"][sel]
            per_method[m] = {
                "poses": int(sel.sum()),
                "pos_rms_m": float(np.sqrt(np.mean(pe**2))) if len(pe) else None,
                "pos_p95_m": float(np.percentile(pe, 95)) if len(pe) else None,
                "pos_max_m": float(pe.max()) if len(pe) else None,
                "att_rms_deg": float(np.sqrt(np.mean(ae**2))) if len(ae) else None,
                "att_p95_deg": float(np.percentile(ae, 95)) if len(ae) else None,
                "ambiguous_fraction": float(a["vision_ambiguous"][sel].mean()) if len(pe) else None,
                "pnp_ms_per_frame": 1e3 * float(np.mean(self.pnp_s[m])) if self.pnp_s[m] else None,
            }
        return {
            "frames": dict(self.frames),
            "detection_rate": {c: self.detected.get(c, 0) / n for c, n in self.frames.items()},
            "detect_ms_per_frame": 1e3 * float(np.mean(self.detect_s)) if self.detect_s else None,
            "pnp": per_method,
            "frames_total": n_frames,
        }

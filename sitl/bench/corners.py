"""Corner refinement measured on rendered frames: which of OpenCV's ArUco refinements finds the
corners where they are, and what each does to the marker's pose.

A scenario with cameras is flown in batch mode (:mod:`sitl.scenarios`); every frame its cameras
deliver also goes to :class:`CornerLog`, which detects the markers once per refinement method
(:data:`companion.vision.config.CORNER_REFINEMENTS`: ``none``, ``subpix``, ``contour``, ``apriltag``)
and compares each detected corner with the true one, the marker's corners at its true pose
projected with the camera's intrinsics (:func:`~companion.vision.geometry.project_points`; the
detector's corners are undistorted to the same pinhole pixels). Per method:

* ``corner_rms_px``: RMS over corners of the distance to the true corner;
* ``inward_bias_px``: the mean error along the direction to the marker's centre (positive: the
  corners found inside the true square, which makes the marker look smaller, hence farther);
* ``range_bias_cm`` / ``range_std_cm``: the PnP distance (IPPE square, the companion's default,
  each camera with its own continuity) minus the true distance, mean and spread;
* ``pos_rms_cm`` / ``att_rms_deg``: the pose's translation and attitude error (report eqs. 2, 3);
* ``detect_ms_per_frame``: the detector's wall time per frame with that refinement.

The CLI is ``python -m sitl.bench corners``.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.vision.config import CORNER_REFINEMENTS

__all__ = ["REFINEMENTS", "CornerLog", "run_corners", "format_corners", "markdown_corners"]

#: every refinement the bench measures
REFINEMENTS = CORNER_REFINEMENTS


class CornerLog:
    """A frame consumer (:class:`~sitl.cameras.flight.FlightCameras`) that measures every
    refinement method on every delivered frame (module docstring)."""

    def __init__(self, markers, refinements: tuple[str, ...] = REFINEMENTS):
        from companion.vision.markers import make_detector
        from sitl.cameras.video import pipeline_config

        self.cfg = pipeline_config(markers)
        self.refinements = refinements
        self.detectors = {r: make_detector(replace(self.cfg.detector, corner_refinement=r)) for r in refinements}
        self.previous: dict[tuple[str, str], dict] = {}
        self.detect_s: dict[str, list[float]] = {r: [] for r in refinements}
        # per detection: refinement, corner error norms (4), inward errors (4), range error, position error, attitude
        self.rows: dict[str, list[tuple]] = {r: [] for r in refinements}
        self.frames = 0

    def on_frame(self, captured) -> None:
        from companion.vision.geometry import (geodesic_angle_rad, project_points, transform_points,
                                               translation_error_m)
        from companion.vision.markers import detect_markers, marker_object_points
        from companion.vision.pnp import configured_pose

        h, truth = captured.frame.header, captured.truth
        self.frames += 1
        for r in self.refinements:
            t0 = time.perf_counter()
            dets = detect_markers(captured.frame.image, self.detectors[r], h.intrinsics)
            self.detect_s[r].append(time.perf_counter() - t0)
            previous = self.previous.setdefault((r, h.camera), {})
            for d in dets:
                if d.marker_id not in truth.markers:
                    continue
                length = self.cfg.length_m(d.marker_id)
                R_true, t_true = truth.marker_in_camera(d.marker_id)
                true_px = project_points(transform_points(R_true, t_true, marker_object_points(length)), h.intrinsics)
                err = d.corners_px - true_px
                to_centre = true_px.mean(axis=0) - true_px
                inward = np.sum(err * to_centre, axis=1) / np.linalg.norm(to_centre, axis=1)
                pose = configured_pose(d, h.intrinsics, self.cfg, previous=previous)
                if pose is None:
                    continue
                previous[d.marker_id] = pose
                self.rows[r].append((*np.linalg.norm(err, axis=1), *inward,
                                     float(np.linalg.norm(pose.t_cm_m) - np.linalg.norm(t_true)),
                                     float(np.linalg.norm(translation_error_m(pose.t_cm_m, t_true))),
                                     float(np.degrees(geodesic_angle_rad(pose.R_cm, R_true)))))

    def metrics(self) -> dict:
        out = {}
        for r in self.refinements:
            a = np.array(self.rows[r], dtype=float).reshape(-1, 11)
            n = len(a)

            def rms(x):
                return float(np.sqrt(np.mean(x ** 2))) if n else None

            out[r] = {
                "detections": n,
                "corner_rms_px": rms(a[:, 0:4].ravel()),
                "inward_bias_px": float(a[:, 4:8].mean()) if n else None,
                "range_bias_cm": 100 * float(a[:, 8].mean()) if n else None,
                "range_std_cm": 100 * float(a[:, 8].std()) if n else None,
                "pos_rms_cm": 100 * rms(a[:, 9]) if n else None,
                "att_rms_deg": rms(a[:, 10]),
                "detect_ms_per_frame": 1e3 * float(np.mean(self.detect_s[r])) if self.detect_s[r] else None,
            }
        return out


def run_corners(config: str | Path, out_dir: Path, duration_s: float | None = None, seed: int | None = None,
                progress=None) -> dict:
    """Fly ``config`` (a scenario with cameras) into ``out_dir`` with a :class:`CornerLog` on its
    frames; the measurement per refinement, with the scenario's own refinement named
    (``configured``). ``ValueError`` for a scenario without cameras or markers."""
    from sitl.cameras.rendering import choose_backend, require_rendering
    from sitl.scenarios import load
    from sitl.watch import watching

    overrides = {k: v for k, v in (("duration_s", duration_s), ("seed", seed)) if v is not None}
    kind, sc = load(config, **overrides)
    if not sc.cameras or not sc.markers:
        raise ValueError(f"{config}: the scenario has no cameras or no markers: nothing to measure")
    choose_backend(True)
    require_rendering()
    log = CornerLog(sc.markers)

    from sitl.cameras.flight import FlightCameras

    def attach(sim) -> None:
        if isinstance(sim, FlightCameras):
            sim.consumers.append(log.on_frame)

    with watching(attach):
        flight = kind.fly(sc, out_dir, plots=False, progress=progress)
    return {"scenario": sc.name, "duration_s": sc.duration_s, "seed": sc.seed, "frames": log.frames,
            "cameras": [c.name for c in sc.cameras], "configured": log.cfg.detector.corner_refinement,
            "pnp_method": log.cfg.method, "crashed": bool(flight.get("crashed")), "refinements": log.metrics()}


_COLUMNS = (("corner_rms_px", "corner RMS [px]", ".3f"), ("inward_bias_px", "inward bias [px]", "+.3f"),
            ("range_bias_cm", "range bias [cm]", "+.2f"), ("range_std_cm", "range std [cm]", ".2f"),
            ("pos_rms_cm", "position RMS [cm]", ".2f"), ("att_rms_deg", "attitude RMS [deg]", ".2f"),
            ("detect_ms_per_frame", "detect [ms/frame]", ".2f"))


def _cells(row: dict) -> list[str]:
    return [str(row["detections"])] + ["-" if row[k] is None else format(row[k], f) for k, _, f in _COLUMNS]


def _intro(result: dict) -> str:
    return (f"{result['scenario']}, {result['duration_s']:g} s, seed {result['seed']}: {result['frames']} frames of "
            f"{', '.join(result['cameras'])}; PnP {result['pnp_method']}; the scenario's refinement: "
            f"{result['configured']}")


def format_corners(result: dict) -> str:
    """The console table: a row per refinement."""
    head = ["refinement", "detections", *(t for _, t, _ in _COLUMNS)]
    rows = [[r, *_cells(row)] for r, row in result["refinements"].items()]
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    lines = [_intro(result), ""] + ["  ".join(str(x).rjust(w) for x, w in zip(line, widths)) for line in [head, *rows]]
    return "\n".join(lines)


def markdown_corners(result: dict) -> str:
    """The Markdown report: the same table."""
    from .report import md_table

    rows = [(r, *_cells(row)) for r, row in result["refinements"].items()]
    return "\n".join([_intro(result) + ". Errors against the true corners and pose at each frame's capture.", "",
                      md_table(("refinement", "detections", *(t for _, t, _ in _COLUMNS)), rows)])

"""Marker pose by PnP (the report's eq. 1), its ambiguity and covariance, and the image-to-pose pipeline.

Methods (OpenCV's ``solvePnPGeneric``): ``ippe_square`` (IPPE for a square planar target: two
solutions), ``p3p`` (minimal: three corners solve, the fourth picks among up to four solutions),
``sqpnp`` and ``iterative`` (Levenberg-Marquardt from a homography start). The ``refine`` option
polishes any of them with ``solvePnPRefineLM`` on all four corners.

**IPPE's two-fold ambiguity.** A small or nearly fronto-parallel planar square fits two poses,
mirrored about the line of sight (the report's "flipping of the z-axis", sec. III-A). When the
worse solution's reprojection error is at least ``ambiguity_ratio`` times the better's, the
better one is kept; otherwise the pose is *ambiguous* and the solution closest (eq. 3 angle) to
the previous estimate of that marker is kept, or, with none, the better one, flagged.

**P3P's spikes.** P3P solves from three corners only; the fourth only selects among its up to four
solutions. When the marker is small in the image the corners' pixel noise is a large fraction of
their spread, the three-point solutions move far and the fourth corner cannot tell them apart:
the translation jumps by metres along the line of sight (the report's 2 m spikes). Using all four
corners (IPPE square, SQPnP, iterative, or ``refine``) removes them.

**Covariance.** Per detection, ``cov = s^2 (J^T J)^-1`` over the pose error ``[dtheta; dt]``
(:data:`~.geometry.ROT`, :data:`~.geometry.POS`), ``J`` the Jacobian of the four corners'
pixels (:func:`~.geometry.projection_jacobian`) and ``s^2`` the reprojection residuals' variance
(``rss / (2N - 6)``), never below ``sigma_floor_px^2`` (the corner detector's own noise). The
marker's size in pixels enters through ``J``: a marker half the size in the image gives about
four times the variance along the line of sight. With the calibration's stated accuracy in the
pipeline's config, its error is added, mapped through the same least-squares geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from companion.estimation.so3 import rotmat_to_quat

from .config import PNP_METHOD_NAMES, PipelineConfig, PnpMethod
from .geometry import (
    CameraIntrinsics,
    geodesic_angle_rad,
    intrinsics_jacobian,
    project_points,
    projection_jacobian,
    transform_points,
)
from .markers import MarkerDetection, detect_markers, make_detector, marker_object_points

__all__ = [
    "PNP_METHODS",
    "PnpMethod",
    "PipelineConfig",
    "MarkerPose",
    "pnp_candidates",
    "resolve_ambiguity",
    "pose_covariance",
    "estimate_marker_pose",
    "configured_pose",
    "measure_markers",
    "MarkerPipeline",
]

#: method name -> OpenCV flag
PNP_METHODS: dict[str, int] = {  # the order of PNP_METHOD_NAMES
    "ippe_square": cv2.SOLVEPNP_IPPE_SQUARE,
    "p3p": cv2.SOLVEPNP_P3P,
    "sqpnp": cv2.SOLVEPNP_SQPNP,
    "iterative": cv2.SOLVEPNP_ITERATIVE,
}
assert tuple(PNP_METHODS) == PNP_METHOD_NAMES


@dataclass(frozen=True)
class MarkerPose:
    """A marker's pose in the camera frame, ``p_c = R_cm p_m + t_cm_m``, with its covariance
    (6, 6) over ``[dtheta; dt]`` (camera frame), the reprojection RMS [px], the marker's side in
    the image [px], and whether the IPPE ambiguity was left unresolved by the residuals
    (``ambiguity_ratio``: the worse candidate's reprojection error over the better's)."""

    marker_id: int
    method: str
    R_cm: np.ndarray
    t_cm_m: np.ndarray
    cov: np.ndarray
    reproj_rms_px: float
    side_px: float
    ambiguous: bool = False
    ambiguity_ratio: float = float("inf")

    @property
    def q_cm_wxyz(self) -> np.ndarray:
        return rotmat_to_quat(self.R_cm)

    @property
    def range_m(self) -> float:
        return float(np.linalg.norm(self.t_cm_m))


def _rms(obj: np.ndarray, img: np.ndarray, R: np.ndarray, t: np.ndarray, intr: CameraIntrinsics) -> float:
    r = project_points(transform_points(R, t, obj), intr) - img
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def pnp_candidates(obj_m: np.ndarray, img_px: np.ndarray, intr: CameraIntrinsics, method: str,
                   refine: bool = False) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Every pose ``(R_cm, t_cm_m, reprojection RMS px)`` the method returns for undistorted pixels
    ``img_px`` (N, 2) of ``obj_m`` (N, 3), best first; poses behind the camera are dropped."""
    if method not in PNP_METHODS:
        raise ValueError(f"method: one of {', '.join(PNP_METHODS)}, got {method!r}")
    obj = np.ascontiguousarray(obj_m, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(img_px, dtype=np.float64).reshape(-1, 1, 2)
    K = intr.K
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, None, flags=PNP_METHODS[method])
    except cv2.error:
        return []
    out = []
    for rv, tv in zip(rvecs[:n], tvecs[:n]):
        rv = np.asarray(rv, dtype=float).reshape(3, 1)
        tv = np.asarray(tv, dtype=float).reshape(3, 1)
        if refine:
            rv, tv = cv2.solvePnPRefineLM(obj, img, K, None, rv, tv)
        R, _ = cv2.Rodrigues(rv)
        t = tv.ravel()
        if not np.all(np.isfinite(t)) or t[2] <= 0:
            continue
        out.append((R, t, _rms(obj.reshape(-1, 3), img.reshape(-1, 2), R, t, intr)))
    out.sort(key=lambda c: c[2])
    return out


def resolve_ambiguity(candidates: list[tuple[np.ndarray, np.ndarray, float]], previous_R_cm: np.ndarray | None,
                      ambiguity_ratio: float) -> tuple[int, bool, float]:
    """Which candidate to keep: ``(index, ambiguous, ratio)`` (see the module docstring).
    ``ratio`` is the second-best reprojection RMS over the best (inf with one candidate)."""
    if len(candidates) < 2:
        return 0, False, float("inf")
    best, second = candidates[0][2], candidates[1][2]
    ratio = second / best if best > 0 else float("inf")
    if ratio >= ambiguity_ratio:
        return 0, False, ratio
    if previous_R_cm is None:
        return 0, True, ratio
    angles = [float(geodesic_angle_rad(c[0], previous_R_cm)) for c in candidates[:2]]
    return int(np.argmin(angles)), True, ratio


def pose_covariance(obj_m: np.ndarray, img_px: np.ndarray, R_cm: np.ndarray, t_cm_m: np.ndarray,
                    intr: CameraIntrinsics, sigma_floor_px: float,
                    calibration_std: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """``s^2 (J^T J)^-1 + G C G^T`` (module docstring), symmetric, over ``[dtheta; dt]``: the
    second term the calibration's error, ``C = J_k S_k J_k^T`` the corners' pixel covariance from
    ``calibration_std`` (focal fraction, principal point px, distortion fraction;
    :func:`~.geometry.intrinsics_jacobian`), ``G = (J^T J)^-1 J^T`` the least-squares pose's
    sensitivity to the pixels. The calibration's error moves all corners together, so it does not
    average out over the corners as their noise does."""
    J = projection_jacobian(obj_m, R_cm, t_cm_m, intr)
    pc = transform_points(R_cm, t_cm_m, obj_m)
    r = (project_points(pc, intr) - img_px).ravel()
    dof = J.shape[0] - J.shape[1]
    s2 = max(float(r @ r) / dof if dof > 0 else 0.0, sigma_floor_px**2)
    JtJ_inv = np.linalg.pinv(J.T @ J)
    cov = s2 * JtJ_inv
    focal, principal, dist = calibration_std
    if focal or principal or dist:
        var = np.concatenate(([(focal * intr.fx_px) ** 2, (focal * intr.fy_px) ** 2, principal**2, principal**2],
                              (dist * np.asarray(intr.dist_coeffs, dtype=float)) ** 2))
        G = JtJ_inv @ J.T @ intrinsics_jacobian(pc, intr)
        cov = cov + (G * var) @ G.T
    return 0.5 * (cov + cov.T)


def estimate_marker_pose(det: MarkerDetection, length_m: float, intr: CameraIntrinsics, method: str, *,
                         previous: MarkerPose | None = None, ambiguity_ratio: float = 3.0,
                         sigma_floor_px: float = 0.3, refine: bool = False,
                         calibration_std: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> MarkerPose | None:
    """The pose of one detected marker (``None`` if the method finds none in front of the camera)."""
    obj = marker_object_points(length_m)
    cands = pnp_candidates(obj, det.corners_px, intr, method, refine=refine)
    if not cands:
        return None
    idx, ambiguous, ratio = resolve_ambiguity(cands, None if previous is None else previous.R_cm, ambiguity_ratio)
    R, t, rms = cands[idx]
    cov = pose_covariance(obj, det.corners_px, R, t, intr, sigma_floor_px, calibration_std)
    return MarkerPose(det.marker_id, method, R, t, cov, rms, det.side_px, ambiguous, ratio)


def measure_markers(image: np.ndarray, intr: CameraIntrinsics, cfg: PipelineConfig, detector=None,
                    previous: dict[int, MarkerPose] | None = None,
                    method: str | None = None) -> tuple[tuple[MarkerDetection, ...], tuple[MarkerPose, ...]]:
    """Image in, detections and marker poses out (the pipeline as one pure function).

    ``detector``: a :func:`~.markers.make_detector` of ``cfg.detector`` (made here if ``None``:
    pass one in a loop, it is reused); ``previous``: the last pose of each marker id (continuity
    for the IPPE ambiguity); ``method`` overrides ``cfg.method``."""
    detector = make_detector(cfg.detector) if detector is None else detector
    dets = detect_markers(image, detector, intr)
    if cfg.ids:
        dets = tuple(d for d in dets if d.marker_id in cfg.ids)
    poses = [pose for d in dets if (pose := configured_pose(d, intr, cfg, method, previous)) is not None]
    return dets, tuple(poses)


def configured_pose(det: MarkerDetection, intr: CameraIntrinsics, cfg: PipelineConfig, method: str | None = None,
                    previous: dict[int, MarkerPose] | None = None) -> MarkerPose | None:
    """:func:`estimate_marker_pose` of one detection with ``cfg``'s marker length, ambiguity
    ratio, noise floor, calibration accuracy and refinement (``method`` overrides ``cfg.method``); ``previous``: the last
    pose of each marker id, for the IPPE ambiguity."""
    return estimate_marker_pose(det, cfg.length_m(det.marker_id), intr, method or cfg.method,
                                previous=(previous or {}).get(det.marker_id), ambiguity_ratio=cfg.ambiguity_ratio,
                                sigma_floor_px=cfg.sigma_floor_px, refine=cfg.refine,
                                calibration_std=cfg.calibration_std)


class MarkerPipeline:
    """The pipeline with its state: one detector, and each marker's last pose for continuity."""

    def __init__(self, cfg: PipelineConfig, method: str | None = None):
        self.cfg = cfg
        self.method = method or cfg.method
        self.detector = make_detector(cfg.detector)
        self.previous: dict[int, MarkerPose] = {}

    def measure(self, image: np.ndarray, intr: CameraIntrinsics
                ) -> tuple[tuple[MarkerDetection, ...], tuple[MarkerPose, ...]]:
        """Detections and poses of ``image`` (:func:`measure_markers`); remembers the poses."""
        dets, poses = measure_markers(image, intr, self.cfg, self.detector, self.previous, self.method)
        for p in poses:
            self.previous[p.marker_id] = p
        return dets, poses

    def __call__(self, image: np.ndarray, intr: CameraIntrinsics) -> tuple[MarkerPose, ...]:
        return self.measure(image, intr)[1]

    def reset(self) -> None:
        self.previous.clear()

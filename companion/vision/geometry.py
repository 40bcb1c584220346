"""Camera geometry of the vision measurement: intrinsics, the pinhole projection, error metrics.

Conventions
-----------
* Camera frame ``C``: OpenCV's optical frame, x right in the image, y down, z forward along the
  optical axis. Pixel ``(u, v)``: column, row, with integer values at pixel centres (OpenCV).
* Marker frame ``M``: OpenCV's ArUco frame, origin at the marker's centre, x right and y up in
  the printed marker, z out of its face (towards a camera that sees it).
* A pose ``(R_cm, t_cm_m)`` maps marker-frame points into the camera frame:
  ``p_c = R_cm p_m + t_cm_m`` (the report's ``T_L^C`` of eq. 1).
* The pose error state is ``[dtheta; dt]`` with ``R = Exp(dtheta) R_hat`` (a camera-frame rotation
  vector, left perturbation, as the link EKF's world-frame error) and ``t = t_hat + dt``;
  its slices are :data:`ROT` and :data:`POS` (never bare indices).
* MuJoCo's cameras look along their -z with y up: :data:`CV_TO_MUJOCO_CAM` maps OpenCV camera
  axes to MuJoCo's (it is its own inverse).

numpy only (no OpenCV): the SITL, the load-pose filters and the tests share it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.estimation.so3 import skew

__all__ = [
    "ROT",
    "POS",
    "CV_TO_MUJOCO_CAM",
    "CameraIntrinsics",
    "frame_from_axes",
    "transform_points",
    "project_points",
    "projection_jacobian",
    "intrinsics_jacobian",
    "translation_error_m",
    "geodesic_angle_rad",
]

#: rotation part ``dtheta`` [rad] of a pose error state / pose covariance
ROT = slice(0, 3)
#: translation part ``dt`` [m] of a pose error state / pose covariance
POS = slice(3, 6)

#: OpenCV camera axes (x right, y down, z forward) -> MuJoCo camera axes (x right, y up, looks along -z)
CV_TO_MUJOCO_CAM = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of a ``width_px`` x ``height_px`` camera and OpenCV's distortion
    coefficients ``(k1, k2, p1, p2[, k3])`` (empty: none). ``K`` is the report's eq. 1 matrix."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    dist_coeffs: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"width_px and height_px must be positive, got {self.width_px} x {self.height_px}")
        for name in ("fx_px", "fy_px"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v}")
        for name in ("cx_px", "cy_px"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")
        if len(self.dist_coeffs) not in (0, 4, 5, 8):
            raise ValueError(f"dist_coeffs: 0, 4, 5 or 8 coefficients (k1, k2, p1, p2[, k3...]), "
                             f"got {len(self.dist_coeffs)}")
        if not all(math.isfinite(c) for c in self.dist_coeffs):
            raise ValueError("dist_coeffs must be finite")

    @classmethod
    def from_fov(cls, width_px: int, height_px: int, fovy_deg: float,
                 dist_coeffs: tuple[float, ...] = ()) -> CameraIntrinsics:
        """Square pixels with the vertical field of view ``fovy_deg`` (MuJoCo's ``fovy``) and the
        principal point at the image centre: ``f = (h / 2) / tan(fovy / 2)``,
        ``c = ((w - 1) / 2, (h - 1) / 2)`` (pixel centres at integers, as OpenCV counts them)."""
        if not 0.0 < fovy_deg < 180.0:
            raise ValueError(f"fovy_deg must be in (0, 180), got {fovy_deg}")
        f = 0.5 * height_px / math.tan(math.radians(fovy_deg) / 2.0)
        return cls(int(width_px), int(height_px), f, f, 0.5 * (width_px - 1), 0.5 * (height_px - 1),
                   tuple(float(c) for c in dist_coeffs))

    @property
    def K(self) -> np.ndarray:
        """The 3x3 camera matrix."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """Distortion coefficients as OpenCV takes them (five zeros when there are none)."""
        return np.array(self.dist_coeffs if self.dist_coeffs else (0.0,) * 5, dtype=float)

    @property
    def distorted(self) -> bool:
        return any(c != 0.0 for c in self.dist_coeffs)


def frame_from_axes(z_axis, x_axis) -> np.ndarray:
    """Rotation ``R_parent_child`` (columns: the child's x, y, z in the parent) of a right-handed
    frame with the given z and x axes (``y = z x x``). For a camera: z the optical axis, x the
    image's right; for a marker: z the face normal, x the marker's right. ``ValueError`` unless
    both are finite, non-zero and orthogonal (within 1e-6 after normalisation)."""
    z = np.asarray(z_axis, dtype=float)
    x = np.asarray(x_axis, dtype=float)
    nz, nx = np.linalg.norm(z), np.linalg.norm(x)
    if z.shape != (3,) or x.shape != (3,) or not (np.isfinite(nz) and np.isfinite(nx)) or nz == 0 or nx == 0:
        raise ValueError("axes must be finite non-zero 3-vectors")
    z, x = z / nz, x / nx
    if abs(z @ x) > 1e-6:
        raise ValueError(f"axes must be orthogonal, got z = {z.round(6).tolist()}, x = {x.round(6).tolist()}")
    return np.column_stack((x, np.cross(z, x), z))


def transform_points(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``R p + t`` for every row ``p`` of ``points`` (N, 3)."""
    return np.asarray(points, dtype=float) @ np.asarray(R, dtype=float).T + np.asarray(t, dtype=float)


def project_points(points_c_m: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    """Pinhole projection (report eq. 1, no distortion) of camera-frame points (N, 3) -> pixels (N, 2)."""
    p = np.asarray(points_c_m, dtype=float)
    z = p[:, 2]
    return np.column_stack((intr.fx_px * p[:, 0] / z + intr.cx_px, intr.fy_px * p[:, 1] / z + intr.cy_px))


def projection_jacobian(points_m_m: np.ndarray, R_cm: np.ndarray, t_cm_m: np.ndarray,
                        intr: CameraIntrinsics) -> np.ndarray:
    """Jacobian (2N, 6) of the stacked pixels ``[u1, v1, u2, ...]`` of marker-frame points (N, 3)
    with respect to the pose error ``[dtheta; dt]`` (columns :data:`ROT`, :data:`POS`):
    ``d p_c = -S(R_cm p_m) dtheta + dt``, chained with the pinhole derivative."""
    pm = np.asarray(points_m_m, dtype=float)
    rp = pm @ np.asarray(R_cm, dtype=float).T
    pc = rp + np.asarray(t_cm_m, dtype=float)
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    n = len(pm)
    dpix_dpc = np.zeros((n, 2, 3))
    dpix_dpc[:, 0, 0] = intr.fx_px / z
    dpix_dpc[:, 0, 2] = -intr.fx_px * x / z**2
    dpix_dpc[:, 1, 1] = intr.fy_px / z
    dpix_dpc[:, 1, 2] = -intr.fy_px * y / z**2
    dpc = np.zeros((n, 3, 6))
    dpc[:, :, ROT] = -skew(rp)
    dpc[:, :, POS] = np.eye(3)
    return np.einsum("nij,njk->nik", dpix_dpc, dpc).reshape(2 * n, 6)


def intrinsics_jacobian(points_c_m: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    """Jacobian (2N, 4 + d) of the stacked pinhole pixels ``[u1, v1, u2, ...]`` of camera-frame
    points (N, 3), as the detector reports them (undistorted with ``intr``), with respect to an
    error in ``(fx, fy, cx, cy)`` and in each of the ``d`` distortion coefficients ``(k1, k2, p1,
    p2[, k3])``: ``du/dfx = x'``, ``du/dcx = 1``; a coefficient's error leaves the distortion it
    adds in the undistorted point, ``f d(x'_distorted)/dk`` (OpenCV's model, first order). Eight
    coefficients: the rational and prism terms are left out (zero columns)."""
    p = np.asarray(points_c_m, dtype=float)
    x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    n, d = len(p), len(intr.dist_coeffs)
    J = np.zeros((n, 2, 4 + d))
    J[:, 0, 0], J[:, 1, 1] = x, y
    J[:, 0, 2], J[:, 1, 3] = 1.0, 1.0
    if d:
        r2 = x * x + y * y
        ddx = [x * r2, x * r2 * r2, 2 * x * y, r2 + 2 * x * x]  # d x_distorted / d (k1, k2, p1, p2)
        ddy = [y * r2, y * r2 * r2, r2 + 2 * y * y, 2 * x * y]
        if d >= 5:
            ddx.append(x * r2**3)
            ddy.append(y * r2**3)
        for j, (gx, gy) in enumerate(zip(ddx, ddy)):
            J[:, 0, 4 + j] = intr.fx_px * gx
            J[:, 1, 4 + j] = intr.fy_px * gy
    return J.reshape(2 * n, 4 + d)


def translation_error_m(t_est_m: np.ndarray, t_gt_m: np.ndarray) -> np.ndarray:
    """The report's eq. 2: ``t_est - t_gt`` (per row; its norm is the translation error)."""
    return np.asarray(t_est_m, dtype=float) - np.asarray(t_gt_m, dtype=float)


def geodesic_angle_rad(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """The report's eq. 3: ``|arccos((tr(R_est^T R_gt) - 1) / 2)|`` [rad], the angle of the
    rotation between the two; ``(..., 3, 3)`` pairs, the cosine clipped to [-1, 1]."""
    R_est = np.asarray(R_est, dtype=float)
    R_gt = np.asarray(R_gt, dtype=float)
    tr = np.einsum("...ij,...ij->...", R_est, R_gt)  # tr(R_est^T R_gt)
    return np.abs(np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0)))

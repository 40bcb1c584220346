"""A camera on one link seeing a marker on its neighbour: the relative pose as a measurement of
the two links' states (beside the chain constraint, paper sec. III).

Link ``i`` carries a camera at ``c`` in its body frame with orientation ``R_bc`` (OpenCV camera
axes); link ``j`` carries a marker at ``m`` with orientation ``R_bm``. PnP measures the marker's
pose in the camera frame, ``p_c = R_cm p_m + t_cm`` (:mod:`companion.vision.pnp`), with a
covariance over ``[dtheta_c; dt]`` (``R_cm = Exp(dtheta_c) R_cm_hat``, camera frame; the
slices :data:`ROT`, :data:`POS` of :mod:`companion.vision.geometry`). The model::

    R_cm = R_bc^T R_i^T R_j R_bm
    t_cm = R_bc^T (R_i^T (p_j + R_j m - p_i) - c)

With the chain's world-frame attitude errors ``R = (I + S(dtheta)) R_hat`` (:mod:`.so3`) and
``M = R_bc^T R_i^T``, ``w = p_j + R_j m - p_i``, the Jacobians on the two links' error states
``[dp; dv; dtheta]`` (:mod:`.chain`) are::

    d(dtheta_c) = M (dtheta_j - dtheta_i)
    d(t_cm)     = M (dp_j - dp_i) + M S(w) dtheta_i - M S(R_j m) dtheta_j

The residual is ``[Log(R_cm_meas R_cm^T); t_cm_meas - t_cm]``: it is zero at the truth and its
covariance is the PnP's. Unlike the chain constraint, it measures the relative attitude too, and
it needs no absolute position: common-mode GNSS errors cancel in it.

:func:`relative_pose_update` applies one such measurement to the two links' EKF estimates as a
Kalman update on their stacked state (independent estimates before it, correlated after: the
18 x 18 covariance is returned whole). Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .chain import ERR_DIM, ERR_P, ERR_TH, ERR_V, ChainInputError
from .so3 import quat_to_rotmat, quat_to_rotvec, retract, rotmat_to_quat, skew

__all__ = ["NeighbourView", "marker_in_camera", "relative_pose_residual", "relative_pose_jacobian",
           "RelativePoseUpdate", "relative_pose_update"]

#: rows of the residual: the camera-frame rotation error, then the translation error (as
#: :data:`companion.vision.geometry.ROT` / ``POS``)
RES_ROT = slice(0, 3)
RES_POS = slice(3, 6)


@dataclass(frozen=True)
class NeighbourView:
    """Where the camera sits on the observing link (``camera_pos_b_m``, ``R_b_c``: camera to
    body) and the marker on the observed link (``marker_pos_b_m``, ``R_b_m``: marker to body)."""

    camera_pos_b_m: np.ndarray
    R_b_c: np.ndarray
    marker_pos_b_m: np.ndarray
    R_b_m: np.ndarray

    def __post_init__(self) -> None:
        for name in ("camera_pos_b_m", "marker_pos_b_m"):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} must be 3 finite numbers, got {v}")
            object.__setattr__(self, name, v)
        for name in ("R_b_c", "R_b_m"):
            R = np.asarray(getattr(self, name), dtype=float)
            if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
                raise ValueError(f"{name} must be a rotation matrix")
            object.__setattr__(self, name, R)


def marker_in_camera(p_i, q_i, p_j, q_j, view: NeighbourView) -> tuple[np.ndarray, np.ndarray]:
    """The model ``(R_cm, t_cm)`` (module docstring) from the two links' positions and
    attitudes."""
    R_i, R_j = quat_to_rotmat(np.asarray(q_i, dtype=float)), quat_to_rotmat(np.asarray(q_j, dtype=float))
    M = view.R_b_c.T @ R_i.T
    R_cm = M @ R_j @ view.R_b_m
    t_cm = M @ (np.asarray(p_j, dtype=float) + R_j @ view.marker_pos_b_m - np.asarray(p_i, dtype=float)) \
        - view.R_b_c.T @ view.camera_pos_b_m
    return R_cm, t_cm


def relative_pose_residual(R_cm_meas, t_cm_meas, p_i, q_i, p_j, q_j, view: NeighbourView) -> np.ndarray:
    """``[Log(R_cm_meas R_cm^T); t_cm_meas - t_cm]`` (6,) at the given states."""
    R_cm, t_cm = marker_in_camera(p_i, q_i, p_j, q_j, view)
    r = np.empty(6)
    r[RES_ROT] = quat_to_rotvec(rotmat_to_quat(np.asarray(R_cm_meas, dtype=float) @ R_cm.T))
    r[RES_POS] = np.asarray(t_cm_meas, dtype=float) - t_cm
    return r


def relative_pose_jacobian(p_i, q_i, p_j, q_j, view: NeighbourView) -> tuple[np.ndarray, np.ndarray]:
    """The model's Jacobians ``(H_i, H_j)``, each (6, 9) on that link's error state
    ``[dp; dv; dtheta]`` (module docstring): of ``[Log(R_cm(x) R_cm(x_hat)^T); t_cm(x)]`` at the
    estimate ``x_hat``, so the residual at the estimate moves by ``-H dx``."""
    R_i, R_j = quat_to_rotmat(np.asarray(q_i, dtype=float)), quat_to_rotmat(np.asarray(q_j, dtype=float))
    M = view.R_b_c.T @ R_i.T
    Rm = R_j @ view.marker_pos_b_m
    w = np.asarray(p_j, dtype=float) + Rm - np.asarray(p_i, dtype=float)
    H_i, H_j = np.zeros((6, ERR_DIM)), np.zeros((6, ERR_DIM))
    H_i[RES_ROT, ERR_TH] = -M
    H_j[RES_ROT, ERR_TH] = M
    H_i[RES_POS, ERR_P] = -M
    H_j[RES_POS, ERR_P] = M
    H_i[RES_POS, ERR_TH] = M @ skew(w)
    H_j[RES_POS, ERR_TH] = -M @ skew(Rm)
    return H_i, H_j


@dataclass(frozen=True)
class RelativePoseUpdate:
    """One relative-pose update of links ``i`` and ``j``: their corrected positions, velocities
    and attitudes (each (2, 3) / (2, 4), ``i`` first), the stacked 18 x 18 covariance after it,
    the normalised innovation squared, and whether it passed the gate (rejected: the inputs
    unchanged)."""

    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    P: np.ndarray
    nis: float
    accepted: bool


def relative_pose_update(p, v, q, P_blocks, R_cm_meas, t_cm_meas, cov_pnp, view: NeighbourView,
                         gate_chi2: float | None = None) -> RelativePoseUpdate:
    """Kalman update of two links (rows 0 = observing ``i``, 1 = observed ``j``: ``p``, ``v``
    (2, 3), ``q`` (2, 4), ``P_blocks`` (2, 9, 9), their independent EKF covariances) with one
    PnP pose of the marker and its covariance ``cov_pnp`` (6, 6). Joseph form; the error is
    injected as the chain's estimators do (positions and velocities added, attitudes by
    :func:`~.so3.retract`). ``gate_chi2``: reject above this NIS (6 dof). ``ChainInputError``
    for shapes or non-finite values."""
    p, v, q = (np.asarray(a, dtype=float) for a in (p, v, q))
    P_blocks = np.asarray(P_blocks, dtype=float)
    cov = np.asarray(cov_pnp, dtype=float)
    for name, arr, shape in (("p", p, (2, 3)), ("v", v, (2, 3)), ("q", q, (2, 4)), ("P", P_blocks, (2, 9, 9)),
                             ("cov_pnp", cov, (6, 6)), ("t_cm_meas", np.asarray(t_cm_meas, dtype=float), (3,)),
                             ("R_cm_meas", np.asarray(R_cm_meas, dtype=float), (3, 3))):
        if arr.shape != shape or not np.all(np.isfinite(arr)):
            raise ChainInputError(f"{name} must be finite with shape {shape}, got {arr.shape}", field=name)
    r = relative_pose_residual(R_cm_meas, t_cm_meas, p[0], q[0], p[1], q[1], view)
    H_i, H_j = relative_pose_jacobian(p[0], q[0], p[1], q[1], view)
    H = np.hstack((H_i, H_j))
    P = np.zeros((2 * ERR_DIM, 2 * ERR_DIM))
    P[:ERR_DIM, :ERR_DIM], P[ERR_DIM:, ERR_DIM:] = P_blocks[0], P_blocks[1]
    S = H @ P @ H.T + cov
    S = 0.5 * (S + S.T)
    S_inv = np.linalg.inv(S)
    nis = float(r @ S_inv @ r)
    if gate_chi2 is not None and nis > gate_chi2:
        return RelativePoseUpdate(p, v, q, P, nis, False)
    K = P @ H.T @ S_inv
    I_KH = np.eye(2 * ERR_DIM) - K @ H
    P_new = I_KH @ P @ I_KH.T + K @ cov @ K.T
    dx = (K @ r).reshape(2, ERR_DIM)
    q_new = np.stack([retract(q[k], dx[k, ERR_TH]) for k in range(2)])
    return RelativePoseUpdate(p + dx[:, ERR_P], v + dx[:, ERR_V], q_new, 0.5 * (P_new + P_new.T), nis, True)

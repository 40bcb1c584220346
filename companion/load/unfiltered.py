"""The unfiltered baseline: the load's pose solved from the latest images alone (eq. 4 over the
vehicles, no dynamics, no memory): what the cameras alone give. numpy only."""

from __future__ import annotations

import numpy as np

from companion.estimation.so3 import rotmat_to_quat

from .model import LoadObservation, VehicleStates

__all__ = ["solve_load_pose", "UnfilteredLoadPose"]


def solve_load_pose(vehicle_in_load_m: np.ndarray, vehicle_w_m: np.ndarray,
                    weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4 solved without a filter: the load pose ``(p, q_wxyz)`` with ``t_i ~ R y_i + p``
    for three or more vehicles (weighted least squares: Kabsch/Horn with an SVD).
    ``ValueError`` if fewer than three or (nearly) collinear."""
    y = np.asarray(vehicle_in_load_m, dtype=float)
    t = np.asarray(vehicle_w_m, dtype=float)
    if y.shape != t.shape or y.ndim != 2 or y.shape[1] != 3:
        raise ValueError(f"vehicle_in_load_m and vehicle_w_m must both be (k, 3), got {y.shape}, {t.shape}")
    if y.shape[0] < 3:
        raise ValueError(f"need three or more vehicles, got {y.shape[0]}")
    w = np.ones(len(y)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (len(y),) or np.any(w <= 0):
        raise ValueError("weights must be positive, one per vehicle")
    w = w / w.sum()
    y_c, t_c = w @ y, w @ t
    Y, T = y - y_c, t - t_c
    H = (Y * w[:, None]).T @ T
    U, s, Vt = np.linalg.svd(H)
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise ValueError("vehicles (nearly) collinear: the rotation about their line is unobservable")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return t_c - R @ y_c, rotmat_to_quat(R)


class UnfilteredLoadPose:
    """The unfiltered baseline: the latest image of every vehicle (captured within ``window_s``
    of the newest) solved for the pose by :func:`solve_load_pose`, weighted by the inverse trace
    of each image's covariance, vehicles' positions taken at each image's capture time. No
    dynamics, no memory beyond the latest images: what the cameras alone give. The solved pose
    refers to ``stamp_s``, the mean capture time of the images used (with a moving load, images of
    different times mix: part of this baseline's error)."""

    def __init__(self, n_vehicles: int, window_s: float = 0.1) -> None:
        if n_vehicles < 3:
            raise ValueError(f"the unfiltered solve needs three or more vehicles, got {n_vehicles}")
        if not window_s > 0:
            raise ValueError(f"window_s must be positive, got {window_s}")
        self.window_s = window_s
        self._latest: list[tuple[LoadObservation, np.ndarray] | None] = [None] * n_vehicles
        self.pos_w_m: np.ndarray | None = None
        self.q_wxyz: np.ndarray | None = None
        self.stamp_s: float | None = None

    def push(self, obs: LoadObservation, vehicles: VehicleStates) -> bool:
        """Add one image (with the vehicle samples in force at its capture time); returns whether
        a new pose was solved."""
        if obs.vehicle >= len(self._latest):
            raise ValueError(f"observation of vehicle {obs.vehicle}, only {len(self._latest)} vehicles")
        cur = self._latest[obs.vehicle]
        if cur is not None and cur[0].stamp_s > obs.stamp_s:
            return False
        self._latest[obs.vehicle] = (obs, vehicles.positions_at(obs.stamp_s)[obs.vehicle])
        newest = max(o.stamp_s for o, _ in filter(None, self._latest))
        use = [e for e in self._latest if e is not None and newest - e[0].stamp_s <= self.window_s]
        if len(use) < 3:
            return False
        try:
            p, q = solve_load_pose(np.array([o.vehicle_in_load_m for o, _ in use]), np.array([t for _, t in use]),
                                   np.array([1.0 / np.trace(o.cov_m2) for o, _ in use]))
        except ValueError:
            return False
        self.pos_w_m, self.q_wxyz, self.stamp_s = p, q, float(np.mean([o.stamp_s for o, _ in use]))
        return True

"""What the load filters measure: eq. 4, the marker's attitude and the taut cables' lengths.

* **Eq. 4** (the report's measurement): vehicle ``i``'s position in the load frame,
  ``y_i = R^T (t_i - p)``, with ``t_i`` the vehicle's GNSS/EKF position.
  :func:`observation_from_pnp` turns one camera's PnP pose of the load's marker into ``y_i``
  and its covariance (the inverse of what PnP measures, with the static camera and marker
  offsets, as the report says; the vehicle's attitude is not needed).
* **The marker's attitude** (beyond the report): the same PnP pose gives the load's attitude in
  the vehicle's body frame, ``R_bl = R_bc R_cm R_lm^T``; with the vehicle's own attitude estimate
  ``R_wb`` it measures the load's attitude in the world, ``R_wl = R_wb R_bl``. Its error is the
  PnP's rotation error (correlated with ``y``'s, both from the same corners) plus the vehicle's
  attitude error. Eq. 4 alone gets the load's tilt from the vehicles' positions, so every
  centimetre of GNSS bias between two vehicles tilts the estimate; this measurement does not
  depend on them.
* **A taut cable's length**: ``|t_i - p - R r_i| = L_i``, for every cable whose estimated
  tension says it is taut.

:func:`image_measurement` and :func:`cable_measurement` assemble a :class:`Measurement` (the
value, the batched model, its Jacobian on the error state and the noise) that both the EKF and
the UKF (:mod:`.kalman`) apply. The attitude part is in the tangent space at the estimate:
``z = Log(R_meas R_hat^T)``, ``h(x) = Log(R(x) R_hat^T)`` (zero at the estimate, Jacobian
``I`` on ``dtheta``), the world-frame error of the filters' convention.

Pure numpy, vectorised over a leading batch axis of ``x`` where the UKF needs it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.estimation.so3 import attitude_error, quat_mul, quat_to_rotmat, rotmat_to_quat, skew

from companion.vision.geometry import POS as PNP_POS
from companion.vision.geometry import ROT as PNP_ROT

from .model import (
    ERR_ATT,
    ERR_POS,
    NOM_POS,
    NOM_QUAT,
    LoadObservation,
    LoadParams,
    Pose3,
    VehicleStates,
    cable_geometry,
    error_dim,
    nominal_tension_slice,
)

__all__ = [
    "vehicle_in_load", "vehicle_in_load_jacobian", "cable_lengths", "cable_length_jacobian",
    "observation_from_pnp", "marker_in_camera", "Measurement", "image_measurement", "cable_measurement",
    "taut_cables",
]


def vehicle_in_load(x: np.ndarray, vehicle_w_m: np.ndarray) -> np.ndarray:
    """Eq. 4: ``y = R^T (t - p)``, the vehicle's position in the load frame (batched over x)."""
    x = np.asarray(x, dtype=float)
    R = quat_to_rotmat(x[..., NOM_QUAT])
    return np.einsum("...ji,...j->...i", R, np.asarray(vehicle_w_m, dtype=float) - x[..., NOM_POS])


def vehicle_in_load_jacobian(x: np.ndarray, vehicle_w_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4's Jacobians: ``H`` (3, 12 + n) w.r.t. the error state (``-R^T`` on ``dp``,
    ``R^T S(t - p)`` on ``dtheta``) and ``R^T`` w.r.t. the vehicle's position (its noise)."""
    x = np.asarray(x, dtype=float)
    n = x.shape[-1] - 13
    R = quat_to_rotmat(x[NOM_QUAT])
    H = np.zeros((3, error_dim(n)))
    H[:, ERR_POS] = -R.T
    H[:, ERR_ATT] = R.T @ skew(np.asarray(vehicle_w_m, dtype=float) - x[NOM_POS])
    return H, R.T


def cable_lengths(x: np.ndarray, vehicles_w_m: np.ndarray, params: LoadParams) -> np.ndarray:
    """``|t_i - p - R r_i|`` per cable (batched): a taut cable's length."""
    return cable_geometry(np.asarray(x, dtype=float), vehicles_w_m, params)[1]


def cable_length_jacobian(x: np.ndarray, vehicles_w_m: np.ndarray, params: LoadParams):
    """Jacobians of :func:`cable_lengths`: ``H`` (n, 12 + n) (``-u^T`` on ``dp``,
    ``u^T S(R r)`` on ``dtheta``) and per-cable ``u_i^T`` w.r.t. vehicle ``i``'s position (n, 3)."""
    _, _, u, _, Rr = cable_geometry(np.asarray(x, dtype=float), vehicles_w_m, params)
    n = params.n_cables
    H = np.zeros((n, error_dim(n)))
    H[:, ERR_POS] = -u
    H[:, ERR_ATT] = np.einsum("ni,nij->nj", u, skew(Rr))
    return H, u


def observation_from_pnp(vehicle: int, stamp_s: float, R_cm: np.ndarray, t_cm_m: np.ndarray,
                         cov_pnp: np.ndarray, camera_in_body: Pose3, marker_in_load: Pose3) -> LoadObservation:
    """One camera's PnP pose of the load's marker -> eq. 4's ``y`` and the load's attitude in the
    vehicle's body frame, with their joint covariance.

    ``(R_cm, t_cm_m)`` maps marker points into the camera frame (OpenCV, the report's ``T_L^C``);
    ``cov_pnp`` (6, 6) is its covariance in the error ``[dtheta; dt]`` (slices of
    ``companion.vision.geometry``: ``R = Exp(dtheta) R_hat`` in the camera frame). The vehicle's
    origin is ``c = -R_bc^T t_bc`` in the camera frame, so
    ``y = R_lm R_cm^T (c - t_cm) + t_lm`` with Jacobians
    ``dy/ddtheta = R_lm R_cm^T S(c - t_cm)`` and ``dy/ddt = -R_lm R_cm^T``; the load in the body
    frame is ``R_bl = R_bc R_cm R_lm^T`` with ``dphi = R_bc dtheta``.
    """
    R_cm = np.asarray(R_cm, dtype=float)
    t_cm = np.asarray(t_cm_m, dtype=float).reshape(3)
    cov_pnp = np.asarray(cov_pnp, dtype=float)
    if R_cm.shape != (3, 3) or cov_pnp.shape != (6, 6):
        raise ValueError(f"R_cm must be (3, 3) and cov_pnp (6, 6), got {R_cm.shape}, {cov_pnp.shape}")
    R_bc = camera_in_body.R
    c = -R_bc.T @ camera_in_body.pos_m
    R_lm = marker_in_load.R
    A = R_lm @ R_cm.T
    y = A @ (c - t_cm) + marker_in_load.pos_m
    J = np.zeros((6, 6))
    J[:3, PNP_ROT] = A @ skew(c - t_cm)
    J[:3, PNP_POS] = -A
    J[3:, PNP_ROT] = R_bc
    joint = J @ cov_pnp @ J.T
    joint = 0.5 * (joint + joint.T)
    return LoadObservation(vehicle, stamp_s, y, joint[:3, :3], rotmat_to_quat(R_bc @ R_cm @ R_lm.T), joint)


def marker_in_camera(load: Pose3, vehicle: Pose3, camera_in_body: Pose3, marker_in_load: Pose3):
    """The true ``(R_cm, t_cm_m)`` a camera on ``vehicle`` sees of the load's marker (world poses
    in): ``T_cm = T_cb T_bw T_wl T_lm``. For ground truth of PnP and for synthetic measurements."""
    R_wm = load.R @ marker_in_load.R
    t_wm = load.R @ marker_in_load.pos_m + load.pos_m
    R_wc = vehicle.R @ camera_in_body.R
    t_wc = vehicle.R @ camera_in_body.pos_m + vehicle.pos_m
    return R_wc.T @ R_wm, R_wc.T @ (t_wm - t_wc)


# --- measurements as the filters apply them ----------------------------------------------------


@dataclass(frozen=True)
class Measurement:
    """A measurement at the estimate ``x``: the value ``z`` (m,), the model ``h`` (batched: x
    (..., 13 + n) -> (..., m)), its Jacobian ``H`` (m, 12 + n) on the error state at ``x`` and the
    noise covariance ``R`` (m, m)."""

    z: np.ndarray
    h: Callable[[np.ndarray], np.ndarray]
    H: np.ndarray
    R: np.ndarray

    @property
    def dof(self) -> int:
        return int(self.z.shape[0])


def image_measurement(x: np.ndarray, obs: LoadObservation, vehicles: VehicleStates, *,
                      attitude: bool = True) -> Measurement:
    """One image's measurement at the estimate ``x`` (at the image's capture time).

    Eq. 4 (3 rows): ``y`` against ``R^T (t - p)`` with the vehicle's position extrapolated to the
    capture time, noise ``cov_y + R^T cov_t R``. With ``attitude`` and an observation and
    vehicle sample that carry attitudes, three rows more: the load's world attitude
    ``R_wb R_bl`` in the tangent space at ``x`` (module docstring), noise
    ``R_wb cov_phi R_wb^T + cov_vehicle_att`` and the PnP's correlation with ``y``
    (``cov_y_phi R_wb^T``). The vehicle's attitude is carried to the capture time with its body
    rate (:meth:`~.model.VehicleStates.attitudes_at`)."""
    x = np.asarray(x, dtype=float)
    i = obs.vehicle
    if i >= vehicles.pos_w_m.shape[0]:
        raise ValueError(f"observation of vehicle {i}, only {vehicles.pos_w_m.shape[0]} vehicles")
    t_w = vehicles.positions_at(obs.stamp_s)[i]
    H_y, Ht = vehicle_in_load_jacobian(x, t_w)
    R_yy = obs.cov_m2 + Ht @ vehicles.pos_cov_m2[i] @ Ht.T
    if not (attitude and obs.has_attitude and vehicles.has_attitude):
        return Measurement(obs.vehicle_in_load_m, lambda chi: vehicle_in_load(chi, t_w), H_y, R_yy)
    q_ref = x[NOM_QUAT].copy()
    q_wb = vehicles.attitudes_at(obs.stamp_s)[i]
    R_wb = quat_to_rotmat(q_wb)
    z_att = attitude_error(quat_mul(q_wb, obs.load_in_body_q_wxyz), q_ref)
    H = np.zeros((6, x.shape[-1] - 1))
    H[:3] = H_y
    H[3:, ERR_ATT] = np.eye(3)
    R = np.empty((6, 6))
    R[:3, :3] = R_yy
    R[:3, 3:] = obs.joint_cov[:3, 3:] @ R_wb.T
    R[3:, :3] = R[:3, 3:].T
    R[3:, 3:] = R_wb @ obs.joint_cov[3:, 3:] @ R_wb.T + vehicles.att_cov_rad2[i]

    def h(chi: np.ndarray) -> np.ndarray:
        chi = np.asarray(chi, dtype=float)
        return np.concatenate((vehicle_in_load(chi, t_w), attitude_error(chi[..., NOM_QUAT], q_ref)), axis=-1)

    return Measurement(np.concatenate((obs.vehicle_in_load_m, z_att)), h, H, 0.5 * (R + R.T))


def taut_cables(x: np.ndarray, params: LoadParams, taut_fraction: float) -> np.ndarray:
    """Indices of the cables taut by the estimate: tension above ``taut_fraction`` of an equal
    share of the load's weight (``m g / n``)."""
    share = params.mass_kg * params.gravity_m_s2 / params.n_cables
    return np.flatnonzero(np.asarray(x, dtype=float)[nominal_tension_slice(params.n_cables)] > taut_fraction * share)


def cable_measurement(x: np.ndarray, vehicles: VehicleStates, t_s: float, params: LoadParams, sigma_m: float,
                      taut_fraction: float) -> Measurement | None:
    """The taut cables' lengths at the estimate ``x`` (at ``t_s``): ``|t_i - p - R r_i| = L_i``
    for every cable :func:`taut_cables` picks, noise ``sigma_m^2 + u_i^T cov_t_i u_i`` each
    (the cable's stretch and attachment tolerance, the vehicle's position noise along the cable).
    ``None`` when no cable is taut."""
    taut = taut_cables(x, params, taut_fraction)
    if not taut.size:
        return None
    t_all = vehicles.positions_at(t_s)
    H, u = cable_length_jacobian(x, t_all, params)
    R = np.diag([sigma_m**2 + u[i] @ vehicles.pos_cov_m2[i] @ u[i] for i in taut])
    return Measurement(params.cable_length_m[taut], lambda chi: cable_lengths(chi, t_all, params)[..., taut],
                       H[taut], R)

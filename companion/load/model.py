"""The slung load's model: state on SE(3), dynamics (report eq. 8), measurement (report eq. 4).

The slung-load report (sec. IV) estimates a load carried by cables from several
vehicles. Its filter folded the dynamics into a control input (eq. 5, 7) on a roll-pitch-yaw state
(eq. 6), which is why its EKF and UKF gave the same trajectory. Here the dynamics are in the
prediction and the attitude lives on SO(3):

* **State** (nominal, :class:`LoadState`): load position ``p`` and velocity ``v`` in the world
  frame (z-up, m, m/s), attitude ``q`` (Hamilton ``[w, x, y, z]``, load body to world), body
  angular velocity ``w`` (rad/s) and the tension ``T_i`` (N) of every cable, estimated (a random
  walk), so the filter needs no force sensor and no vehicle thrust. Packed arrays use the slices
  :data:`NOM_POS`, :data:`NOM_VEL`, :data:`NOM_QUAT`, :data:`NOM_OMEGA` and
  :func:`nominal_tension_slice`.
* **Error state** ``[dp; dv; dtheta; dw; dT]`` (slices :data:`ERR_POS`, :data:`ERR_VEL`,
  :data:`ERR_ATT`, :data:`ERR_OMEGA`, :func:`error_tension_slice`), ``dtheta`` the world-frame
  rotation vector with ``q = Exp(dtheta) (x) q_hat``: the repo's convention (``companion/
  estimation/so3.py``, paper sec. III-A). :func:`boxplus` / :func:`boxminus` use the exact
  exponential and logarithm so that the UKF's sigma points go round trip.
* **Dynamics, eq. 8** (after Sreenath & Kumar, the report's ref. [4]): with ``u_i`` the unit
  vector from cable ``i``'s attachment point ``p + R r_i`` to vehicle ``i`` (the report's
  ``-q_i``, which points from the vehicle to the load; its ``R_L^W q_i`` writes the same vector
  in the load frame)::

      m a     = sum_i T_i u_i - m g e3                                   (8a)
      J w'    = sum_i r_i x (T_i R^T u_i) - w x J w                      (8b)

  (8b) uses the body angular velocity ``w`` where the report writes the Euler-angle rate
  ``theta_L'``; the two differ unless the load barely rotates. The vehicles' positions (and
  velocities, to carry them through a prediction step) are inputs.
* The measurements (eq. 4, the marker's attitude, the taut cables' lengths) are in
  :mod:`.measurements`; the typed inputs they take (:class:`VehicleStates`,
  :class:`LoadObservation`) are here.

Pure numpy: no OpenCV, no clocks. Every model function is vectorised over a leading batch axis
(the UKF pushes all sigma points through at once).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.estimation.so3 import (
    attitude_error,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    quat_to_rotmat,
    skew,
)
from companion.skeleton.body import GRAVITY_M_S2


__all__ = [
    "NOM_POS", "NOM_VEL", "NOM_QUAT", "NOM_OMEGA", "nominal_tension_slice", "nominal_dim",
    "ERR_POS", "ERR_VEL", "ERR_ATT", "ERR_OMEGA", "error_tension_slice", "error_dim",
    "LoadParams", "LoadState", "VehicleStates", "LoadObservation", "Pose3",
    "pack_state", "unpack_state", "boxplus", "boxminus",
    "cable_geometry", "load_accelerations", "error_dynamics_jacobian", "propagate_nominal",
    "static_tensions",
]

# --- named slices -------------------------------------------------------------------------

#: nominal state: world position [m]
NOM_POS = slice(0, 3)
#: nominal state: world velocity [m/s]
NOM_VEL = slice(3, 6)
#: nominal state: attitude quaternion [w, x, y, z], load body -> world
NOM_QUAT = slice(6, 10)
#: nominal state: body angular velocity [rad/s]
NOM_OMEGA = slice(10, 13)

#: error state: position [m]
ERR_POS = slice(0, 3)
#: error state: velocity [m/s]
ERR_VEL = slice(3, 6)
#: error state: world-frame attitude error [rad], q = Exp(dtheta) (x) q_hat
ERR_ATT = slice(6, 9)
#: error state: body angular velocity [rad/s]
ERR_OMEGA = slice(9, 12)


def nominal_tension_slice(n_cables: int) -> slice:
    """Nominal-state slice of the cable tensions [N]."""
    return slice(13, 13 + n_cables)


def error_tension_slice(n_cables: int) -> slice:
    """Error-state slice of the cable tensions [N]."""
    return slice(12, 12 + n_cables)


def nominal_dim(n_cables: int) -> int:
    return 13 + n_cables


def error_dim(n_cables: int) -> int:
    return 12 + n_cables


# --- typed inputs ---------------------------------------------------------------------------


def _vec(value, shape, name) -> np.ndarray:
    arr = np.array(value, dtype=float)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    arr.setflags(write=False)
    return arr


def _cov(value, shape, name) -> np.ndarray:
    arr = _vec(value, shape, name)
    mats = arr.reshape((-1,) + shape[-2:])
    if not np.allclose(mats, np.swapaxes(mats, -1, -2), atol=1e-12 + 1e-9 * np.abs(mats).max()):
        raise ValueError(f"{name} must be symmetric")
    if np.any(np.linalg.eigvalsh(mats)[:, 0] < -1e-12):
        raise ValueError(f"{name} must be positive semi-definite")
    return arr


@dataclass(frozen=True)
class LoadParams:
    """The load and its cables: mass [kg], body inertia about the centre of mass [kg m^2],
    attachment points ``r_i`` in the load's body frame [m] (one row per cable; cable ``i`` goes to
    vehicle ``i``) and the cables' lengths [m] (used by the optional taut-cable measurement)."""

    mass_kg: float
    inertia_b_kg_m2: np.ndarray
    attach_b_m: np.ndarray
    cable_length_m: np.ndarray
    gravity_m_s2: float = GRAVITY_M_S2

    def __post_init__(self) -> None:
        if not (math.isfinite(self.mass_kg) and self.mass_kg > 0):
            raise ValueError(f"mass_kg must be positive, got {self.mass_kg}")
        if not (math.isfinite(self.gravity_m_s2) and self.gravity_m_s2 >= 0):
            raise ValueError(f"gravity_m_s2 must be >= 0, got {self.gravity_m_s2}")
        J = np.array(self.inertia_b_kg_m2, dtype=float)
        if J.shape == (3,):
            J = np.diag(J)
        J = _cov(J, (3, 3), "inertia_b_kg_m2")
        if np.linalg.eigvalsh(J)[0] <= 0:
            raise ValueError("inertia_b_kg_m2 must be positive definite")
        r = np.array(self.attach_b_m, dtype=float)
        if r.ndim != 2 or r.shape[1] != 3 or r.shape[0] < 1:
            raise ValueError(f"attach_b_m must be (n_cables, 3), got {r.shape}")
        r = _vec(r, r.shape, "attach_b_m")
        L = _vec(np.atleast_1d(np.asarray(self.cable_length_m, dtype=float)), (r.shape[0],), "cable_length_m")
        if np.any(L <= 0):
            raise ValueError("cable_length_m must be positive")
        object.__setattr__(self, "inertia_b_kg_m2", J)
        object.__setattr__(self, "attach_b_m", r)
        object.__setattr__(self, "cable_length_m", L)
        Jinv = np.linalg.inv(J)
        Jinv.setflags(write=False)
        object.__setattr__(self, "_J_inv", Jinv)
        Sr = skew(r)
        Sr.setflags(write=False)
        object.__setattr__(self, "_attach_skew", Sr)

    @property
    def n_cables(self) -> int:
        return self.attach_b_m.shape[0]

    @property
    def inertia_inv_b(self) -> np.ndarray:
        return self._J_inv  # type: ignore[attr-defined]

    @property
    def attach_skew_b(self) -> np.ndarray:
        """``S(r_i)`` per cable (n, 3, 3)."""
        return self._attach_skew  # type: ignore[attr-defined]

    @classmethod
    def box(cls, mass_kg: float, size_m, attach_b_m, cable_length_m, **kw) -> LoadParams:
        """A solid box of ``size_m = (x, y, z)``: ``J = m/12 diag(y^2+z^2, x^2+z^2, x^2+y^2)``."""
        x, y, z = (float(s) for s in size_m)
        if min(x, y, z) <= 0:
            raise ValueError(f"size_m must be positive, got {size_m}")
        J = mass_kg / 12.0 * np.array([y * y + z * z, x * x + z * z, x * x + y * y])
        return cls(mass_kg, J, attach_b_m, cable_length_m, **kw)


@dataclass(frozen=True)
class LoadState:
    """The load's nominal state (module docstring): world z-up, SI units."""

    pos_w_m: np.ndarray
    vel_w_m_s: np.ndarray
    q_wxyz: np.ndarray
    omega_b_rad_s: np.ndarray
    tension_n: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "pos_w_m", _vec(self.pos_w_m, (3,), "pos_w_m"))
        object.__setattr__(self, "vel_w_m_s", _vec(self.vel_w_m_s, (3,), "vel_w_m_s"))
        q = _vec(self.q_wxyz, (4,), "q_wxyz")
        q = quat_normalize(q)
        q.setflags(write=False)
        object.__setattr__(self, "q_wxyz", q)
        object.__setattr__(self, "omega_b_rad_s", _vec(self.omega_b_rad_s, (3,), "omega_b_rad_s"))
        T = np.atleast_1d(np.asarray(self.tension_n, dtype=float))
        object.__setattr__(self, "tension_n", _vec(T, T.shape, "tension_n"))


@dataclass(frozen=True)
class VehicleStates:
    """Every carrying vehicle at one time (row ``i`` = the vehicle on cable ``i``): position and
    velocity in the world frame from its own estimator (GNSS-aided EKF), with the position's
    covariance; optionally its attitude (body to world) with the covariance of the world-frame
    attitude error (``q = Exp(dtheta) (x) q_hat``, the vehicle EKF's convention), which the
    marker's attitude measurement needs, and its body angular velocity ``rate_b_rad_s`` (zero if
    not given) to carry the attitude to an image's capture time. ``stamp_s`` is on the filter's
    clock (the simulation clock in the SITL)."""

    stamp_s: float
    pos_w_m: np.ndarray
    vel_w_m_s: np.ndarray
    pos_cov_m2: np.ndarray
    q_wxyz: np.ndarray | None = None
    att_cov_rad2: np.ndarray | None = None
    rate_b_rad_s: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not math.isfinite(self.stamp_s):
            raise ValueError("stamp_s must be finite")
        p = np.asarray(self.pos_w_m, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"pos_w_m must be (n_vehicles, 3), got {p.shape}")
        n = p.shape[0]
        object.__setattr__(self, "pos_w_m", _vec(p, (n, 3), "pos_w_m"))
        object.__setattr__(self, "vel_w_m_s", _vec(self.vel_w_m_s, (n, 3), "vel_w_m_s"))
        object.__setattr__(self, "pos_cov_m2", _cov(self.pos_cov_m2, (n, 3, 3), "pos_cov_m2"))
        if (self.q_wxyz is None) != (self.att_cov_rad2 is None):
            raise ValueError("q_wxyz and att_cov_rad2 come together (both or neither)")
        if self.q_wxyz is not None:
            q = _vec(self.q_wxyz, (n, 4), "q_wxyz")
            if np.any(np.abs(np.linalg.norm(q, axis=1) - 1.0) > 1e-6):
                raise ValueError("q_wxyz must be unit quaternions")
            object.__setattr__(self, "q_wxyz", q)
            object.__setattr__(self, "att_cov_rad2", _cov(self.att_cov_rad2, (n, 3, 3), "att_cov_rad2"))
        rate = np.zeros((n, 3)) if self.rate_b_rad_s is None else self.rate_b_rad_s
        object.__setattr__(self, "rate_b_rad_s", _vec(rate, (n, 3), "rate_b_rad_s"))

    @property
    def has_attitude(self) -> bool:
        return self.q_wxyz is not None

    def positions_at(self, t_s: float) -> np.ndarray:
        """Positions extrapolated with the velocities to ``t_s`` (n, 3)."""
        return self.pos_w_m + self.vel_w_m_s * (t_s - self.stamp_s)

    def attitudes_at(self, t_s: float) -> np.ndarray:
        """Attitudes carried with the body rates to ``t_s``, ``q (x) Exp(w (t - stamp))`` (n, 4);
        ``ValueError`` without attitudes."""
        if self.q_wxyz is None:
            raise ValueError("these vehicle samples carry no attitudes")
        return quat_normalize(quat_mul(self.q_wxyz, quat_from_rotvec(self.rate_b_rad_s * (t_s - self.stamp_s))))


@dataclass(frozen=True)
class LoadObservation:
    """One camera's measurement of the load, for the image captured at ``stamp_s`` (filter clock):
    eq. 4's vehicle ``vehicle``'s position in the load frame [m] with its covariance [m^2]; and,
    optionally, the load's attitude in that vehicle's body frame ``load_in_body_q_wxyz`` with
    ``joint_cov`` (6, 6), the covariance over ``[dy; dphi]`` (``dphi`` the body-frame rotation
    vector of ``R_bl = Exp(dphi) R_bl_hat``; its first block is ``cov_m2``)."""

    vehicle: int
    stamp_s: float
    vehicle_in_load_m: np.ndarray
    cov_m2: np.ndarray
    load_in_body_q_wxyz: np.ndarray | None = None
    joint_cov: np.ndarray | None = None

    def __post_init__(self) -> None:
        if int(self.vehicle) != self.vehicle or self.vehicle < 0:
            raise ValueError(f"vehicle must be a non-negative integer, got {self.vehicle}")
        if not math.isfinite(self.stamp_s):
            raise ValueError("stamp_s must be finite")
        object.__setattr__(self, "vehicle_in_load_m", _vec(self.vehicle_in_load_m, (3,), "vehicle_in_load_m"))
        cov = _cov(self.cov_m2, (3, 3), "cov_m2")
        if np.linalg.eigvalsh(cov)[0] <= 0:
            raise ValueError("cov_m2 must be positive definite")
        object.__setattr__(self, "cov_m2", cov)
        if (self.load_in_body_q_wxyz is None) != (self.joint_cov is None):
            raise ValueError("load_in_body_q_wxyz and joint_cov come together (both or neither)")
        if self.joint_cov is not None:
            q = _vec(self.load_in_body_q_wxyz, (4,), "load_in_body_q_wxyz")
            if abs(np.linalg.norm(q) - 1.0) > 1e-6:
                raise ValueError("load_in_body_q_wxyz must be a unit quaternion")
            joint = _cov(self.joint_cov, (6, 6), "joint_cov")
            if np.linalg.eigvalsh(joint)[0] <= 0:
                raise ValueError("joint_cov must be positive definite")
            if not np.allclose(joint[:3, :3], cov, rtol=1e-9, atol=1e-15):
                raise ValueError("joint_cov's position block must equal cov_m2")
            object.__setattr__(self, "load_in_body_q_wxyz", q)
            object.__setattr__(self, "joint_cov", joint)

    @property
    def has_attitude(self) -> bool:
        return self.joint_cov is not None


@dataclass(frozen=True)
class Pose3:
    """Pose of a child frame in a parent frame: ``x_parent = R(q_wxyz) x_child + pos_m``."""

    pos_m: np.ndarray
    q_wxyz: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "pos_m", _vec(self.pos_m, (3,), "pos_m"))
        q = quat_normalize(_vec(self.q_wxyz, (4,), "q_wxyz"))
        q.setflags(write=False)
        object.__setattr__(self, "q_wxyz", q)

    @property
    def R(self) -> np.ndarray:
        return quat_to_rotmat(self.q_wxyz)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis, broadcast (``np.cross`` costs ~30 us per call on small arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


# --- packing and the manifold ------------------------------------------------------------------


def pack_state(s: LoadState) -> np.ndarray:
    """:class:`LoadState` -> nominal vector (13 + n,)."""
    return np.concatenate((s.pos_w_m, s.vel_w_m_s, s.q_wxyz, s.omega_b_rad_s, s.tension_n))


def unpack_state(x: np.ndarray) -> LoadState:
    """Nominal vector -> :class:`LoadState`."""
    x = np.asarray(x, dtype=float)
    return LoadState(x[NOM_POS], x[NOM_VEL], x[NOM_QUAT], x[NOM_OMEGA], x[13:])


def boxplus(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """``x [+] dx``: add the error state, attitude by ``Exp(dtheta) (x) q`` (batched)."""
    x = np.asarray(x, dtype=float)
    dx = np.asarray(dx, dtype=float)
    n = x.shape[-1] - 13
    out = np.empty(np.broadcast_shapes(x.shape[:-1], dx.shape[:-1]) + (x.shape[-1],))
    out[..., NOM_POS] = x[..., NOM_POS] + dx[..., ERR_POS]
    out[..., NOM_VEL] = x[..., NOM_VEL] + dx[..., ERR_VEL]
    out[..., NOM_QUAT] = quat_mul(quat_from_rotvec(dx[..., ERR_ATT]), x[..., NOM_QUAT])
    out[..., NOM_OMEGA] = x[..., NOM_OMEGA] + dx[..., ERR_OMEGA]
    out[..., nominal_tension_slice(n)] = x[..., nominal_tension_slice(n)] + dx[..., error_tension_slice(n)]
    return out


def boxminus(x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """``x [-] x_ref``: the error state ``dx`` with ``x = x_ref [+] dx`` (batched)."""
    x = np.asarray(x, dtype=float)
    x_ref = np.asarray(x_ref, dtype=float)
    n = x.shape[-1] - 13
    out = np.empty(np.broadcast_shapes(x.shape[:-1], x_ref.shape[:-1]) + (12 + n,))
    out[..., ERR_POS] = x[..., NOM_POS] - x_ref[..., NOM_POS]
    out[..., ERR_VEL] = x[..., NOM_VEL] - x_ref[..., NOM_VEL]
    out[..., ERR_ATT] = attitude_error(x[..., NOM_QUAT], x_ref[..., NOM_QUAT])
    out[..., ERR_OMEGA] = x[..., NOM_OMEGA] - x_ref[..., NOM_OMEGA]
    out[..., error_tension_slice(n)] = x[..., nominal_tension_slice(n)] - x_ref[..., nominal_tension_slice(n)]
    return out


# --- dynamics (eq. 8) --------------------------------------------------------------------------


def cable_geometry(x: np.ndarray, vehicles_w_m: np.ndarray, params: LoadParams):
    """Per cable: ``d_i = t_i - p - R r_i`` (attachment point to vehicle, world), its length and
    unit vector ``u_i``; plus ``R`` and ``R r_i``. Shapes ``(B, n, 3)``, ``(B, n)``, ``(B, n, 3)``,
    ``(B, 3, 3)``, ``(B, n, 3)`` for ``x`` of shape ``(B, 13 + n)``."""
    R = quat_to_rotmat(x[..., NOM_QUAT])
    Rr = params.attach_b_m @ np.swapaxes(R, -1, -2)  # rows R r_i
    d = np.asarray(vehicles_w_m, dtype=float) - x[..., None, NOM_POS] - Rr
    length = np.sqrt(np.sum(d * d, axis=-1))
    u = d / np.maximum(length, 1e-9)[..., None]
    return d, length, u, R, Rr


def load_accelerations(x: np.ndarray, vehicles_w_m: np.ndarray, params: LoadParams):
    """Eq. 8: linear acceleration (world, m/s^2) and body angular acceleration (rad/s^2)."""
    x = np.asarray(x, dtype=float)
    n = params.n_cables
    _, _, u, R, _ = cable_geometry(x, vehicles_w_m, params)
    T = x[..., nominal_tension_slice(n)]
    acc = (T[..., None, :] @ u)[..., 0, :] / params.mass_kg
    acc[..., 2] -= params.gravity_m_s2  # (8a)
    u_b = u @ R  # rows R^T u_i
    torque_b = (T[..., None, :] @ cross(params.attach_b_m, u_b))[..., 0, :]
    w = x[..., NOM_OMEGA]
    Jw = w @ params.inertia_b_kg_m2.T
    alpha = (torque_b - cross(w, Jw)) @ params.inertia_inv_b.T  # (8b)
    return acc, alpha


def error_dynamics_jacobian(x: np.ndarray, vehicles_w_m: np.ndarray, params: LoadParams) -> np.ndarray:
    """Continuous-time Jacobian ``A`` of the error dynamics, ``d(dx)/dt = A dx`` (one state).

    With ``M_i = I - u_i u_i^T``, ``l_i`` the cable length, ``g_i = R^T u_i``:
    ``d u_i / d p = -M_i / l_i``, ``d u_i / d dtheta = M_i S(R r_i) / l_i``,
    ``d g_i / d dtheta = R^T (S(u_i) + M_i S(R r_i) / l_i)``, ``d dtheta/dt = R dw``.
    """
    x = np.asarray(x, dtype=float)
    n = params.n_cables
    N = error_dim(n)
    _, length, u, R, Rr = cable_geometry(x, vehicles_w_m, params)
    T = x[nominal_tension_slice(n)]
    w = x[NOM_OMEGA]
    J, Jinv = params.inertia_b_kg_m2, params.inertia_inv_b
    M = np.eye(3) - u[:, :, None] * u[:, None, :]  # (n, 3, 3)
    du_dp = -M / length[:, None, None]
    du_dth = -du_dp @ skew(Rr)
    RT = R.T
    dg_dp = RT @ du_dp
    dg_dth = RT @ (skew(u) + du_dth)
    TSr = T[:, None, None] * params.attach_skew_b  # T_i S(r_i)
    A = np.zeros((N, N))
    A[ERR_POS, ERR_VEL] = _I3
    A[ERR_VEL, ERR_POS] = (T @ du_dp.reshape(n, 9)).reshape(3, 3) / params.mass_kg
    A[ERR_VEL, ERR_ATT] = (T @ du_dth.reshape(n, 9)).reshape(3, 3) / params.mass_kg
    A[ERR_VEL, error_tension_slice(n)] = u.T / params.mass_kg
    A[ERR_ATT, ERR_OMEGA] = R
    A[ERR_OMEGA, ERR_POS] = Jinv @ (TSr @ dg_dp).sum(axis=0)
    A[ERR_OMEGA, ERR_ATT] = Jinv @ (TSr @ dg_dth).sum(axis=0)
    A[ERR_OMEGA, ERR_OMEGA] = -Jinv @ (skew(w) @ J - skew(J @ w))
    A[ERR_OMEGA, error_tension_slice(n)] = Jinv @ cross(params.attach_b_m, u @ R).T
    return A


_I3 = np.eye(3)


def _step_tangent(x: np.ndarray, rates, h: float) -> np.ndarray:
    """Move ``x`` along ``(v, a, w, alpha)`` for ``h`` seconds (attitude: ``q (x) Exp(h w)``)."""
    vel, acc, omega, alpha = rates
    out = x.copy()
    out[..., NOM_POS] += h * vel
    out[..., NOM_VEL] += h * acc
    out[..., NOM_QUAT] = quat_mul(x[..., NOM_QUAT], quat_from_rotvec(h * omega))
    out[..., NOM_OMEGA] += h * alpha
    return out


def propagate_nominal(x: np.ndarray, vehicles: VehicleStates, t_from_s: float, dt_s: float,
                      params: LoadParams, max_step_s: float) -> np.ndarray:
    """Integrate eq. 8 from ``t_from_s`` for ``dt_s`` (midpoint rule, steps <= ``max_step_s``),
    the vehicles moving with their velocities; tensions held (their random walk has zero mean).
    ``x`` may be batched ``(B, 13 + n)``."""
    x = np.asarray(x, dtype=float)
    if dt_s <= 0.0:
        return x.copy()
    n_sub = max(1, math.ceil(dt_s / max_step_s - 1e-9))
    h = dt_s / n_sub
    for k in range(n_sub):
        t = t_from_s + k * h
        acc, alpha = load_accelerations(x, vehicles.positions_at(t), params)
        mid = _step_tangent(x, (x[..., NOM_VEL], acc, x[..., NOM_OMEGA], alpha), 0.5 * h)
        acc, alpha = load_accelerations(mid, vehicles.positions_at(t + 0.5 * h), params)
        x = _step_tangent(x, (mid[..., NOM_VEL], acc, mid[..., NOM_OMEGA], alpha), h)
        x[..., NOM_QUAT] = quat_normalize(x[..., NOM_QUAT])
    return x


def static_tensions(x: np.ndarray, vehicles_w_m: np.ndarray, params: LoadParams) -> np.ndarray:
    """Tensions [N] that hold the load at rest in the current geometry: the least-squares
    solution of ``sum_i T_i u_i = m g e3`` and zero torque (eq. 8 with ``a = 0``, ``w = 0``)."""
    _, _, u, R, _ = cable_geometry(np.asarray(x, dtype=float), vehicles_w_m, params)
    g = u @ R
    A = np.vstack((u.T, cross(params.attach_b_m, g).T))
    b = np.concatenate(([0.0, 0.0, params.mass_kg * params.gravity_m_s2], np.zeros(3)))
    T, *_ = np.linalg.lstsq(A, b, rcond=None)
    return T

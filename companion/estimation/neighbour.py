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
covariance is the PnP's plus the mounts' (:func:`mount_covariance`: ``c``, ``m``, ``R_bc`` and
``R_bm`` are known to a calibration's accuracy only; PnP alone puts the marker's centre to a
fraction of a millimetre, and the lever arm of the camera to the marker turns that into an
attitude measurement the mounts cannot back). Unlike the chain constraint, it measures the relative attitude too, and
it needs no absolute position: common-mode GNSS errors cancel in it.

:func:`neighbour_updates` applies such measurements (:class:`NeighbourMeasurement`) to a chain's
EKF estimates as iterated Kalman updates on their stacked state (with GNSS positions known to
metres, the camera's lever arm at the prior is that far off, and a single linearisation hides the
relative attitude in the positions), before the constraint application:
independent estimates before them, correlated after (the covariance is returned whole, as
:func:`~.sckf.constraint_apply_dense` takes it). :func:`relative_pose_update` is one measurement
of one pair. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .chain import ERR_DIM, ERR_P, ERR_TH, ChainInputError
from .sckf import block_diag_covariance, inject_errors
from .so3 import quat_from_rotvec, quat_mul, quat_to_rotmat, quat_to_rotvec, rotmat_to_quat, skew

__all__ = ["ITERATIONS", "NEIGHBOUR_GATE_CHI2", "NeighbourView", "marker_in_camera", "relative_pose_residual",
           "relative_pose_jacobian", "mount_covariance", "NeighbourMeasurement", "NeighbourUpdates",
           "neighbour_updates", "RelativePoseUpdate", "relative_pose_update"]

#: the gate of a neighbour measurement: chi-square with 6 degrees of freedom at 0.999
NEIGHBOUR_GATE_CHI2 = 22.46
#: Gauss-Newton iterations of each update at most, and the change of the error state [m, m/s,
#: rad] below which they stop
ITERATIONS = 5
ITERATION_TOL = 1e-9

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


def mount_covariance(t_cm_m, std_m: float, std_rad: float) -> np.ndarray:
    """(6, 6) covariance over ``[dtheta_c; dt]`` of a pose measured at ``t_cm_m`` from the mounts'
    calibration errors: each of the two mounts' positions off by ``std_m`` per axis, each of their
    orientations by ``std_rad`` per axis, all independent. With the camera turned by ``phi``
    (camera frame) the measured pose is ``(Exp(-phi) R_cm, Exp(-phi) t_cm)``: ``dtheta_c = -phi``,
    ``dt = S(t_cm) phi``; the marker turned by ``psi`` turns the measured attitude by ``R_cm psi``
    (isotropic: ``std_rad^2 I``) and leaves its centre; a mount moved moves the centre
    (``std_m^2 I`` each)."""
    J = np.vstack([-np.eye(3), skew(np.asarray(t_cm_m, dtype=float))])  # camera orientation
    cov = std_rad**2 * (J @ J.T)
    cov[RES_ROT, RES_ROT] += std_rad**2 * np.eye(3)  # marker orientation
    cov[RES_POS, RES_POS] += 2.0 * std_m**2 * np.eye(3)  # camera and marker positions
    return cov


@dataclass(frozen=True)
class NeighbourMeasurement:
    """One camera measurement inside a chain (or a group of it): link ``observer`` (0-based)
    sees the marker of link ``observed`` at ``(R_cm, t_cm_m)`` (the PnP pose, camera frame) with
    covariance ``cov`` (6, 6) over ``[dtheta_c; dt]``, through ``view``; ``age_s``: how long
    before the states it updates it was captured (the model is then evaluated at the states
    taken back that long: :func:`neighbour_updates`). ``ChainInputError`` for shapes,
    non-finite values, one link seeing itself, a covariance that is not positive definite or a
    negative age."""

    observer: int
    observed: int
    R_cm: np.ndarray
    t_cm_m: np.ndarray
    cov: np.ndarray
    view: NeighbourView
    age_s: float = 0.0

    def __post_init__(self) -> None:
        if int(self.observer) == int(self.observed) or min(int(self.observer), int(self.observed)) < 0:
            raise ChainInputError(f"a link sees another's marker: got observer {self.observer}, observed "
                                  f"{self.observed}", field="observed")
        for name, shape in (("R_cm", (3, 3)), ("t_cm_m", (3,)), ("cov", (6, 6))):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != shape or not np.all(np.isfinite(arr)):
                raise ChainInputError(f"{name} must be finite with shape {shape}, got {arr.shape}", field=name)
            object.__setattr__(self, name, arr)
        cov = 0.5 * (self.cov + self.cov.T)
        if np.linalg.eigvalsh(cov)[0] <= 0.0:
            raise ChainInputError("cov must be positive definite", field="cov")
        object.__setattr__(self, "cov", cov)
        if not (np.isfinite(self.age_s) and self.age_s >= 0.0):
            raise ChainInputError(f"age_s must be finite and >= 0, got {self.age_s!r}", field="age_s")

    def numbered_from(self, first: int) -> NeighbourMeasurement:
        """The same measurement with its links numbered from link ``first`` (a segment's or a
        group's first)."""
        return replace(self, observer=self.observer - first, observed=self.observed - first)


@dataclass(frozen=True)
class NeighbourUpdates:
    """The links after the measurements: positions, velocities, attitudes ((n, 3), (n, 3),
    (n, 4)), their whole (9n, 9n) covariance (correlated by the measurements), and per
    measurement its normalised innovation squared and whether it passed the gate."""

    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    P: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray


def neighbour_updates(p, v, q, P, measurements, gate_chi2: float | None = None, w=None,
                      iterations: int = ITERATIONS, d=None) -> NeighbourUpdates:
    """Kalman updates of ``n`` links (``p``, ``v`` (n, 3), ``q`` (n, 4); ``P`` their (n, 9, 9)
    independent EKF covariances or a whole (9n, 9n) one) with each of ``measurements``
    (:class:`NeighbourMeasurement`) in turn, on the stacked state: each moves every link its
    pair is correlated with, and the covariance comes back whole, ready for the constraint
    application (:func:`~.sckf.constraint_apply_dense`). Each update is iterated (Gauss-Newton
    from the prior, relinearised at the newest estimate, at most ``iterations`` times; 1: the
    plain update), its covariance in Joseph form with the last gain; the error is injected as
    the chain's estimators do (positions and velocities added, attitudes by
    :func:`~.so3.retract`). ``gate_chi2``: a measurement above this NIS (6 dof, at the prior) is
    rejected and changes nothing. ``w`` (n, 3): the links' body rates; a measurement ``age_s``
    old is then compared with the model at the pair's states taken back that long (``q (x)
    Exp(-w age)``, ``p - v age``, as the step aligns states forward), its Jacobian at the states
    themselves; without ``w`` the age is not used. With ``d`` (n, 3), the links' tip vectors, a
    pair of joined links is taken back as joined (:func:`_taken_back`): the observed link moves
    with the observer and the turn of the two about their joint, not by its own velocity (two
    links' velocity errors over the age are millimetres of relative position, through their
    rates a fraction of one). ``ChainInputError`` for shapes, non-finite values or a link out of range."""
    p, v, q = (np.array(a, dtype=float) for a in (p, v, q))
    n = p.shape[0] if p.ndim == 2 else -1
    for name, arr, shape in (("p", p, (n, 3)), ("v", v, (n, 3)), ("q", q, (n, 4))):
        if n < 2 or arr.shape != shape or not np.all(np.isfinite(arr)):
            raise ChainInputError(f"{name} must be finite with shape {shape} (n >= 2), got {arr.shape}", field=name)
    P = np.asarray(P, dtype=float)
    N = ERR_DIM * n
    if P.shape == (n, ERR_DIM, ERR_DIM):
        P = block_diag_covariance(P)
    elif P.shape != (N, N):
        raise ChainInputError(f"P must be ({n}, 9, 9) blocks or ({N}, {N}), got {P.shape}", field="P")
    if not np.all(np.isfinite(P)):
        raise ChainInputError("P must be finite", field="P")
    if d is not None:
        d = np.asarray(d, dtype=float)
        if d.shape != (n, 3) or not np.all(np.isfinite(d)):
            raise ChainInputError(f"d must be finite with shape {(n, 3)}, got {d.shape}", field="d")
    nis, accepted = np.zeros(len(measurements)), np.zeros(len(measurements), dtype=bool)
    for k, m in enumerate(measurements):
        i, j = int(m.observer), int(m.observed)
        if max(i, j) >= n:
            raise ChainInputError(f"measurement {k}: links {i} and {j} of {n}", field="measurements", index=max(i, j))
        r, H = _residual_and_jacobian(m, p, v, q, w, d, i, j, N)
        PHt = P @ H.T
        S = H @ PHt + m.cov
        nis[k] = float(r @ np.linalg.solve(0.5 * (S + S.T), r))
        if gate_chi2 is not None and nis[k] > gate_chi2:
            continue
        accepted[k] = True
        # iterated (Gauss-Newton from the prior x0): the residual and its Jacobian at the newest
        # estimate x, the innovation taken back to x0 as r(x0) ~ r(x) + H (x - x0); one
        # iteration is the plain update. (Positions known to metres only put the camera's lever
        # arm far from where the chain holds it; the first pass corrects them, the next ones the
        # attitudes they hid.)
        dx = np.zeros(N)
        x = (p, v, q)
        for it in range(iterations):
            K = PHt @ np.linalg.inv(0.5 * (S + S.T))
            new = K @ (r + H @ dx)
            done = float(np.max(np.abs(new - dx))) < ITERATION_TOL
            dx = new
            x = inject_errors(p, v, q, dx.reshape(n, ERR_DIM))
            if done or it == iterations - 1:
                break
            r, H = _residual_and_jacobian(m, *x, w, d, i, j, N)
            PHt = P @ H.T
            S = H @ PHt + m.cov
        A = np.eye(N) - K @ H
        P = A @ P @ A.T + K @ m.cov @ K.T
        P = 0.5 * (P + P.T)
        p, v, q = x
    return NeighbourUpdates(p, v, q, P, nis, accepted)


def _taken_back(p, v, q, w, d, i: int, j: int, age_s: float):
    """Links ``i`` and ``j`` taken back ``age_s``: ``((p_i, q_i), (p_j, q_j))``. Each turns back by
    its body rate (``q (x) Exp(-w age)``) and the observer moves back by its velocity; the observed
    link by its own velocity, or, with ``d`` and the two joined (``|i - j| = 1``), with the
    observer and the change of the joint's lever arms: ``p_j - p_i = s (R_i d_i + R_j d_j)`` with
    ``s`` = 1 when ``j`` follows ``i`` (eq. 3's joint), -1 when it precedes it."""
    qb = {k: quat_mul(q[k], quat_from_rotvec(-w[k] * age_s)) for k in (i, j)}
    pi = p[i] - v[i] * age_s
    if d is None or abs(i - j) != 1:
        return (pi, qb[i]), (p[j] - v[j] * age_s, qb[j])
    s = 1.0 if j == i + 1 else -1.0
    lever = sum((quat_to_rotmat(qb[k]) - quat_to_rotmat(q[k])) @ d[k] for k in (i, j))
    return (pi, qb[i]), (p[j] - v[i] * age_s + s * lever, qb[j])


def _residual_and_jacobian(m: NeighbourMeasurement, p, v, q, w, d, i: int, j: int, N: int):
    """Measurement ``m``'s residual (at the capture time when ``w`` is given: :func:`_taken_back`)
    and its (6, N) Jacobian on the stacked error state, at the states ``p``, ``v``, ``q``."""
    if w is not None and m.age_s > 0.0:  # the model at the capture time
        (pi, qi), (pj, qj) = _taken_back(p, v, q, w, d, i, j, m.age_s)
        r = relative_pose_residual(m.R_cm, m.t_cm_m, pi, qi, pj, qj, m.view)
    else:
        r = relative_pose_residual(m.R_cm, m.t_cm_m, p[i], q[i], p[j], q[j], m.view)
    H = np.zeros((6, N))
    H[:, ERR_DIM * i:ERR_DIM * (i + 1)], H[:, ERR_DIM * j:ERR_DIM * (j + 1)] = \
        relative_pose_jacobian(p[i], q[i], p[j], q[j], m.view)
    return r, H


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
    """:func:`neighbour_updates` of two links (rows 0 = observing ``i``, 1 = observed ``j``:
    ``p``, ``v`` (2, 3), ``q`` (2, 4), ``P_blocks`` (2, 9, 9), their independent EKF
    covariances) with one PnP pose of the marker and its covariance ``cov_pnp`` (6, 6)."""
    P_blocks = np.asarray(P_blocks, dtype=float)
    if P_blocks.shape != (2, ERR_DIM, ERR_DIM):
        raise ChainInputError(f"P must be finite with shape (2, 9, 9), got {P_blocks.shape}", field="P")
    up = neighbour_updates(p, v, q, P_blocks, [NeighbourMeasurement(0, 1, R_cm_meas, t_cm_meas, cov_pnp, view)],
                           gate_chi2)
    return RelativePoseUpdate(up.p, up.v, up.q, up.P, float(up.nis[0]), bool(up.accepted[0]))

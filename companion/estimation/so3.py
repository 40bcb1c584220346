"""Quaternion and SO(3) helpers with the conventions of DESIGN.md sec. 4.

Conventions (used everywhere in the estimation core):

* Quaternions are Hamilton, scalar first: ``q = [w, x, y, z]``.
* A link attitude ``q`` maps body vectors to the world frame: ``v_w = R(q) v_b``.
* The world frame ``W`` is z-up (gravity is ``[0, 0, -g]``), as in the paper's model
  (``m p'' + m g e3 = ...``, sec. II). Conversion to MAVLink's NED/FRD happens at the
  MAVLink boundary only.
* Attitude errors are world-frame small angles (paper sec. III-A, eq. 2 text):
  ``q_true = dq(dtheta) (x) q_hat``, i.e. ``q (x) q_hat^-1 ~ [1; dtheta/2]``, so
  ``R_true ~ (I + S(dtheta)) R_hat``. Error injection therefore multiplies on the left
  (:func:`retract`). (Alg. 1's text writes ``q_hat (x) dq``; that right product belongs to a
  body-frame error and contradicts both the paper's error definition and the Jacobian of
  eq. 4, which is written for the world-frame error. We follow the definition and eq. 4.)

All functions are vectorised over leading dimensions: a ``(..., 4)`` array of quaternions
gives a ``(..., 3, 3)`` array of rotation matrices, and so on. No I/O, no state.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "skew",
    "cross",
    "quat_mul",
    "quat_conj",
    "quat_normalize",
    "quat_to_rotmat",
    "rotmat_tuple",
    "rotmat_to_quat",
    "quat_from_rotvec",
    "quat_to_rotvec",
    "small_angle_quat",
    "retract",
    "attitude_error",
    "quat_distance",
    "quat_rotate",
    "quat_from_euler_zyx",
    "yaw_from_quat",
]


def _skew_basis() -> np.ndarray:
    T = np.zeros((3, 3, 3))
    # S(v) = sum_k v_k T[k]
    T[0, 1, 2], T[0, 2, 1] = -1.0, 1.0
    T[1, 0, 2], T[1, 2, 0] = 1.0, -1.0
    T[2, 0, 1], T[2, 1, 0] = -1.0, 1.0
    return T.reshape(3, 9)


_SKEW_BASIS = _skew_basis()


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix S(v) with S(v) u = v x u; ``(..., 3) -> (..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:
        x, y, z = v.tolist()
        return np.array(((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0)))
    return (v @ _SKEW_BASIS).reshape(v.shape[:-1] + (3, 3))


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis of (..., 3) arrays (broadcast): ``np.cross``'s operations and
    numbers without its axis handling, which costs it 10-20 us a call on small arrays (the
    companion's per-target chain dynamics calls it a dozen times)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.shape == b.shape == (3,):
        (a0, a1, a2), (b0, b1, b2) = a.tolist(), b.tolist()
        return np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def _product_tensor() -> np.ndarray:
    """(16, 4) map from the outer product a b^T (flattened) to the Hamilton product a (x) b."""
    T = np.zeros((4, 4, 4))
    # (w, x, y, z) components of a (x) b as sums of sign * a_i b_j.
    terms = {
        0: [(0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)],
        1: [(0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)],
        2: [(0, 2, 1), (1, 3, -1), (2, 0, 1), (3, 1, 1)],
        3: [(0, 3, 1), (1, 2, 1), (2, 1, -1), (3, 0, 1)],
    }
    for k, entries in terms.items():
        for i, j, sign in entries:
            T[i, j, k] = sign
    return T.reshape(16, 4)


_PRODUCT = _product_tensor()


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a (x) b`` (scalar first), broadcast over leading dims."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.ndim == 1 and b.ndim == 1:  # one product: plain floats beat numpy's per-call overhead
        aw, ax, ay, az = a.tolist()
        bw, bx, by, bz = b.tolist()
        return np.array(
            (
                aw * bw - ax * bx - ay * by - az * bz,
                aw * bx + ax * bw + ay * bz - az * by,
                aw * by - ax * bz + ay * bw + az * bx,
                aw * bz + ax * by - ay * bx + az * bw,
            )
        )
    outer = a[..., :, None] * b[..., None, :]
    return (outer.reshape(outer.shape[:-2] + (16,))) @ _PRODUCT


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion)."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with the same direction; raises ``ValueError`` on a zero quaternion."""
    q = np.asarray(q, dtype=float)
    norm = np.sqrt(np.einsum("...i,...i->...", q, q))[..., None]
    if norm.min() < 1e-12:
        raise ValueError("cannot normalise a zero quaternion")
    return q / norm


def _rotmat_quadratic_form() -> np.ndarray:
    """(16, 9) map from the outer product q q^T (flattened) to R(q) (flattened).

    R = (w^2 - |u|^2) I + 2 u u^T + 2 w S(u) for q = [w; u], all quadratic in q.
    """
    M = np.zeros((4, 4, 3, 3))
    for k in range(3):
        M[0, 0, k, k] += 1.0
        for l in range(3):
            M[1 + l, 1 + l, k, k] -= 1.0
            M[1 + k, 1 + l, k, l] += 2.0
    S = _SKEW_BASIS.reshape(3, 3, 3)
    for k in range(3):
        M[0, 1 + k] += 2.0 * S[k]
    return M.reshape(16, 9)


_ROTMAT_FORM = _rotmat_quadratic_form()


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix R(q) (body to world) of unit quaternions; ``(..., 4) -> (..., 3, 3)``."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        return np.array(rotmat_tuple(q.tolist())).reshape(3, 3)
    outer = (q[..., :, None] * q[..., None, :]).reshape(q.shape[:-1] + (16,))
    return (outer @ _ROTMAT_FORM).reshape(q.shape[:-1] + (3, 3))


def rotmat_tuple(q) -> tuple:
    """R(q) of one unit quaternion ``(w, x, y, z)`` as a row-major 9-tuple of floats.

    For the 500 Hz firmware paths, where numpy's per-call overhead dominates 3x3 arithmetic.
    """
    w, x, y, z = q
    return (
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w >= 0) of rotation matrices; ``(..., 3, 3) -> (..., 4)``.

    Shepperd's method: picks the numerically largest of w, x, y, z as pivot.
    """
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    tr = np.trace(flat, axis1=1, axis2=2)
    diag = np.stack((tr, flat[:, 0, 0], flat[:, 1, 1], flat[:, 2, 2]), axis=1)
    pivot = np.argmax(diag, axis=1)
    for k, Rk in enumerate(flat):
        p = pivot[k]
        if p == 0:
            s = 2.0 * np.sqrt(1.0 + tr[k])
            out[k] = (0.25 * s, (Rk[2, 1] - Rk[1, 2]) / s, (Rk[0, 2] - Rk[2, 0]) / s, (Rk[1, 0] - Rk[0, 1]) / s)
        elif p == 1:
            s = 2.0 * np.sqrt(1.0 + Rk[0, 0] - Rk[1, 1] - Rk[2, 2])
            out[k] = ((Rk[2, 1] - Rk[1, 2]) / s, 0.25 * s, (Rk[0, 1] + Rk[1, 0]) / s, (Rk[0, 2] + Rk[2, 0]) / s)
        elif p == 2:
            s = 2.0 * np.sqrt(1.0 - Rk[0, 0] + Rk[1, 1] - Rk[2, 2])
            out[k] = ((Rk[0, 2] - Rk[2, 0]) / s, (Rk[0, 1] + Rk[1, 0]) / s, 0.25 * s, (Rk[1, 2] + Rk[2, 1]) / s)
        else:
            s = 2.0 * np.sqrt(1.0 - Rk[0, 0] - Rk[1, 1] + Rk[2, 2])
            out[k] = ((Rk[1, 0] - Rk[0, 1]) / s, (Rk[0, 2] + Rk[2, 0]) / s, (Rk[1, 2] + Rk[2, 1]) / s, 0.25 * s)
    out *= np.where(out[:, :1] < 0.0, -1.0, 1.0)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.reshape(R.shape[:-2] + (4,))


def quat_from_rotvec(rv: np.ndarray) -> np.ndarray:
    """Exponential map: rotation vector (angle * axis, rad) to unit quaternion."""
    rv = np.asarray(rv, dtype=float)
    angle = np.linalg.norm(rv, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a with its Taylor series near zero.
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / safe)
    return np.concatenate((np.cos(half), k * rv), axis=-1)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Logarithm map of unit quaternions to rotation vectors with angle in [0, pi]."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        w, x, y, z = q.tolist()
        if w < 0.0:
            w, x, y, z = -w, -x, -y, -z
        s = math.sqrt(x * x + y * y + z * z)
        k = 2.0 * math.atan2(s, w) / s if s > 1e-12 else 2.0 / max(w, 1e-300)
        return np.array((k * x, k * y, k * z))
    q = q * np.where(q[..., :1] < 0.0, -1.0, 1.0)
    vec = q[..., 1:]
    s = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    small = s < 1e-12
    scale = np.where(small, 2.0 / np.maximum(q[..., :1], 1e-300), angle / np.where(small, 1.0, s))
    return scale * vec


def small_angle_quat(dtheta: np.ndarray) -> np.ndarray:
    """The paper's error quaternion ``dq ~ [1; dtheta/2]``, normalised (Alg. 1 update)."""
    dtheta = np.asarray(dtheta, dtype=float)
    dq = np.empty(dtheta.shape[:-1] + (4,))
    dq[..., 0] = 1.0
    dq[..., 1:] = 0.5 * dtheta
    return dq / np.sqrt(np.einsum("...i,...i->...", dq, dq))[..., None]


def retract(q: np.ndarray, dtheta: np.ndarray) -> np.ndarray:
    """Inject a world-frame attitude error: ``q <- normalise(dq(dtheta)) (x) q``."""
    q = np.asarray(q, dtype=float)
    dtheta = np.asarray(dtheta, dtype=float)
    if q.ndim == 1 and dtheta.ndim == 1:
        hx, hy, hz = (0.5 * dtheta).tolist()
        w, x, y, z = q.tolist()
        # (1, h) (x) q, then one normalisation (dq's own normalisation cancels in it).
        rw = w - hx * x - hy * y - hz * z
        rx = x + hx * w + hy * z - hz * y
        ry = y - hx * z + hy * w + hz * x
        rz = z + hx * y - hy * x + hz * w
        inv = 1.0 / math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
        return np.array((rw * inv, rx * inv, ry * inv, rz * inv))
    return quat_normalize(quat_mul(small_angle_quat(dtheta), q))


def attitude_error(q_to: np.ndarray, q_from: np.ndarray) -> np.ndarray:
    """World-frame rotation vector ``dtheta`` with ``q_to = Exp(dtheta) (x) q_from``."""
    return quat_to_rotvec(quat_mul(q_to, quat_conj(q_from)))


def quat_distance(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """2-norm of the quaternion difference, sign-aligned (q and -q are the same attitude).

    This is the paper's "quaternion error" metric (sec. IV, Table II).
    """
    q_a = np.asarray(q_a, dtype=float)
    q_b = np.asarray(q_b, dtype=float)
    return np.minimum(np.linalg.norm(q_a - q_b, axis=-1), np.linalg.norm(q_a + q_b, axis=-1))


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate body vectors into the world frame: ``R(q) v``."""
    return np.einsum("...ij,...j->...i", quat_to_rotmat(q), np.asarray(v, dtype=float))


def quat_from_euler_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Quaternion of ``Rz(yaw) Ry(pitch) Rx(roll)`` (intrinsic z-y-x, radians)."""
    yaw, pitch, roll = (np.asarray(a, dtype=float) for a in (yaw, pitch, roll))
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    cp, sp = np.cos(0.5 * pitch), np.sin(0.5 * pitch)
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    return np.stack(
        (
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ),
        axis=-1,
    )


def yaw_from_quat(q: np.ndarray) -> np.ndarray:
    """Heading (rotation about world z, rad) of the body x axis: ``atan2(R10, R00)``."""
    R = quat_to_rotmat(q)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])

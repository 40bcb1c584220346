"""Frame conversions at the MAVLink boundary (the only place they happen).

Inside the stack: world frame ENU (x east, y north, z up) and link body frame FLU (x along the
link towards its right tip, y left, z up). On MAVLink: local NED and body FRD. Both changes are
proper rotations and their own inverses:

* ENU <-> NED: ``[x, y, z] -> [y, x, -z]`` (180 deg about ``(1, 1, 0)/sqrt 2``);
* FLU <-> FRD: ``[x, y, z] -> [x, -y, -z]`` (180 deg about x).

A body-to-world attitude converts as ``q_ned_frd = q_E2N (x) q_enu_flu (x) q_F2F``; a world
error state ``[dp; dv; dtheta]`` and its covariance rotate block by block with ``M_E2N``.
"""

from __future__ import annotations

import math

import numpy as np

from companion.estimation.so3 import quat_mul

__all__ = [
    "ENU_NED",
    "FLU_FRD",
    "enu_ned",
    "flu_frd",
    "quat_enu_flu_to_ned_frd",
    "quat_ned_frd_to_enu_flu",
    "FRAME_CHANGE_QUATS",
    "error_cov_enu_ned",
    "UPPER_9",
    "pack_upper",
    "unpack_upper",
]

ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
FLU_FRD = np.diag([1.0, -1.0, -1.0])
_S = 1.0 / math.sqrt(2.0)
_Q_E2N = np.array([0.0, _S, _S, 0.0])  # rotation ENU -> NED
_Q_F2F = np.array([0.0, 1.0, 0.0, 0.0])  # rotation FLU -> FRD
#: ``q_E2N`` then ``q_F2F`` (8,): the attitude's frame change as data, for a compiled copy of
#: :func:`quat_ned_frd_to_enu_flu` that must give its numbers (the vehicle's record tick)
FRAME_CHANGE_QUATS = np.concatenate((_Q_E2N, _Q_F2F))
FRAME_CHANGE_QUATS.setflags(write=False)
_T9 = np.kron(np.eye(3), ENU_NED)  # [dp; dv; dtheta]

#: Row-major upper triangle (diagonal included) of a 9x9 matrix: the order of the 45
#: covariance floats in SKELETON_LINK_STATE, shared by every codec.
UPPER_9 = np.triu_indices(9)


def enu_ned(v: np.ndarray) -> np.ndarray:
    """World vector ENU -> NED, or NED -> ENU (the map is its own inverse)."""
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:  # one vector (the per-message case): avoid numpy's per-call overhead
        x, y, z = v.tolist()
        return np.array((y, x, -z))
    return np.stack((v[..., 1], v[..., 0], -v[..., 2]), axis=-1)


_FLIP_YZ = np.array([1.0, -1.0, -1.0])


def flu_frd(v: np.ndarray) -> np.ndarray:
    """Body vector FLU -> FRD, or FRD -> FLU."""
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:
        x, y, z = v.tolist()
        return np.array((x, -y, -z))
    return v * _FLIP_YZ  # (exactly the negations: a product by -1 only flips the sign)


def quat_enu_flu_to_ned_frd(q: np.ndarray) -> np.ndarray:
    return quat_mul(quat_mul(_Q_E2N, q), _Q_F2F)


def quat_ned_frd_to_enu_flu(q: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quat_enu_flu_to_ned_frd`: the same product, because both frame
    rotations are 180-degree turns (``q^-1 = -q``, and the two signs cancel)."""
    return quat_enu_flu_to_ned_frd(q)


def error_cov_enu_ned(P: np.ndarray) -> np.ndarray:
    """9x9 covariance of ``[dp; dv; dtheta]`` ENU -> NED, or NED -> ENU."""
    return _T9 @ P @ _T9.T


def pack_upper(P: np.ndarray) -> list[float]:
    """45 floats: the row-major upper triangle of a symmetric 9x9 matrix."""
    return np.asarray(P, dtype=float)[UPPER_9].tolist()


def unpack_upper(values) -> np.ndarray:
    """Symmetric 9x9 matrix from :func:`pack_upper`'s 45 floats."""
    v = np.asarray(values, dtype=float)
    if v.shape != (45,):
        raise ValueError(f"covariance: expected 45 values, got {v.shape}")
    P = np.empty((9, 9))
    P[UPPER_9] = v
    P[UPPER_9[1], UPPER_9[0]] = v  # the mirror (the diagonal written twice, the same values)
    return P

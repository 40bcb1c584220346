"""Kinematic chain constraint (paper eq. 3) and its error-state Jacobian (eq. 4).

Links ``i`` and ``i+1`` share a ball joint: the right tip of link ``i`` (``+d_i`` from its
centre, body frame) coincides with the left tip of link ``i+1`` (``-d_{i+1}``) in position
and in velocity::

    c_i = [p_i + R_i d_i - (p_{i+1} - R_{i+1} d_{i+1});
           v_i + R_i S(w_i) d_i - (v_{i+1} - R_{i+1} S(w_{i+1}) d_{i+1})]        (eq. 3)

With the world-frame attitude error ``R = (I + S(dtheta)) R_hat`` (see :mod:`.so3`) the
linearisation is (eq. 4)::

    c~_i = [dp_i - S(R_i d_i) dth_i;  dv_i - S(R_i S(w_i) d_i) dth_i]
         - [dp_{i+1} + S(R_{i+1} d_{i+1}) dth_{i+1};  dv_{i+1} + S(R_{i+1} S(w_{i+1}) d_{i+1}) dth_{i+1}]

so the Jacobian only couples neighbours: row block ``i`` has a 6x9 block ``L_i`` in column
block ``i`` and ``R_i`` in column block ``i+1``. The angular velocity ``w`` is an input
(not estimated by the constraint application).
"""

from __future__ import annotations

import numpy as np

from .chain import CON_DIM, CON_POS, CON_VEL, ERR_DIM, ERR_P, ERR_TH, ERR_V
from .so3 import quat_to_rotmat, skew

__all__ = [
    "tip_offsets",
    "body_tip_vectors",
    "tips_from_body",
    "constraint_residual",
    "constraint_norm",
    "joint_error_norms",
    "constraint_jacobian_blocks",
    "constraint_jacobian",
    "residual_from_tips",
    "jacobian_blocks_from_tips",
    "dense_jacobian_from_blocks",
    "left_tip",
    "right_tip",
    "tip_jacobians",
]


def body_tip_vectors(w: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Body-frame ``[d, w x d]`` per link as ``(..., n, 3, 2)`` (constant during one CA call)."""
    w, d = np.broadcast_arrays(w, d)
    wxd = np.empty(w.shape)
    wxd[..., 0] = w[..., 1] * d[..., 2] - w[..., 2] * d[..., 1]
    wxd[..., 1] = w[..., 2] * d[..., 0] - w[..., 0] * d[..., 2]
    wxd[..., 2] = w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]
    return np.stack((d, wxd), axis=-1)


def tips_from_body(q: np.ndarray, body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(a, b) = (R d, R S(w) d)`` from :func:`body_tip_vectors`."""
    ab = quat_to_rotmat(q) @ body
    return ab[..., 0], ab[..., 1]


def tip_offsets(q: np.ndarray, w: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-frame right-tip offset ``a = R d`` and its velocity ``b = R S(w) d`` per link.

    Shapes ``(..., n, 4)``, ``(..., n, 3)``, ``(..., n, 3)`` -> two ``(..., n, 3)``; leading
    dimensions batch independent chains of equal length.
    """
    return tips_from_body(q, body_tip_vectors(w, d))


def right_tip(p, v, q, w, d) -> np.ndarray:
    """(..., n, 6) right-tip [position; velocity] of every link."""
    a, b = tip_offsets(q, w, d)
    return np.concatenate((p + a, v + b), axis=-1)


def left_tip(p, v, q, w, d) -> np.ndarray:
    """(..., n, 6) left-tip [position; velocity] of every link (offset ``-d``)."""
    a, b = tip_offsets(q, w, d)
    return np.concatenate((p - a, v - b), axis=-1)


def constraint_residual(p, v, q, w, d) -> np.ndarray:
    """Stacked constraint error ``c`` of eq. 3, shape ``(..., 6 (n-1))`` (empty for one link)."""
    return residual_from_tips(p, v, *tip_offsets(q, w, d))


def residual_from_tips(p, v, a, b) -> np.ndarray:
    """Eq. 3 from precomputed :func:`tip_offsets` ``(a, b)``."""
    c = np.empty(p.shape[:-2] + (p.shape[-2] - 1, CON_DIM))
    c[..., CON_POS] = (p[..., :-1, :] + a[..., :-1, :]) - (p[..., 1:, :] - a[..., 1:, :])
    c[..., CON_VEL] = (v[..., :-1, :] + b[..., :-1, :]) - (v[..., 1:, :] - b[..., 1:, :])
    return c.reshape(p.shape[:-2] + (-1,))


def joint_error_norms(p, v, q, w, d) -> tuple[np.ndarray, np.ndarray]:
    """Per joint, the norms of the eq. 3 tip position and velocity errors: two ``(..., n-1)`` arrays."""
    c = constraint_residual(p, v, q, w, d).reshape(np.shape(p)[:-2] + (-1, CON_DIM))
    return np.linalg.norm(c[..., CON_POS], axis=-1), np.linalg.norm(c[..., CON_VEL], axis=-1)


def constraint_norm(p, v, q, w, d) -> float:
    """``||c||_2`` of the stacked residual, the stop criterion of Alg. 1."""
    return float(np.linalg.norm(constraint_residual(p, v, q, w, d)))


def constraint_jacobian_blocks(q, w, d) -> tuple[np.ndarray, np.ndarray]:
    """Non-zero blocks of the eq. 4 Jacobian.

    Returns ``(L, R)``, each ``(..., n-1, 6, 9)``: ``L[i] = dc_i/dx~_i`` and
    ``R[i] = dc_i/dx~_{i+1}``.
    """
    return jacobian_blocks_from_tips(*tip_offsets(q, w, d))


def _block_template(sign: float) -> np.ndarray:
    T = np.zeros((CON_DIM, ERR_DIM))
    T[CON_POS, ERR_P] = sign * np.eye(3)
    T[CON_VEL, ERR_V] = sign * np.eye(3)
    return T


_L_TEMPLATE = _block_template(1.0)


def jacobian_blocks_from_tips(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4 blocks from precomputed :func:`tip_offsets` ``(a, b)``: ``L_i`` is link ``i``'s right-tip
    Jacobian, ``R_i`` minus link ``i+1``'s left-tip Jacobian (:func:`tip_jacobians`)."""
    left, right = _tip_jacobians(a, b)
    R = left[..., 1:, :, :]
    np.negative(R, out=R)
    return right[..., :-1, :, :], R


def _tip_jacobians(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    shape = a.shape[:-1] + (CON_DIM, ERR_DIM)
    Sa = skew(a)
    Sb = skew(b)
    right = np.broadcast_to(_L_TEMPLATE, shape).copy()
    left = right.copy()
    right[..., CON_POS, ERR_TH] = -Sa
    right[..., CON_VEL, ERR_TH] = -Sb
    left[..., CON_POS, ERR_TH] = Sa
    left[..., CON_VEL, ERR_TH] = Sb
    return left, right


def tip_jacobians(q, w, d) -> tuple[np.ndarray, np.ndarray]:
    """``(J_left, J_right)``, each ``(..., n, 6, 9)``: the derivative of every link's left and
    right tip [position; velocity] (:func:`left_tip`, :func:`right_tip`) with respect to its error
    state ``[dp; dv; dtheta]`` (eq. 4's blocks: ``L_i = J_right_i``, ``R_i = -J_left_{i+1}``)."""
    return _tip_jacobians(*tip_offsets(q, w, d))


def dense_jacobian_from_blocks(L: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Dense ``(..., 6m, 9(m+1))`` eq. 4 Jacobian scattered from its neighbour blocks."""
    m = L.shape[-3]
    left = np.eye(m, m + 1)  # constraint i -> link i
    right = np.eye(m, m + 1, k=1)  # constraint i -> link i+1
    C = np.einsum("...ixk,ij->...ixjk", L, left) + np.einsum("...ixk,ij->...ixjk", R, right)
    return C.reshape(L.shape[:-3] + (CON_DIM * m, ERR_DIM * (m + 1)))


def constraint_jacobian(q, w, d) -> np.ndarray:
    """Dense ``(..., 6 (n-1), 9 n)`` Jacobian of eq. 4 (for the reference solver and tests)."""
    return dense_jacobian_from_blocks(*constraint_jacobian_blocks(q, w, d))

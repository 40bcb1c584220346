"""Forward kinematics of the chain, vectorised over any leading batch dimensions (pure numpy).

Links are joined tip to tip (paper eq. 3): the right tip of link ``i`` (``+d_i`` from its centre,
body frame) is the left tip of link ``i+1`` (``-d_{i+1}``). From every link's attitude ``R_i`` and
body rate ``w_i`` the link centres follow, relative to the first link's centre::

    r_0 = 0,   r_{i+1} = r_i + R_i d_i + R_{i+1} d_{i+1}
    r'_0 = 0,  r'_{i+1} = r'_i + R_i S(w_i) d_i + R_{i+1} S(w_{i+1}) d_{i+1}

This is the one implementation of the chain's kinematics for batches: the synthetic chain of the
Table II benchmark (thousands of instants), the CPG's expected physics (hundreds of parameter
sets at once) and the trajectories. :class:`companion.skeleton.dynamics.ChainModel` (pinocchio)
computes the same for one configuration with its inverse dynamics; ``tests/unit/test_chain_model.py``
checks both agree. Evaluated through pinocchio from Python, one 7-link configuration costs about
80 us (the placements are read back one by one) against about 4 us per configuration here for a
batch of 400, hence this vectorised form for batches.
"""

from __future__ import annotations

import numpy as np

from companion.estimation.so3 import cross, quat_to_rotmat

__all__ = ["chain_offsets", "chain_middle", "middle_offset", "middle_of_link", "tension"]


def _tip_vectors(R: np.ndarray, omega_b: np.ndarray | None, d: np.ndarray):
    """World right-tip offsets ``R d`` and their rates ``R S(w) d`` per link, (..., n, 3) each."""
    d = np.broadcast_to(np.asarray(d, dtype=float), R.shape[:-1])
    a = np.einsum("...ij,...j->...i", R, d)
    if omega_b is None:
        return a, None
    return a, np.einsum("...ij,...j->...i", R, cross(omega_b, d))


def chain_offsets(R: np.ndarray, omega_b: np.ndarray | None, d) -> tuple[np.ndarray, np.ndarray | None]:
    """Link centres relative to the first link's centre, and their velocities relative to the
    first link's velocity: ``(r, r')``, each ``(..., n, 3)`` (``r'`` is ``None`` without rates).

    ``R``: (..., n, 3, 3) body-to-world attitudes; ``omega_b``: (..., n, 3) body rates or ``None``;
    ``d``: centre-to-right-tip vector(s), (3,) or (n, 3), body frame.
    """
    R = np.asarray(R, dtype=float)
    a, b = _tip_vectors(R, omega_b, d)

    def accumulate(x):
        zero = np.zeros(x.shape[:-2] + (1, 3))
        return np.concatenate([zero, np.cumsum(x[..., :-1, :] + x[..., 1:, :], axis=-2)], axis=-2)

    return accumulate(a), (None if b is None else accumulate(b))


def middle_offset(r: np.ndarray, R: np.ndarray, d) -> np.ndarray:
    """The chain's middle point given link centres ``r`` (..., n, 3): the middle link's centre
    (odd ``n``), else the middle joint (the left tip of link ``n/2``, 0-based)."""
    n = r.shape[-2]
    mid = n // 2
    if n % 2:
        return r[..., mid, :]
    d_mid = np.broadcast_to(np.asarray(d, dtype=float), r.shape)[..., mid, :]
    return middle_of_link(r[..., mid, :], np.asarray(R, dtype=float)[..., mid, :, :], d_mid, n)


def middle_of_link(r_mid: np.ndarray, R_mid: np.ndarray, d_mid, n_links: int) -> np.ndarray:
    """The middle point of an ``n_links`` chain (see :func:`middle_offset`) from its link ``n_links //
    2`` (0-based) alone: its centre ``r_mid`` (..., 3), attitude ``R_mid`` (..., 3, 3) and
    centre-to-right-tip vector ``d_mid`` (3,)."""
    if n_links % 2:
        return r_mid
    return r_mid - np.einsum("...ij,...j->...i", R_mid, np.asarray(d_mid, dtype=float))


def chain_middle(p_w_m: np.ndarray, q_wxyz: np.ndarray, d) -> np.ndarray:
    """The middle point of a chain of link centres ``p`` and attitudes ``q`` (see :func:`middle_offset`)."""
    return middle_offset(np.asarray(p_w_m, dtype=float), quat_to_rotmat(np.asarray(q_wxyz, dtype=float)), d)


def tension(joint_force_w_n: np.ndarray, R_wl: np.ndarray) -> np.ndarray:
    """Cable tension at every joint [N] (positive: the cable pulls): the force on the child link
    against the chain direction (the mean of the two links' x axes) at the joint.

    ``joint_force_w_n`` (..., n-1, 3) as in :class:`ChainDynamics`; ``R_wl`` (..., n, 3, 3)."""
    axis = R_wl[..., :-1, :, 0] + R_wl[..., 1:, :, 0]
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return -np.sum(joint_force_w_n * axis, axis=-1)

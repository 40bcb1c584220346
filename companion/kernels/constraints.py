"""The chain constraint's pieces as the companion's kernels share them: eq. 3's residual and
eq. 4's Jacobian of a chain's joints, from the links' tips.

The specification is :mod:`companion.estimation.constraints` (``body_tip_vectors``,
``tips_from_body``, ``residual_from_tips``, ``tip_jacobians``, ``dense_jacobian_from_blocks``). A
link's error state is ``[dp; dv; dtheta]`` (``companion.estimation.chain.ERR_*``), a joint's
constraint ``[position; velocity]`` (``CON_*``); the kernels index them by the offsets below.
"""

from __future__ import annotations

import numpy as np

from .jit import jit
from .so3 import rotmat_quadratic_into

__all__ = ["EP", "EV", "ETH", "ED", "CP", "CV", "CD", "body_tip_rates", "link_tip", "tips",
           "residual", "tip_jacobian", "jacobian"]

#: a link's error state: position, velocity, attitude offsets and its size
EP, EV, ETH, ED = 0, 3, 6, 9
#: a joint's constraint: position, velocity offsets and its size
CP, CV, CD = 0, 3, 6


@jit
def body_tip_rates(w, d):
    """``w x d`` per link (n, 3): the body-frame velocity of a tip (``constraints.body_tip_vectors``)."""
    wd = np.empty(w.shape)
    for i in range(w.shape[0]):
        wd[i, 0] = w[i, 1] * d[i, 2] - w[i, 2] * d[i, 1]
        wd[i, 1] = w[i, 2] * d[i, 0] - w[i, 0] * d[i, 2]
        wd[i, 2] = w[i, 0] * d[i, 1] - w[i, 1] * d[i, 0]
    return wd


@jit
def link_tip(q, body_d, body_wd, i, R, a, b):
    """Link ``i``: ``R`` <- R(q[i]); ``a`` (3,) <- ``R d``, ``b`` (3,) <- ``R (w x d)``."""
    rotmat_quadratic_into(q, i, R)
    for half in range(2):
        src, dst = (body_d, a) if half == 0 else (body_wd, b)
        u0, u1, u2 = src[i, 0], src[i, 1], src[i, 2]
        for r in range(3):
            dst[r] = R[r, 0] * u0 + R[r, 1] * u1 + R[r, 2] * u2


@jit
def tips(q, body_d, body_wd, a, b):
    """``a = R(q) d``, ``b = R(q) (w x d)`` per link (``constraints.tips_from_body``)."""
    R = np.empty((3, 3))
    for i in range(q.shape[0]):
        link_tip(q, body_d, body_wd, i, R, a[i], b[i])


@jit
def residual(p, v, a, b, c):
    """Eq. 3: ``c`` (6 (n-1),) of the tips; returns ``||c||``."""
    s = 0.0
    for i in range(p.shape[0] - 1):
        for k in range(3):
            cp = (p[i, k] + a[i, k]) - (p[i + 1, k] - a[i + 1, k])
            cv = (v[i, k] + b[i, k]) - (v[i + 1, k] - b[i + 1, k])
            c[CD * i + CP + k] = cp
            c[CD * i + CV + k] = cv
    for r in range(c.shape[0]):
        s += c[r] * c[r]
    return np.sqrt(s)


@jit
def tip_jacobian(a, b, sgn, scale, row, col, J):
    """``J[row:row + 6, col:col + 9]`` <- ``scale`` times the Jacobian of a link's tip ``[p + sgn a;
    v + sgn b]`` with respect to its error state, ``[I 0 -sgn S(a); 0 I -sgn S(b)]``
    (``constraints.tip_jacobians``: right tip ``sgn = 1``, left tip ``-1``)."""
    for half in range(2):
        blk = row + (CP if half == 0 else CV)
        u = a if half == 0 else b
        f = -sgn * scale
        u0, u1, u2 = f * u[0], f * u[1], f * u[2]
        for k in range(3):
            for c in range(ED):
                J[blk + k, col + c] = 0.0
            J[blk + k, col + (EP if half == 0 else EV) + k] = scale
        # S(u) rows (0, -u2, u1), (u2, 0, -u0), (-u1, u0, 0)
        J[blk + 0, col + ETH + 1] = -u2
        J[blk + 0, col + ETH + 2] = u1
        J[blk + 1, col + ETH + 0] = u2
        J[blk + 1, col + ETH + 2] = -u0
        J[blk + 2, col + ETH + 0] = -u1
        J[blk + 2, col + ETH + 1] = u0


@jit
def jacobian(a, b, C):
    """Eq. 4 dense: joint ``i``'s rows take link ``i``'s right-tip Jacobian ``[I 0 -S(a_i); 0 I
    -S(b_i)]`` at link ``i`` and minus link ``i+1``'s left-tip Jacobian ``[-I 0 -S(a_i+1); 0 -I
    -S(b_i+1)]`` at link ``i+1``."""
    C[:, :] = 0.0
    for i in range(a.shape[0] - 1):
        tip_jacobian(a[i], b[i], 1.0, 1.0, CD * i, ED * i, C)
        tip_jacobian(a[i + 1], b[i + 1], -1.0, -1.0, CD * i, ED * (i + 1), C)

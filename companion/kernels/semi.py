"""A group's boundary terms after its local step (the semi-decentralised SCKF), as a kernel.

The specification is :func:`companion.estimation.semi.local_boundary`'s numpy path
(:func:`~companion.estimation.semi.group_tip_terms`, :func:`~companion.estimation.semi.group_boundary`).
"""

from __future__ import annotations

import numpy as np

from .constraints import CD, CP, CV, ED, body_tip_rates, link_tip, tip_jacobian
from .jit import jit

__all__ = ["group_terms_kernel"]


@jit
def group_terms_kernel(chain, P, ends, has_w, rate_var, out):
    """One group after its local step: ``chain = (p, v, q, w, d)`` its corrected states, body rates
    and centre-to-right-tip vectors (n, 3) ((n, 4) for ``q``), ``P`` (n, 9, 9) its corrected blocks,
    ``ends = (P_ends, W_ends)`` the step's end columns (2, n, 9, 9) and (used when ``has_w``) (2, n,
    9, 3), ``rate_var`` the body-rate noise variance. ``out = (tips, info, T, Y)`` gets ``tips``
    (2, 6) the first link's left tip and the last link's right tip, ``info`` (6, 6) the sum of the
    links' ``P_pv^-1`` (symmetrised), ``T`` (12, 12) the tips' covariance and ``Y`` (n, 12, 9)
    ``Cov(tau, x~_i)`` (``semi.group_tip_terms``)."""
    p, v, q, w, d = chain
    P_ends, W_ends = ends
    tips, info, T, Y = out
    n = p.shape[0]
    R = np.empty((3, 3))
    a, b = np.empty(3), np.empty(3)
    J = np.zeros((2, 2 * CD, ED))
    B = np.zeros((2, 2 * CD, 3))
    wd = body_tip_rates(w, d)
    for e in range(2):
        i = 0 if e == 0 else n - 1
        sgn = -1.0 if e == 0 else 1.0  # left tip p - a, right tip p + a
        link_tip(q, d, wd, i, R, a, b)
        for k in range(3):
            tips[e, CP + k] = p[i, k] + sgn * a[k]
            tips[e, CV + k] = v[i, k] + sgn * b[k]
        tip_jacobian(a, b, sgn, 1.0, e * CD, 0, J[e])
        d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
        for r in range(3):  # the tip velocity's rate column: +-R S(w) d = -+R S(d) w, so -sgn R S(d)
            B[e, e * CD + CV + r, 0] = -sgn * (R[r, 1] * d2 - R[r, 2] * d1)
            B[e, e * CD + CV + r, 1] = -sgn * (-R[r, 0] * d2 + R[r, 2] * d0)
            B[e, e * CD + CV + r, 2] = -sgn * (R[r, 0] * d1 - R[r, 1] * d0)
    for i in range(n):
        Y[i] = J[0] @ np.ascontiguousarray(P_ends[0, i].T) + J[1] @ np.ascontiguousarray(P_ends[1, i].T)
        if has_w:
            Y[i] += B[0] @ np.ascontiguousarray(W_ends[0, i].T) + B[1] @ np.ascontiguousarray(W_ends[1, i].T)
    T[:, :] = Y[0] @ np.ascontiguousarray(J[0].T) + Y[n - 1] @ np.ascontiguousarray(J[1].T)
    if rate_var > 0.0:
        for e in range(2):
            Z = rate_var * (B[0] + B[1] if n == 1 else B[e])
            if has_w:
                Z = Z + J[0] @ W_ends[e, 0] + J[1] @ W_ends[e, n - 1]
            T[:, :] += Z @ np.ascontiguousarray(B[e].T)
    T[:, :] = 0.5 * (T + T.T)
    info[:, :] = 0.0
    for i in range(n):
        info[:, :] += np.linalg.inv(np.ascontiguousarray(P[i, :CD, :CD]))
    info[:, :] = 0.5 * (info + info.T)

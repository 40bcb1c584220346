"""The joint gate's NIS (normalised innovation squared of each joint's eq. 3 residual), as a kernel.

The specification is :func:`companion.estimation.gate.joint_nis` (its numpy code).
"""

from __future__ import annotations

import numpy as np

from .constraints import CD, CP, CV, ED, body_tip_rates, tip_jacobian, tips
from .jit import jit

__all__ = ["joint_nis_kernel"]


@jit
def joint_nis_kernel(chain, P, slack_pos, slack_vel, nis):
    """``nis`` (n-1,) <- per joint ``i`` the NIS ``c_i^T S_i^-1 c_i`` of its eq. 3 residual, ``S_i =
    L_i P_i L_i^T + R_i P_{i+1} R_i^T + G`` with ``G = diag(slack_pos I3, slack_vel I3)`` (the
    squared slacks), symmetrised; ``chain = (p, v, q, w, d)`` (n, 3), (n, 3), (n, 4), (n, 3), (n, 3)
    the EKF states, body rates and centre-to-right-tip vectors, ``P`` (n, 9, 9) the EKF blocks."""
    p, v, q, w, d = chain
    n = p.shape[0]
    a, b = np.empty((n, 3)), np.empty((n, 3))
    tips(q, d, body_tip_rates(w, d), a, b)
    L, Rb = np.empty((CD, ED)), np.empty((CD, ED))
    c = np.empty(CD)
    S = np.empty((CD, CD))
    for i in range(n - 1):
        for k in range(3):
            c[CP + k] = (p[i, k] + a[i, k]) - (p[i + 1, k] - a[i + 1, k])
            c[CV + k] = (v[i, k] + b[i, k]) - (v[i + 1, k] - b[i + 1, k])
        tip_jacobian(a[i], b[i], 1.0, 1.0, 0, 0, L)  # eq. 4's blocks, as constraints.jacobian's
        tip_jacobian(a[i + 1], b[i + 1], -1.0, -1.0, 0, 0, Rb)
        S[:, :] = (L @ P[i]) @ np.ascontiguousarray(L.T) + (Rb @ P[i + 1]) @ np.ascontiguousarray(Rb.T)
        for k in range(3):
            S[CP + k, CP + k] += slack_pos
            S[CV + k, CV + k] += slack_vel
        S[:, :] = 0.5 * (S + S.T)
        if not (np.isfinite(S).all() and np.isfinite(c).all()):
            nis[i] = np.nan  # (numpy's solve passes a NaN through; numba's raises)
            continue
        x = np.linalg.solve(S, c)
        s = 0.0
        for r in range(CD):
            s += c[r] * x[r]
        nis[i] = s

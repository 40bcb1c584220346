"""Alg. 1 (the paper's constraint application) on a chain's dense covariance, as a kernel.

The specification is :func:`companion.estimation.sckf.constraint_apply_dense_batched` (its numpy
code); :func:`constraint_apply_kernel` computes the same iterates with plain loops.
"""

from __future__ import annotations

import numpy as np

from .constraints import CD, CV, ED, EP, ETH, EV, body_tip_rates, jacobian, residual, tips
from .jit import jit
from .so3 import quat_mul, rotmat_quadratic_into, small_angle_quat

__all__ = ["constraint_apply_kernel", "covariance_terms", "constraint_apply_batched_kernel"]


@jit
def _inject(p, v, q, dx):
    """Each link's state corrected by its error ``dx[9 i:9 i + 9]``: ``p += dp``, ``v += dv``,
    ``q <- normalise(normalise((1, dtheta / 2)) (x) q)`` (``sckf._inject``, ``so3.retract`` of a stack)."""
    for i in range(p.shape[0]):
        o = ED * i
        for k in range(3):
            p[i, k] = p[i, k] + dx[o + EP + k]
            v[i, k] = v[i, k] + dx[o + EV + k]
        aw, ax, ay, az = small_angle_quat(0.5 * dx[o + ETH], 0.5 * dx[o + ETH + 1], 0.5 * dx[o + ETH + 2])
        rw, rx, ry, rz = quat_mul(aw, ax, ay, az, q[i, 0], q[i, 1], q[i, 2], q[i, 3])
        nq = np.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
        q[i, 0], q[i, 1], q[i, 2], q[i, 3] = rw / nq, rx / nq, ry / nq, rz / nq


@jit
def _rate_noise_gain(q, d, a, b, C, PE):
    """``K D`` (9n, 3n) of ``sckf._rate_noise_gain`` at the attitudes ``q`` (tips ``a``, ``b``)."""
    n = q.shape[0]
    jacobian(a, b, C)
    D = np.zeros((CD * (n - 1), 3 * n))
    R = np.empty((3, 3))
    for i in range(n - 1):
        for side in range(2):
            link = i + side
            rotmat_quadratic_into(q, link, R)
            d0, d1, d2 = d[link, 0], d[link, 1], d[link, 2]
            for r in range(3):  # B = -R S(d): d(tip velocity offset)/d(w)
                D[CD * i + CV + r, 3 * link + 0] = -(R[r, 1] * d2 - R[r, 2] * d1)
                D[CD * i + CV + r, 3 * link + 1] = -(-R[r, 0] * d2 + R[r, 2] * d0)
                D[CD * i + CV + r, 3 * link + 2] = -(R[r, 0] * d1 - R[r, 1] * d0)
    PCt = PE @ np.ascontiguousarray(C.T)
    return PCt @ np.linalg.solve(C @ PCt, D)


@jit
def constraint_apply_kernel(chain, PE, settings, history):
    """Alg. 1 on one chain. ``chain = (p, v, q, w, d)``: the EKF states ``p``, ``v`` (n, 3), ``q``
    (n, 4), updated in place, the body rates ``w`` and the centre-to-right-tip vectors ``d`` (n,
    3); ``PE`` (9n, 9n) the EKF covariance (block-diagonal for independent links); ``settings = (alpha, eps, max_iter, rate_gain)``: Alg. 1's
    weakening, tolerance and iteration limit, and whether to compute the rate-noise gain.
    ``history`` (max_iter + 1,) takes ``||c||`` before the first iteration and after each. Returns
    ``(Pc, iterations, KD)``: the corrected ``9n x 9n`` covariance (before the rate noise), the
    iterations run, and (``rate_gain`` and at least one iteration, else zeros) the rate-noise gain
    ``K D`` (9n, 3n) at the corrected attitudes."""
    p, v, q, w, d = chain
    alpha, eps, max_iter, rate_gain = settings
    n = p.shape[0]
    N, M = ED * n, CD * (n - 1)
    body_wd = body_tip_rates(w, d)
    Pc = PE.copy()
    a, b = np.empty((n, 3)), np.empty((n, 3))
    c = np.empty(M)
    C = np.empty((M, N))
    eye = np.eye(N)
    tips(q, d, body_wd, a, b)
    norm = residual(p, v, a, b, c)
    history[0] = norm
    j = 0
    while norm > eps and j < max_iter:
        jacobian(a, b, C)
        Ct = np.ascontiguousarray(C.T)
        Pw = (alpha * np.exp(-float(j))) * ((C @ PE) @ Ct)
        PCt = Pc @ Ct
        S = C @ PCt + Pw
        K = np.ascontiguousarray(np.linalg.solve(S, np.ascontiguousarray(PCt.T)).T)  # K = P C^T S^-1
        A = eye - K @ C
        Pn = (A @ Pc) @ np.ascontiguousarray(A.T) + (K @ Pw) @ np.ascontiguousarray(K.T)  # Joseph form
        Pc = 0.5 * (Pn + Pn.T)
        _inject(p, v, q, -(K @ c))
        tips(q, d, body_wd, a, b)
        norm = residual(p, v, a, b, c)
        j += 1
        history[j] = norm
    KD = np.zeros((N, 3 * n))
    if rate_gain and j > 0 and n > 1:
        KD = _rate_noise_gain(q, d, a, b, C, PE)
    return Pc, j, KD


@jit
def covariance_terms(Pc, KD, s2, rate, blocks, ends, W_ends):
    """``sckf._ca_results``' covariance terms of one chain, in place: with ``rate``, ``Pc``
    (9n, 9n) takes the body-rate noise ``s2 sym(KD KD^T)`` (``s2`` the noise's variance); then
    ``blocks`` (n, 9, 9) <- its diagonal blocks, ``ends`` (2, n, 9, 9) <- its columns of the first
    and the last link, and (with ``rate``) ``W_ends`` (2, n, 9, 3) <- ``-s2`` times ``KD``'s
    columns of the first and the last link's rate."""
    N = Pc.shape[0]
    n = N // ED
    if rate:
        Q = KD @ np.ascontiguousarray(KD.T)
        for r in range(N):
            for c in range(N):
                Pc[r, c] = Pc[r, c] + s2 * (0.5 * (Q[r, c] + Q[c, r]))
    last = ED * (n - 1)
    for i in range(n):
        o = ED * i
        for r in range(ED):
            for c in range(ED):
                blocks[i, r, c] = Pc[o + r, o + c]
                ends[0, i, r, c] = Pc[o + r, c]
                ends[1, i, r, c] = Pc[o + r, last + c]
            if rate:
                for c in range(3):
                    W_ends[0, i, r, c] = -s2 * KD[o + r, c]
                    W_ends[1, i, r, c] = -s2 * KD[o + r, 3 * (n - 1) + c]


@jit
def constraint_apply_batched_kernel(chains, PE, settings, history, out):
    """:func:`constraint_apply_kernel` on ``G`` chains of equal length, then their
    :func:`covariance_terms`: ``chains`` its ``chain`` with a leading axis ``G`` on every array, as
    ``PE`` (G, 9n, 9n) and ``history`` (G, max_iter + 1); ``settings = (alpha, eps, max_iter,
    rate_gain, s2)`` (``s2`` the body-rate noise's variance, used with ``rate_gain``); ``out = (Pc,
    iterations, KD, blocks, ends, W_ends)`` gets each chain's corrected covariance (G, 9n, 9n)
    with the rate noise, iterations (G,), rate-noise gain (G, 9n, 3n), diagonal blocks (G, n, 9,
    9), end columns (G, 2, n, 9, 9) and rate end columns (G, 2, n, 9, 3; with ``rate_gain``)."""
    p, v, q, w, d = chains
    alpha, eps, max_iter, rate, s2 = settings
    Pc, iterations, KD, blocks, ends, W_ends = out
    for g in range(p.shape[0]):
        Pc[g], iterations[g], KD[g] = constraint_apply_kernel((p[g], v[g], q[g], w[g], d[g]), PE[g],
                                                              (alpha, eps, max_iter, rate), history[g])
        covariance_terms(Pc[g], KD[g], s2, rate, blocks[g], ends[g], W_ends[g])

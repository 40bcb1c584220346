"""Optional compiled kernels (numba) of the companion's hottest numpy paths, beside their specification.

The numpy functions stay the specification; a kernel here computes the same numbers with plain
loops over scalars, compiled by numba (``njit(cache=True)``), and
``tests/test_fast_paths.py`` checks it against its specification on random inputs (agreement to
1e-12). The kernels:

* :func:`feedforward_kernel`: the whole-chain inverse dynamics of
  :meth:`~companion.skeleton.dynamics.ChainModel.solve` after the joints' passive torques (the
  target source calls it at 50 Hz: 49 us a 3-link call, 148 us in numpy);
* :func:`constraint_apply_kernel`: Alg. 1 (paper) on one chain's dense covariance, with the
  body-rate noise gain, the iterates of :func:`~companion.estimation.sckf.constraint_apply_dense`
  (each SCKF step of a group: 59 us a 3-link step, 337 us in numpy);
  :func:`constraint_apply_batched_kernel` runs it over equal groups in one call;
* :func:`joint_nis_kernel`: the joint gate's NIS (:func:`~companion.estimation.gate.joint_nis`),
  before every step;
* :func:`group_terms_kernel`: a group's boundary and tip covariance terms after its local step
  (:func:`~companion.estimation.semi.local_boundary`).
* :func:`trajectory_kernel`: the targets of a bending chain (poses at five instants and their
  central differences: :meth:`~companion.trajectory.ChainTrajectory.target_arrays`), at 50 Hz.

numba is not an onboard dependency: it comes with the ``sim`` extra. Without it (the Raspberry Pi
install), or with ``SKELETON_JIT=0`` in the environment, :data:`ENABLED` is false, :func:`jit`
returns the function unchanged and every caller runs the numpy specification.

Compilation happens at the first call and is cached on disk (``__pycache__`` beside this file, or
``NUMBA_CACHE_DIR``); :func:`warm_up` compiles (or loads) every kernel here once. The simulator's
firmware kernels (``link_firmware_sim._fast``) use the same :func:`jit`.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

__all__ = ["ENABLED", "jit", "warm_up", "as_kernel_array", "feedforward_kernel", "constraint_apply_kernel",
           "constraint_apply_batched_kernel", "joint_nis_kernel", "group_terms_kernel", "trajectory_kernel"]

log = logging.getLogger(__name__)


from companion.kernels.jit import ENABLED, as_kernel_array, jit  # noqa: E402  (the one switch)


@jit
def feedforward_kernel(p, R, w, wd, acc, tau_j, d, mass, J, gravity, scale, weights, force_ff, torque_ff, F, rotor):
    """:meth:`~companion.skeleton.dynamics.ChainModel.solve` from the joints' passive torques on:
    ``p`` (n, 3) centres, ``R`` (n, 3, 3) attitudes, ``w``/``wd`` (n, 3) body rates and their
    derivatives, ``acc`` (n, 3) centre accelerations, ``tau_j`` (n-1, 3) passive joint torques
    (world), ``d`` (3,) the centre-to-right-tip offset, ``J`` (3,) the principal inertia, ``scale``
    the moment weight (1 / half link length), ``weights`` (n,) each link's rotor-wrench weight in
    the least squares. Writes ``force_ff``/``torque_ff`` (n, 3) (minus the joints' wrench on each
    link), ``F`` (n-1, 3) the joint forces and ``rotor`` (n, 6)."""
    n = p.shape[0]
    own = np.empty((n, 6))
    for i in range(n):
        for k in range(3):
            own[i, k] = mass * (acc[i, k] + (gravity if k == 2 else 0.0))
        Jw0, Jw1, Jw2 = J[0] * w[i, 0], J[1] * w[i, 1], J[2] * w[i, 2]
        b0 = J[0] * wd[i, 0] + (w[i, 1] * Jw2 - w[i, 2] * Jw1)
        b1 = J[1] * wd[i, 1] + (w[i, 2] * Jw0 - w[i, 0] * Jw2)
        b2 = J[2] * wd[i, 2] + (w[i, 0] * Jw1 - w[i, 1] * Jw0)
        for k in range(3):
            own[i, 3 + k] = R[i, k, 0] * b0 + R[i, k, 1] * b1 + R[i, k, 2] * b2
    m = n - 1
    # joint points, and their arms from the parent's (l) and the child's (r) centre
    arm_l = np.empty((max(m, 0), 3))
    arm_r = np.empty((max(m, 0), 3))
    for j in range(m):
        for k in range(3):
            x = p[j, k] + (R[j, k, 0] * d[0] + R[j, k, 1] * d[1] + R[j, k, 2] * d[2])
            arm_l[j, k] = x - p[j, k]
            arm_r[j, k] = x - p[j + 1, k]
    # passive torques: +tau_j on the child j+1, -tau_j on the parent j
    tau_m = np.zeros((n, 3))
    for j in range(m):
        for k in range(3):
            tau_m[j + 1, k] += tau_j[j, k]
            tau_m[j, k] -= tau_j[j, k]
    if m > 0:
        A = np.zeros((6 * n, 3 * m))
        b = np.empty(6 * n)
        for j in range(m):
            for side in range(2):  # the child (+F_j) and the parent (-F_j)
                link = j + 1 if side == 0 else j
                sgn = 1.0 if side == 0 else -1.0
                arm = arm_r if side == 0 else arm_l
                a0, a1, a2 = arm[j, 0], arm[j, 1], arm[j, 2]
                r0, c0 = 6 * link, 3 * j
                for k in range(3):
                    A[r0 + k, c0 + k] = sgn
                # scale * skew(arm) with the sign
                A[r0 + 3, c0 + 1] = sgn * (scale * -a2)
                A[r0 + 3, c0 + 2] = sgn * (scale * a1)
                A[r0 + 4, c0 + 0] = sgn * (scale * a2)
                A[r0 + 4, c0 + 2] = sgn * (scale * -a0)
                A[r0 + 5, c0 + 0] = sgn * (scale * -a1)
                A[r0 + 5, c0 + 1] = sgn * (scale * a0)
        for i in range(n):
            for k in range(3):
                b[6 * i + k] = own[i, k]
                b[6 * i + 3 + k] = scale * (own[i, 3 + k] - tau_m[i, k])
        for i in range(n):
            for r in range(6):
                b[6 * i + r] *= weights[i]
                for c in range(3 * m):
                    A[6 * i + r, c] *= weights[i]
        sol = np.linalg.lstsq(A, b)[0]
        for j in range(m):
            for k in range(3):
                F[j, k] = sol[3 * j + k]
    for i in range(n):
        for k in range(6):
            rotor[i, k] = own[i, k]
    for j in range(m):
        f0, f1, f2 = F[j, 0], F[j, 1], F[j, 2]
        for side in range(2):
            link = j + 1 if side == 0 else j
            sgn = 1.0 if side == 0 else -1.0
            arm = arm_r if side == 0 else arm_l
            a0, a1, a2 = arm[j, 0], arm[j, 1], arm[j, 2]
            force_ff[link, 0] += sgn * f0
            force_ff[link, 1] += sgn * f1
            force_ff[link, 2] += sgn * f2
            torque_ff[link, 0] += sgn * ((a1 * f2 - a2 * f1) + tau_j[j, 0])
            torque_ff[link, 1] += sgn * ((a2 * f0 - a0 * f2) + tau_j[j, 1])
            torque_ff[link, 2] += sgn * ((a0 * f1 - a1 * f0) + tau_j[j, 2])
    for i in range(n):
        for k in range(3):
            rotor[i, k] -= force_ff[i, k]
            rotor[i, 3 + k] -= torque_ff[i, k]
            force_ff[i, k] = -force_ff[i, k]
            torque_ff[i, k] = -torque_ff[i, k]


# Alg. 1 (companion.estimation.sckf.constraint_apply_dense): the error state of a link is
# [dp; dv; dtheta] (companion.estimation.chain.ERR_*), a joint's constraint [position; velocity]
# (CON_*); the kernel indexes them by these offsets
_EP, _EV, _ETH, _ED = 0, 3, 6, 9
_CP, _CV, _CD = 0, 3, 6


@jit
def _ca_rotmat(q, i, R):
    """``R`` (3, 3) <- R(q[i]) (companion.estimation.so3.quat_to_rotmat of a unit quaternion)."""
    w, x, y, z = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
    R[0, 0] = w * w + x * x - y * y - z * z
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = w * w - x * x + y * y - z * z
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = w * w - x * x - y * y + z * z


@jit
def _body_wd(w, d):
    """``w x d`` per link (n, 3): the body-frame velocity of a tip (constraints.body_tip_vectors)."""
    wd = np.empty(w.shape)
    for i in range(w.shape[0]):
        wd[i, 0] = w[i, 1] * d[i, 2] - w[i, 2] * d[i, 1]
        wd[i, 1] = w[i, 2] * d[i, 0] - w[i, 0] * d[i, 2]
        wd[i, 2] = w[i, 0] * d[i, 1] - w[i, 1] * d[i, 0]
    return wd


@jit
def _link_tip(q, body_d, body_wd, i, R, a, b):
    """Link ``i``: ``R`` <- R(q[i]); ``a`` (3,) <- ``R d``, ``b`` (3,) <- ``R (w x d)``."""
    _ca_rotmat(q, i, R)
    for half in range(2):
        src, dst = (body_d, a) if half == 0 else (body_wd, b)
        u0, u1, u2 = src[i, 0], src[i, 1], src[i, 2]
        for r in range(3):
            dst[r] = R[r, 0] * u0 + R[r, 1] * u1 + R[r, 2] * u2


@jit
def _ca_tips(q, body_d, body_wd, a, b):
    """``a = R(q) d``, ``b = R(q) (w x d)`` per link (companion.estimation.constraints.tips_from_body)."""
    R = np.empty((3, 3))
    for i in range(q.shape[0]):
        _link_tip(q, body_d, body_wd, i, R, a[i], b[i])


@jit
def _ca_residual(p, v, a, b, c):
    """Eq. 3: ``c`` (6 (n-1),) of the tips; returns ``||c||``."""
    s = 0.0
    for i in range(p.shape[0] - 1):
        for k in range(3):
            cp = (p[i, k] + a[i, k]) - (p[i + 1, k] - a[i + 1, k])
            cv = (v[i, k] + b[i, k]) - (v[i + 1, k] - b[i + 1, k])
            c[_CD * i + _CP + k] = cp
            c[_CD * i + _CV + k] = cv
    for r in range(c.shape[0]):
        s += c[r] * c[r]
    return np.sqrt(s)


@jit
def _tip_jacobian(a, b, sgn, scale, row, col, J):
    """``J[row:row + 6, col:col + 9]`` <- ``scale`` times the Jacobian of a link's tip ``[p + sgn a;
    v + sgn b]`` with respect to its error state, ``[I 0 -sgn S(a); 0 I -sgn S(b)]``
    (companion.estimation.constraints.tip_jacobians: right tip ``sgn = 1``, left tip ``-1``)."""
    for half in range(2):
        blk = row + (_CP if half == 0 else _CV)
        u = a if half == 0 else b
        f = -sgn * scale
        u0, u1, u2 = f * u[0], f * u[1], f * u[2]
        for k in range(3):
            for c in range(_ED):
                J[blk + k, col + c] = 0.0
            J[blk + k, col + (_EP if half == 0 else _EV) + k] = scale
        # S(u) rows (0, -u2, u1), (u2, 0, -u0), (-u1, u0, 0)
        J[blk + 0, col + _ETH + 1] = -u2
        J[blk + 0, col + _ETH + 2] = u1
        J[blk + 1, col + _ETH + 0] = u2
        J[blk + 1, col + _ETH + 2] = -u0
        J[blk + 2, col + _ETH + 0] = -u1
        J[blk + 2, col + _ETH + 1] = u0


@jit
def _ca_jacobian(a, b, C):
    """Eq. 4 dense: joint ``i``'s rows take link ``i``'s right-tip Jacobian ``[I 0 -S(a_i); 0 I
    -S(b_i)]`` at link ``i`` and minus link ``i+1``'s left-tip Jacobian ``[-I 0 -S(a_i+1); 0 -I
    -S(b_i+1)]`` at link ``i+1``."""
    C[:, :] = 0.0
    for i in range(a.shape[0] - 1):
        _tip_jacobian(a[i], b[i], 1.0, 1.0, _CD * i, _ED * i, C)
        _tip_jacobian(a[i + 1], b[i + 1], -1.0, -1.0, _CD * i, _ED * (i + 1), C)


@jit
def constraint_apply_kernel(p, v, q, w, d, P, alpha, eps, max_iter, rate_gain, history):
    """Alg. 1 on one chain (:func:`~companion.estimation.sckf.constraint_apply_dense`'s iterates):
    ``p``, ``v`` (n, 3), ``q`` (n, 4) the EKF states, updated in place; ``w`` the body rates and
    ``d`` the centre-to-right-tip vectors (n, 3); ``P`` (n, 9, 9) the EKF blocks; ``alpha``,
    ``eps``, ``max_iter`` Alg. 1's weakening, tolerance and iteration limit. ``history``
    (max_iter + 1,) takes ``||c||`` before the first iteration and after each. Returns
    ``(Pc, iterations, KD)``: the corrected ``9n x 9n`` covariance (before the rate noise), the
    iterations run, and (``rate_gain`` and at least one iteration, else zeros) the rate-noise gain
    ``K D`` (9n, 3n) of :func:`~companion.estimation.sckf._rate_noise_gain` at the corrected attitudes."""
    n = p.shape[0]
    N, M = _ED * n, _CD * (n - 1)
    body_wd = _body_wd(w, d)
    PE = np.zeros((N, N))
    for i in range(n):
        PE[_ED * i:_ED * (i + 1), _ED * i:_ED * (i + 1)] = P[i]
    Pc = PE.copy()
    a, b = np.empty((n, 3)), np.empty((n, 3))
    c = np.empty(M)
    C = np.empty((M, N))
    eye = np.eye(N)
    _ca_tips(q, d, body_wd, a, b)
    norm = _ca_residual(p, v, a, b, c)
    history[0] = norm
    j = 0
    while norm > eps and j < max_iter:
        _ca_jacobian(a, b, C)
        Ct = np.ascontiguousarray(C.T)
        Pw = (alpha * np.exp(-float(j))) * ((C @ PE) @ Ct)
        PCt = Pc @ Ct
        S = C @ PCt + Pw
        K = np.ascontiguousarray(np.linalg.solve(S, np.ascontiguousarray(PCt.T)).T)  # K = P C^T S^-1
        A = eye - K @ C
        Pn = (A @ Pc) @ np.ascontiguousarray(A.T) + (K @ Pw) @ np.ascontiguousarray(K.T)  # Joseph form
        Pc = 0.5 * (Pn + Pn.T)
        dx = -(K @ c)
        for i in range(n):
            o = _ED * i
            for k in range(3):
                p[i, k] = p[i, k] + dx[o + _EP + k]
                v[i, k] = v[i, k] + dx[o + _EV + k]
            # q <- normalise(normalise((1, dtheta / 2)) (x) q)  (so3.retract)
            h0, h1, h2 = 0.5 * dx[o + _ETH], 0.5 * dx[o + _ETH + 1], 0.5 * dx[o + _ETH + 2]
            inv = 1.0 / np.sqrt(1.0 + h0 * h0 + h1 * h1 + h2 * h2)
            aw, ax, ay, az = inv, h0 * inv, h1 * inv, h2 * inv
            bw, bx, by, bz = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
            rw = aw * bw - ax * bx - ay * by - az * bz
            rx = aw * bx + ax * bw + ay * bz - az * by
            ry = aw * by - ax * bz + ay * bw + az * bx
            rz = aw * bz + ax * by - ay * bx + az * bw
            nq = np.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
            q[i, 0], q[i, 1], q[i, 2], q[i, 3] = rw / nq, rx / nq, ry / nq, rz / nq
        _ca_tips(q, d, body_wd, a, b)
        norm = _ca_residual(p, v, a, b, c)
        j += 1
        history[j] = norm
    KD = np.zeros((N, 3 * n))
    if rate_gain and j > 0 and n > 1:
        _ca_jacobian(a, b, C)
        D = np.zeros((M, 3 * n))
        R = np.empty((3, 3))
        for i in range(n - 1):
            for side in range(2):
                link = i + side
                _ca_rotmat(q, link, R)
                d0, d1, d2 = d[link, 0], d[link, 1], d[link, 2]
                for r in range(3):  # B = -R S(d): d(tip velocity offset)/d(w)
                    D[_CD * i + _CV + r, 3 * link + 0] = -(R[r, 1] * d2 - R[r, 2] * d1)
                    D[_CD * i + _CV + r, 3 * link + 1] = -(-R[r, 0] * d2 + R[r, 2] * d0)
                    D[_CD * i + _CV + r, 3 * link + 2] = -(R[r, 0] * d1 - R[r, 1] * d0)
        PCt = PE @ np.ascontiguousarray(C.T)
        KD = PCt @ np.linalg.solve(C @ PCt, D)
    return Pc, j, KD


@jit
def constraint_apply_batched_kernel(p, v, q, w, d, P, alpha, eps, max_iter, rate_gain, history, Pc, iterations, KD):
    """:func:`constraint_apply_kernel` on ``G`` chains of equal length (leading axis ``G`` of every
    array; ``history`` (G, max_iter + 1)); writes each chain's ``Pc`` (G, 9n, 9n), ``iterations``
    (G,) and ``KD`` (G, 9n, 3n)."""
    for g in range(p.shape[0]):
        Pc[g], iterations[g], KD[g] = constraint_apply_kernel(p[g], v[g], q[g], w[g], d[g], P[g], alpha, eps, max_iter,
                                                              rate_gain, history[g])


@jit
def joint_nis_kernel(p, v, q, w, d, P, slack_pos, slack_vel, nis):
    """:func:`~companion.estimation.gate.joint_nis`: ``nis`` (n-1,) <- per joint ``i`` the NIS
    ``c_i^T S_i^-1 c_i`` of its eq. 3 residual, ``S_i = L_i P_i L_i^T + R_i P_{i+1} R_i^T + G``
    with ``G = diag(slack_pos I3, slack_vel I3)`` (the squared slacks), symmetrised."""
    n = p.shape[0]
    a, b = np.empty((n, 3)), np.empty((n, 3))
    _ca_tips(q, d, _body_wd(w, d), a, b)
    L, Rb = np.empty((_CD, _ED)), np.empty((_CD, _ED))
    c = np.empty(_CD)
    S = np.empty((_CD, _CD))
    for i in range(n - 1):
        for k in range(3):
            c[_CP + k] = (p[i, k] + a[i, k]) - (p[i + 1, k] - a[i + 1, k])
            c[_CV + k] = (v[i, k] + b[i, k]) - (v[i + 1, k] - b[i + 1, k])
        _tip_jacobian(a[i], b[i], 1.0, 1.0, 0, 0, L)  # eq. 4's blocks, as _ca_jacobian's
        _tip_jacobian(a[i + 1], b[i + 1], -1.0, -1.0, 0, 0, Rb)
        S[:, :] = (L @ P[i]) @ np.ascontiguousarray(L.T) + (Rb @ P[i + 1]) @ np.ascontiguousarray(Rb.T)
        for k in range(3):
            S[_CP + k, _CP + k] += slack_pos
            S[_CV + k, _CV + k] += slack_vel
        S[:, :] = 0.5 * (S + S.T)
        if not (np.isfinite(S).all() and np.isfinite(c).all()):
            nis[i] = np.nan  # (numpy's solve passes a NaN through; numba's raises)
            continue
        x = np.linalg.solve(S, c)
        s = 0.0
        for r in range(_CD):
            s += c[r] * x[r]
        nis[i] = s


@jit
def group_terms_kernel(p, v, q, w, d, P, P_ends, W_ends, has_w, rate_var, tips, info, T, Y):
    """One group after its local step (:func:`~companion.estimation.semi.local_boundary`): ``p``,
    ``v``, ``q`` its corrected states, ``w``, ``d`` (n, 3), ``P`` (n, 9, 9) its corrected blocks,
    ``P_ends`` (2, n, 9, 9) and (``has_w``) ``W_ends`` (2, n, 9, 3) the step's end columns,
    ``rate_var`` the body-rate noise variance. Writes ``tips`` (2, 6) the first link's left tip
    and the last link's right tip, ``info`` (6, 6) the sum of the links' ``P_pv^-1``
    (symmetrised), ``T`` (12, 12) the tips' covariance and ``Y`` (n, 12, 9) ``Cov(tau, x~_i)``
    (:func:`~companion.estimation.semi.group_tip_terms`)."""
    n = p.shape[0]
    R = np.empty((3, 3))
    a, b = np.empty(3), np.empty(3)
    J = np.zeros((2, 2 * _CD, _ED))
    B = np.zeros((2, 2 * _CD, 3))
    wd = _body_wd(w, d)
    for e in range(2):
        i = 0 if e == 0 else n - 1
        sgn = -1.0 if e == 0 else 1.0  # left tip p - a, right tip p + a
        _link_tip(q, d, wd, i, R, a, b)
        for k in range(3):
            tips[e, _CP + k] = p[i, k] + sgn * a[k]
            tips[e, _CV + k] = v[i, k] + sgn * b[k]
        _tip_jacobian(a, b, sgn, 1.0, e * _CD, 0, J[e])
        d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
        for r in range(3):  # the tip velocity's rate column: +-R S(w) d = -+R S(d) w, so -sgn R S(d)
            B[e, e * _CD + _CV + r, 0] = -sgn * (R[r, 1] * d2 - R[r, 2] * d1)
            B[e, e * _CD + _CV + r, 1] = -sgn * (-R[r, 0] * d2 + R[r, 2] * d0)
            B[e, e * _CD + _CV + r, 2] = -sgn * (R[r, 0] * d1 - R[r, 1] * d0)
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
        info[:, :] += np.linalg.inv(np.ascontiguousarray(P[i, :_CD, :_CD]))
    info[:, :] = 0.5 * (info + info.T)


@jit
def trajectory_kernel(theta, share, base_q, d, center, h, p, q, R, v, acc, w, wd):
    """:meth:`~companion.trajectory.ChainTrajectory.target_arrays` (its numpy form is the
    specification): ``theta`` (5,) the bend angles and ``center`` (5, 3) the chain's middle point at
    ``t + k h``, ``k = -2..2``; link ``i`` is pitched by ``theta share[i]`` after ``base_q``, the links
    joined tip to tip (``d`` (3,), centre to right tip, body frame). Writes at ``t`` every link's
    centre ``p`` (n, 3), attitude ``q`` (n, 4) and ``R`` (n, 3, 3), velocity ``v``, acceleration
    ``acc``, body rate ``w = (R^T dR/dt)^v`` and its derivative ``wd``, all by central differences."""
    n = share.shape[0]
    P5 = np.empty((5, n, 3))
    Q5 = np.empty((5, n, 4))
    R5 = np.empty((5, n, 3, 3))
    A = np.empty((n, 3))  # each link's right-tip offset R d at one instant
    bw, bx, by, bz = base_q[0], base_q[1], base_q[2], base_q[3]
    mid = n // 2
    for k in range(5):
        for i in range(n):
            half = 0.5 * (theta[k] * share[i])
            c, s = math.cos(half), math.sin(half)  # the bend: (c, 0, s, 0), after the base attitude
            Q5[k, i, 0], Q5[k, i, 1] = bw * c - by * s, bx * c - bz * s
            Q5[k, i, 2], Q5[k, i, 3] = bw * s + by * c, bx * s + bz * c
            _ca_rotmat(Q5[k], i, R5[k, i])
            for j in range(3):
                A[i, j] = R5[k, i, j, 0] * d[0] + R5[k, i, j, 1] * d[1] + R5[k, i, j, 2] * d[2]
        # centres relative to the first link's (r_i = r_(i-1) + R_(i-1) d + R_i d), the middle on ``center``
        for j in range(3):
            P5[k, 0, j] = 0.0
        for i in range(1, n):
            for j in range(3):
                P5[k, i, j] = P5[k, i - 1, j] + (A[i - 1, j] + A[i, j])
        for j in range(3):
            m = P5[k, mid, j]
            if n % 2 == 0:  # the middle joint: the left tip of link n/2
                m -= A[mid, j]
            shift = center[k, j] - m
            for i in range(n):
                P5[k, i, j] += shift
    rates = np.empty((3, n, 3))
    D = np.empty((3, 3))
    for s in range(3):  # (R^T dR/dt)^v at t - h, t, t + h
        for i in range(n):
            for j in range(3):
                for l in range(3):
                    D[j, l] = (R5[s + 2, i, j, l] - R5[s, i, j, l]) / (2.0 * h)
            Rm = R5[s + 1, i]
            rates[s, i, 0] = Rm[0, 2] * D[0, 1] + Rm[1, 2] * D[1, 1] + Rm[2, 2] * D[2, 1]
            rates[s, i, 1] = Rm[0, 0] * D[0, 2] + Rm[1, 0] * D[1, 2] + Rm[2, 0] * D[2, 2]
            rates[s, i, 2] = Rm[0, 1] * D[0, 0] + Rm[1, 1] * D[1, 0] + Rm[2, 1] * D[2, 0]
    for i in range(n):
        for j in range(3):
            p[i, j] = P5[2, i, j]
            v[i, j] = (P5[3, i, j] - P5[1, i, j]) / (2.0 * h)
            acc[i, j] = (P5[3, i, j] - 2.0 * P5[2, i, j] + P5[1, i, j]) / (h * h)
            w[i, j] = rates[1, i, j]
            wd[i, j] = (rates[2, i, j] - rates[0, i, j]) / (2.0 * h)
            for l in range(3):
                R[i, j, l] = R5[2, i, j, l]
        for j in range(4):
            q[i, j] = Q5[2, i, j]


def warm_up() -> float:
    """Compile (first run) or load from the cache (later runs) every kernel here, with the argument
    types its callers pass; returns the seconds it took (0 without numba)."""
    if not ENABLED:
        return 0.0
    t0 = time.perf_counter()
    n = 2
    z = np.zeros((n, 3))
    R = np.repeat(np.eye(3)[None], n, axis=0)
    feedforward_kernel(z, R, z, z, z, np.zeros((n - 1, 3)), np.array([0.5, 0.0, 0.0]), 1.0, np.ones(3), 9.81, 2.0,
                       np.ones(n), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n - 1, 3)), np.zeros((n, 6)))
    q = np.array([[1.0, 0.0, 0.0, 0.0]] * n)
    P = np.repeat(np.eye(9)[None], n, axis=0)
    p = np.array([[0.0, 0.0, 0.0], [1.1, 0.0, 0.0]])
    G, N = 1, 9 * n
    d = z + np.array([0.5, 0.0, 0.0])
    constraint_apply_batched_kernel(p[None], z[None].copy(), q[None], z[None] + 0.1, d[None], P[None], 1.0, 1e-9, 20, True,
                                    np.empty((G, 21)), np.empty((G, N, N)), np.empty(G, dtype=np.int64),
                                    np.empty((G, N, 3 * n)))
    joint_nis_kernel(p, z, q, z, d, P, 0.01, 0.01, np.empty(n - 1))
    group_terms_kernel(p, z, q, z, d, P, np.zeros((2, n, 9, 9)), np.zeros((2, n, 9, 3)), True, 1e-4, np.empty((2, 6)),
                       np.empty((6, 6)), np.empty((12, 12)), np.empty((n, 12, 9)))
    trajectory_kernel(np.zeros(5), np.array([-1.0, 1.0]), np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.5, 0.0, 0.0]),
                      np.zeros((5, 3)), 1e-3, np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3, 3)), np.empty((n, 3)),
                      np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)))
    return time.perf_counter() - t0

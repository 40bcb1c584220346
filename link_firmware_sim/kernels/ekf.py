"""The EKF's kernels (paper eq. 2): the propagation, the gated Joseph-form updates and the
attitude reference's update with its measurement model.

The specification is :mod:`link_firmware_sim.estimators.ekf` (``ekf_predict``, ``kalman_update``,
``kalman_update_block``, ``ekf_update_attitude``); each kernel computes the same numbers with plain
loops over scalars (``tests/unit/test_fast_paths.py``). The state layout is the specification's: nominal
``[p v q b_a b_g (b)]``, error ``[dp dv dtheta db_a db_g (db)]`` (16 / 15 numbers, 17 / 16 with the
barometer's offset); the parameters are one array (``EKF_*`` of :mod:`.layouts`).
"""

from __future__ import annotations

import math

import numpy as np

from companion.kernels.jit import jit
from companion.kernels.so3 import quat_exp, quat_log, quat_mul, retract, rotmat_unit

from .layouts import EKF_ATT_COV, EKF_BARO_DENSITY, EKF_DENSITIES, EKF_GATE_SIGMA, EKF_GRAVITY_W

__all__ = ["X_Q0", "E_TH0", "ekf_predict_kernel", "update_block_kernel", "update_rows_kernel",
           "attitude_update_kernel"]

#: where the attitude starts in the nominal state and in the error state
X_Q0, E_TH0 = 6, 6


@jit
def _inject(x, dx):
    """``estimators.ekf.inject_error``: ``[p v q ba bg (b)]`` corrected by ``[dp dv dtheta dba dbg (db)]``."""
    xn = x.copy()
    for i in range(6):
        xn[i] += dx[i]
    xn[6], xn[7], xn[8], xn[9] = retract(xn[6], xn[7], xn[8], xn[9], 0.5 * dx[6], 0.5 * dx[7], 0.5 * dx[8])
    for i in range(9, len(dx)):
        xn[i + 1] += dx[i]
    return xn


@jit
def _sym(A):
    n = A.shape[0]
    out = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            out[i, j] = 0.5 * (A[i, j] + A[j, i])
    return out


@jit
def _sparse_matmul(S, B):
    """``S B``, skipping the zero entries of ``S`` (the Jacobians are mostly zeros); each entry
    summed over ``k`` in order from 0."""
    out = np.zeros((S.shape[0], B.shape[1]))
    for i in range(S.shape[0]):
        for k in range(S.shape[1]):
            s = S[i, k]
            if s != 0.0:
                for j in range(B.shape[1]):
                    out[i, j] += s * B[k, j]
    return out


@jit
def _matmul_sparse_t(A, S):
    """``A S^T``, skipping the zero entries of ``S``; each entry summed over ``k`` in order from 0."""
    out = np.zeros((A.shape[0], S.shape[0]))
    for j in range(S.shape[0]):
        for k in range(S.shape[1]):
            s = S[j, k]
            if s != 0.0:
                for i in range(A.shape[0]):
                    out[i, j] += A[i, k] * s
    return out


@jit
def ekf_predict_kernel(x, P, gyro, accel, dt_s, par):
    """``estimators.ekf.ekf_predict`` (nominal propagation, ``F P F^T + Q dt``, symmetrised), any
    state size (16 / 17 with the barometer's offset), ``par`` the EKF's parameters (``EKF_*``).
    ``F`` is sparse: the products skip its zeros."""
    px, py, pz = x[0], x[1], x[2]
    vx, vy, vz = x[3], x[4], x[5]
    qw, qx, qy, qz = x[6], x[7], x[8], x[9]
    bax, bay, baz = x[10], x[11], x[12]
    bgx, bgy, bgz = x[13], x[14], x[15]
    R = rotmat_unit(qw, qx, qy, qz)
    f0, f1, f2 = accel[0] - bax, accel[1] - bay, accel[2] - baz
    fw0 = R[0] * f0 + R[1] * f1 + R[2] * f2
    fw1 = R[3] * f0 + R[4] * f1 + R[5] * f2
    fw2 = R[6] * f0 + R[7] * f1 + R[8] * f2
    a0, a1, a2 = fw0 + par[EKF_GRAVITY_W], fw1 + par[EKF_GRAVITY_W + 1], fw2 + par[EKF_GRAVITY_W + 2]
    h = 0.5 * dt_s * dt_s
    ew, ex, ey, ez = quat_exp((gyro[0] - bgx) * dt_s, (gyro[1] - bgy) * dt_s, (gyro[2] - bgz) * dt_s)
    nw, nx, ny, nz = quat_mul(qw, qx, qy, qz, ew, ex, ey, ez)
    inv = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    xn = x.copy()
    xn[0] = px + vx * dt_s + h * a0
    xn[1] = py + vy * dt_s + h * a1
    xn[2] = pz + vz * dt_s + h * a2
    xn[3] = vx + a0 * dt_s
    xn[4] = vy + a1 * dt_s
    xn[5] = vz + a2 * dt_s
    xn[6] = nw * inv
    xn[7] = nx * inv
    xn[8] = ny * inv
    xn[9] = nz * inv
    # F (estimators.ekf.error_transition): identity, F[p, v] = dt I, F[p, th] = -h S(f_w),
    # F[p, ba] = -h R, F[v, th] = -dt S(f_w), F[v, ba] = -dt R, F[th, bg] = -dt R; identity on the
    # barometer's offset.
    n = P.shape[0]
    F = np.zeros((n, n))
    for i in range(n):
        F[i, i] = 1.0
    ms = (0.0, fw2, -fw1, -fw2, 0.0, fw0, fw1, -fw0, 0.0)  # -S(f_w), row-major
    for i in range(3):
        F[i, 3 + i] = dt_s
        for j in range(3):
            F[i, 6 + j] = h * ms[3 * i + j]
            F[i, 9 + j] = -h * R[3 * i + j]
            F[3 + i, 6 + j] = dt_s * ms[3 * i + j]
            F[3 + i, 9 + j] = -dt_s * R[3 * i + j]
            F[6 + i, 12 + j] = -dt_s * R[3 * i + j]
    Pn = _matmul_sparse_t(_sparse_matmul(F, P), F)  # F P F^T
    for i in range(15):
        Pn[i, i] += par[EKF_DENSITIES + i] * dt_s
    if n > 15:
        Pn[15, 15] += par[EKF_BARO_DENSITY] * dt_s
    return xn, _sym(Pn)


@jit
def _solve_right(PHt, S):
    """``K = PHt S^-1`` for a small symmetric ``S`` (m x m): Gaussian elimination with partial
    pivoting on ``S K^T = PHt^T`` (numpy's ``solve(S, PHt.T).T``)."""
    m = S.shape[0]
    n = PHt.shape[0]
    A = S.copy()
    B = np.empty((m, n))
    for i in range(m):
        for j in range(n):
            B[i, j] = PHt[j, i]
    for c in range(m):
        piv = c
        for r in range(c + 1, m):
            if abs(A[r, c]) > abs(A[piv, c]):
                piv = r
        if piv != c:
            for j in range(m):
                A[c, j], A[piv, j] = A[piv, j], A[c, j]
            for j in range(n):
                B[c, j], B[piv, j] = B[piv, j], B[c, j]
        for r in range(c + 1, m):
            f = A[r, c] / A[c, c]
            if f != 0.0:
                for j in range(c, m):
                    A[r, j] -= f * A[c, j]
                for j in range(n):
                    B[r, j] -= f * B[c, j]
    for c in range(m - 1, -1, -1):
        for j in range(n):
            s = B[c, j]
            for k in range(c + 1, m):
                s -= A[c, k] * B[k, j]
            B[c, j] = s / A[c, c]
    K = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            K[i, j] = B[j, i]
    return K


@jit
def _gate(r, S, gate_sigma):
    """``estimators.ekf.innovation_test``: the largest ``r_k^2 / (gate^2 S_kk)`` (NaN if any is NaN)."""
    g2 = gate_sigma * gate_sigma
    test = -np.inf
    for k in range(len(r)):
        v = r[k] * r[k] / (g2 * S[k, k])
        if v != v:
            return v
        if v > test:
            test = v
    return test


@jit
def _matmul(A, B, transpose_b):
    """``A B`` (``transpose_b``: ``A B^T``), each entry summed over ``k`` in order from 0."""
    n, m = A.shape[0], (B.shape[0] if transpose_b else B.shape[1])
    out = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * (B[j, k] if transpose_b else B[k, j])
            out[i, j] = s
    return out


@jit
def _joseph(x, P, K, H, r, Rm):
    """Accepted update: ``x (+) K r`` and the Joseph form ``(I - K H) P (I - K H)^T + K R K^T`` as
    ``A = P - K (H P)``, ``A - (A H^T) K^T + K R K^T`` (O(n^2 m), as the specification's block
    update), symmetrised."""
    n = P.shape[0]
    m = len(r)
    A = P - _matmul(K, _sparse_matmul(H, P), False)
    AHt = _matmul_sparse_t(A, H)
    KR = _matmul(K, Rm, False)
    Pn = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            s = A[i, j]
            for k in range(m):
                s += KR[i, k] * K[j, k] - AHt[i, k] * K[j, k]
            Pn[i, j] = s
    dx = np.zeros(n)
    for i in range(n):
        s = 0.0
        for k in range(m):
            s += K[i, k] * r[k]
        dx[i] = s
    return _inject(x, dx), _sym(Pn)


@jit
def _gated_joseph(x, P, r, H, PHt, S, Rm, gate_sigma):
    """The update with gain ``K = P H^T S^-1`` (:func:`_joseph`) unless the gate rejects the
    residual ``r`` (:func:`_gate`): ``(x, P, accepted, test_ratio)``."""
    test = _gate(r, S, gate_sigma)
    if not (math.isfinite(test) and test <= 1.0):
        return x, P, False, test
    K = _solve_right(PHt, S)
    xn, Pn = _joseph(x, P, K, H, r, Rm)
    return xn, Pn, True, test


@jit
def update_block_kernel(x, P, r, b0, Rm, gate_sigma):
    """``estimators.ekf.kalman_update_block``: gated update of the error-state block ``b0 : b0 + len(r)`` (GPS
    position / velocity, attitude), Joseph form. Returns ``(x, P, accepted, test_ratio)``."""
    n = P.shape[0]
    m = len(r)
    PHt = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            PHt[i, j] = P[i, b0 + j]
    S = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            S[i, j] = PHt[b0 + i, j] + Rm[i, j]
    H = np.zeros((m, n))
    for k in range(m):
        H[k, b0 + k] = 1.0
    return _gated_joseph(x, P, r, H, PHt, S, Rm, gate_sigma)


@jit
def update_rows_kernel(x, P, r, H, Rm, gate_sigma):
    """``estimators.ekf.kalman_update``: gated update with a dense ``H`` (m x n; barometer, magnetometer heading),
    Joseph form. Returns ``(x, P, accepted, test_ratio)``."""
    PHt = _matmul(P, H, True)
    S = _matmul(H, PHt, False) + Rm
    return _gated_joseph(x, P, r, H, PHt, S, Rm, gate_sigma)


@jit
def attitude_update_kernel(x, P, q_meas, par):
    """``estimators.ekf.ekf_update_attitude``: the measured quaternion normalised
    (``so3.quat_normalize``), the residual ``so3.attitude_error(q_meas, q_est)`` (the world-frame
    rotation vector, angle in [0, pi]) and :func:`update_block_kernel` on the attitude error's
    block, with the covariance and gate of ``par`` (``EKF_ATT_COV``, ``EKF_GATE_SIGMA``). Returns
    ``(x, P, status, test_ratio, r)``: status 1 accepted, 0 rejected by the gate, -1 invalid (a
    non-finite or zero quaternion: the caller raises, as the specification does)."""
    r = np.zeros(3)
    w, a, b, c = q_meas[0], q_meas[1], q_meas[2], q_meas[3]
    norm = math.sqrt(w * w + a * a + b * b + c * c)
    if not (math.isfinite(norm) and norm >= 1e-12):
        return x, P, -1, math.nan, r
    d = quat_mul(w / norm, a / norm, b / norm, c / norm, x[X_Q0], -x[X_Q0 + 1], -x[X_Q0 + 2], -x[X_Q0 + 3])
    r[0], r[1], r[2] = quat_log(d[0], d[1], d[2], d[3])  # q_meas (x) conj(q_est), as a rotation vector
    Rm = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            Rm[i, j] = par[EKF_ATT_COV + 3 * i + j]
    xn, Pn, accepted, test = update_block_kernel(x, P, r, E_TH0, Rm, par[EKF_GATE_SIGMA])
    return xn, Pn, 1 if accepted else 0, test, r

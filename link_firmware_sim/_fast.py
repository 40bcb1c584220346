"""Compiled kernels of the firmware's per-tick path (numba), beside the numpy specification.

The readable functions stay the specification: :func:`~link_firmware_sim.ekf.ekf_predict` and the
EKF's measurement updates (paper eq. 2; Joseph form, symmetric ``P``), the impedance controller
(paper eq. 1, :func:`~link_firmware_sim.control.impedance_control`) and the allocation with
selective mapping (thesis Prop. 1, (2.12), (2.15), (2.17); :class:`~link_firmware_sim.allocation.
Allocator`). The kernels here compute the same numbers with plain loops over scalars, compiled by
numba (``njit(cache=True)``): at 500 Hz per link the interpreter's cost of a few hundred scalar
operations, not the arithmetic, was the SITL's limit. ``tests/test_fast_paths.py`` checks every
kernel against its specification on random inputs (agreement to 1e-12).

Fused: :func:`tick_kernel` is one whole tick of the fast loop (propagation, control estimate, eq. 1,
allocation) in one call, which :meth:`~link_firmware_sim.firmware.LinkFirmware.on_imu` takes in its
common case (armed, eq. 1, a fresh target): a call's dispatch and the Python between the steps cost
more than their arithmetic. :func:`attitude_update_kernel` is the 50 Hz attitude reference's whole
update (measurement model too). ``tests/test_fast_paths.py`` checks both against the step-by-step
numpy path. :func:`hil_tick_kernel` wraps the fused tick between the same-host simulator link's
bytes: the HIL_SENSOR record in, the HIL_ACTUATOR_CONTROLS record out (the vehicle's common tick,
no message object on the way); its test checks the answer byte for byte against the decoders'.
:func:`hil_loop_kernel` runs the vehicle's lockstep over its quiet ticks, the waits and the socket
calls included (the C library's ``poll``, ``recv`` and ``send``, linked by symbol, so numba caches
it like the others), and hands back to Python at the first tick whose bookkeeping changes anything;
``tests/test_simlink.py`` flies it against the record tick, bit for bit. Over PX4's TCP link the same
loop reads and writes the ticks' MAVLink 2 frames (:func:`frames_to_records`, :func:`record_to_frame`:
whole, unsigned frames from the simulator, numbered without a gap, checksums checked; anything else
goes to pymavlink's parser), flown against the decoding path bit for bit, counters included.

Dispatch: :class:`~link_firmware_sim.ekf.LinkEkf`, :class:`~link_firmware_sim.allocation.Allocator`
and :class:`~link_firmware_sim.firmware.LinkFirmware` use the kernels when :data:`ENABLED`, else the
numpy functions. numba is in the ``sim`` extra only: an onboard install without it runs the numpy
path (one log line says so). ``SKELETON_JIT=0`` in the environment turns the kernels off (the
reference path, e.g. to compare).

Compilation happens at the first call of each kernel and is cached on disk (numba's cache:
``__pycache__`` beside this file, or ``NUMBA_CACHE_DIR`` when set, e.g. for a read-only install),
so later processes load the machine code instead of compiling. :func:`warm_up` compiles (or loads)
every kernel once; the fleet launcher calls it before it starts the vehicle processes, so that n
vehicles load one cache instead of compiling n times.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

# the one switch and decorator of every compiled kernel (numba optional; ``SKELETON_JIT=0`` turns it off)
from companion.kernels.jit import ENABLED, jit

__all__ = [
    "ENABLED",
    "jit",
    "warm_up",
    "ekf_predict_kernel",
    "update_block_kernel",
    "update_rows_kernel",
    "attitude_update_kernel",
    "impedance_kernel",
    "allocate_kernel",
    "ALLOC_META",
    "tick_kernel",
    "attitude_tick_kernel",
    "TICK_OUT",
    "hil_tick_kernel",
    "hil_loop_kernel",
    "frames_to_records",
    "record_to_frame",
    "crc_mcrf4xx",
    "MAV_HIL_SENSOR",
    "MAV_HIL_AHRS",
    "MAV_HIL_ACTUATOR",
    "FRAMING",
    "FRAMING_SIZE",
    "FRAMES_TO_VEHICLE",
    "FRAMES_TO_SIMULATOR",
    "FRAME_BYTES",
    "LOOP_INFO",
    "LOOP_IDLE",
    "LOOP_PACKET",
    "LOOP_TICKED",
    "HIL_SENSOR_RECORD",
    "HIL_ACTUATOR_RECORD",
    "HIL_AHRS_RECORD",
    "sensor_record_at",
    "AHRS_NORM_TOLERANCE",
    "AHRS_OUT",
    "HIL_BARO_MAG_BITS",
    "packed",
    "pack_correction",
    "pack_target",
    "pack_gains",
    "pack_inertia",
]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# EKF (link_firmware_sim.ekf)
# --------------------------------------------------------------------------------------------


@jit
def _retract_into(xn, q0, hx, hy, hz):
    """so3.retract with ``h = dtheta / 2``: ``xn[q0:q0+4] <- normalise((1, h) (x) q)``."""
    w, x, y, z = xn[q0], xn[q0 + 1], xn[q0 + 2], xn[q0 + 3]
    rw = w - hx * x - hy * y - hz * z
    rx = x + hx * w + hy * z - hz * y
    ry = y - hx * z + hy * w + hz * x
    rz = z + hx * y - hy * x + hz * w
    inv = 1.0 / math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    xn[q0] = rw * inv
    xn[q0 + 1] = rx * inv
    xn[q0 + 2] = ry * inv
    xn[q0 + 3] = rz * inv


@jit
def _inject(x, dx):
    """ekf.inject_error: ``[p v q ba bg (b)]`` corrected by ``[dp dv dtheta dba dbg (db)]``."""
    xn = x.copy()
    for i in range(6):
        xn[i] += dx[i]
    _retract_into(xn, 6, 0.5 * dx[6], 0.5 * dx[7], 0.5 * dx[8])
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
def ekf_predict_kernel(x, P, gyro, accel, dt_s, densities, baro_density, gravity_w):
    """ekf.ekf_predict (nominal propagation, ``F P F^T + Q dt``, symmetrised), any state size
    (16 / 17 with the barometer's offset). ``F`` is sparse: the products skip its zeros."""
    px, py, pz = x[0], x[1], x[2]
    vx, vy, vz = x[3], x[4], x[5]
    qw, qx, qy, qz = x[6], x[7], x[8], x[9]
    bax, bay, baz = x[10], x[11], x[12]
    bgx, bgy, bgz = x[13], x[14], x[15]
    R0 = 1.0 - 2.0 * (qy * qy + qz * qz)
    R1 = 2.0 * (qx * qy - qw * qz)
    R2 = 2.0 * (qx * qz + qw * qy)
    R3 = 2.0 * (qx * qy + qw * qz)
    R4 = 1.0 - 2.0 * (qx * qx + qz * qz)
    R5 = 2.0 * (qy * qz - qw * qx)
    R6 = 2.0 * (qx * qz - qw * qy)
    R7 = 2.0 * (qy * qz + qw * qx)
    R8 = 1.0 - 2.0 * (qx * qx + qy * qy)
    f0, f1, f2 = accel[0] - bax, accel[1] - bay, accel[2] - baz
    fw0 = R0 * f0 + R1 * f1 + R2 * f2
    fw1 = R3 * f0 + R4 * f1 + R5 * f2
    fw2 = R6 * f0 + R7 * f1 + R8 * f2
    a0, a1, a2 = fw0 + gravity_w[0], fw1 + gravity_w[1], fw2 + gravity_w[2]
    h = 0.5 * dt_s * dt_s
    rx, ry, rz = (gyro[0] - bgx) * dt_s, (gyro[1] - bgy) * dt_s, (gyro[2] - bgz) * dt_s
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-8:
        ew, k = 1.0, 0.5
    else:
        ew, k = math.cos(0.5 * angle), math.sin(0.5 * angle) / angle
    ex, ey, ez = k * rx, k * ry, k * rz
    nw = qw * ew - qx * ex - qy * ey - qz * ez
    nx = qw * ex + qx * ew + qy * ez - qz * ey
    ny = qw * ey - qx * ez + qy * ew + qz * ex
    nz = qw * ez + qx * ey - qy * ex + qz * ew
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
    # F (ekf._transition): identity, F[p, v] = dt I, F[p, th] = -h S(f_w), F[p, ba] = -h R,
    # F[v, th] = -dt S(f_w), F[v, ba] = -dt R, F[th, bg] = -dt R; identity on the baro offset.
    n = P.shape[0]
    F = np.zeros((n, n))
    for i in range(n):
        F[i, i] = 1.0
    ms = (0.0, fw2, -fw1, -fw2, 0.0, fw0, fw1, -fw0, 0.0)  # -S(f_w), row-major
    R = (R0, R1, R2, R3, R4, R5, R6, R7, R8)
    for i in range(3):
        F[i, 3 + i] = dt_s
        for j in range(3):
            F[i, 6 + j] = h * ms[3 * i + j]
            F[i, 9 + j] = -h * R[3 * i + j]
            F[3 + i, 6 + j] = dt_s * ms[3 * i + j]
            F[3 + i, 9 + j] = -dt_s * R[3 * i + j]
            F[6 + i, 12 + j] = -dt_s * R[3 * i + j]
    A = np.zeros((n, n))  # F P
    for i in range(n):
        for k in range(n):
            f = F[i, k]
            if f != 0.0:
                for j in range(n):
                    A[i, j] += f * P[k, j]
    Pn = np.zeros((n, n))  # A F^T
    for j in range(n):
        for k in range(n):
            f = F[j, k]
            if f != 0.0:
                for i in range(n):
                    Pn[i, j] += A[i, k] * f
    for i in range(15):
        Pn[i, i] += densities[i] * dt_s
    if n > 15:
        Pn[15, 15] += baro_density * dt_s
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
    """ekf._gate: the largest ``r_k^2 / (gate^2 S_kk)`` (NaN if any is NaN)."""
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
def _joseph(x, P, K, H, r, Rm):
    """Accepted update: ``x (+) K r`` and the Joseph form ``(I - K H) P (I - K H)^T + K R K^T``
    as ``A = P - K (H P)``, ``A - (A H^T) K^T + K R K^T`` (O(n^2 m), as ekf._update_block), symmetrised."""
    n = P.shape[0]
    m = len(r)
    HP = np.zeros((m, n))
    for k in range(m):
        for c in range(n):
            h = H[k, c]
            if h != 0.0:
                for j in range(n):
                    HP[k, j] += h * P[c, j]
    A = P.copy()
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(m):
                s += K[i, k] * HP[k, j]
            A[i, j] -= s
    AHt = np.zeros((n, m))
    for k in range(m):
        for c in range(n):
            h = H[k, c]
            if h != 0.0:
                for i in range(n):
                    AHt[i, k] += A[i, c] * h
    KR = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for k in range(m):
                s += K[i, k] * Rm[k, j]
            KR[i, j] = s
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
def update_block_kernel(x, P, r, b0, Rm, gate_sigma):
    """ekf._update_block: gated update of the error-state block ``b0 : b0 + len(r)`` (GPS
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
    test = _gate(r, S, gate_sigma)
    if not (math.isfinite(test) and test <= 1.0):
        return x, P, False, test
    K = _solve_right(PHt, S)
    H = np.zeros((m, n))
    for k in range(m):
        H[k, b0 + k] = 1.0
    xn, Pn = _joseph(x, P, K, H, r, Rm)
    return xn, Pn, True, test


@jit
def update_rows_kernel(x, P, r, H, Rm, gate_sigma):
    """ekf._update: gated update with a dense ``H`` (m x n; barometer, magnetometer heading),
    Joseph form. Returns ``(x, P, accepted, test_ratio)``."""
    n = P.shape[0]
    m = len(r)
    PHt = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for k in range(n):
                s += P[i, k] * H[j, k]
            PHt[i, j] = s
    S = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            s = 0.0
            for k in range(n):
                s += H[i, k] * PHt[k, j]
            S[i, j] = s + Rm[i, j]
    test = _gate(r, S, gate_sigma)
    if not (math.isfinite(test) and test <= 1.0):
        return x, P, False, test
    K = _solve_right(PHt, S)
    xn, Pn = _joseph(x, P, K, H, r, Rm)
    return xn, Pn, True, test


@jit
def _quat_mul_into(a, b, out):
    """``so3.quat_mul``'s one-product case into ``out``: the same operations in the same order."""
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    out[0] = aw * bw - ax * bx - ay * by - az * bz
    out[1] = aw * bx + ax * bw + ay * bz - az * by
    out[2] = aw * by - ax * bz + ay * bw + az * bx
    out[3] = aw * bz + ax * by - ay * bx + az * bw


@jit
def attitude_update_kernel(x, P, q_meas, Rm, gate_sigma, q0, b0):
    """ekf.ekf_update_attitude: the measured quaternion normalised (``so3.quat_normalize``), the
    residual ``so3.attitude_error(q_meas, q_est)`` (the world-frame rotation vector, angle in
    [0, pi]; ``q_est = x[q0:q0+4]``) and :func:`update_block_kernel` on the error block ``b0:b0+3``
    (ekf.X_Q, ekf.E_TH). Returns ``(x, P, status,
    test_ratio, r)``: status 1 accepted, 0 rejected by the gate, -1 invalid (a non-finite or
    zero quaternion: the caller raises, as the specification does)."""
    r = np.zeros(3)
    w, a, b, c = q_meas[0], q_meas[1], q_meas[2], q_meas[3]
    norm = math.sqrt(w * w + a * a + b * b + c * c)
    if not (math.isfinite(norm) and norm >= 1e-12):
        return x, P, -1, math.nan, r
    qn = np.empty(4)
    qn[0], qn[1], qn[2], qn[3] = w / norm, a / norm, b / norm, c / norm
    conj = np.empty(4)  # conj(q_est)
    conj[0], conj[1], conj[2], conj[3] = x[q0], -x[q0 + 1], -x[q0 + 2], -x[q0 + 3]
    d = np.empty(4)
    _quat_mul_into(qn, conj, d)  # q_meas (x) conj(q_est)
    dw, dx, dy, dz = d[0], d[1], d[2], d[3]
    if dw < 0.0:
        dw, dx, dy, dz = -dw, -dx, -dy, -dz
    sn = math.sqrt(dx * dx + dy * dy + dz * dz)
    k = 2.0 * math.atan2(sn, dw) / sn if sn > 1e-12 else 2.0 / max(dw, 1e-300)
    r[0], r[1], r[2] = k * dx, k * dy, k * dz
    xn, Pn, accepted, test = update_block_kernel(x, P, r, b0, Rm, gate_sigma)
    return xn, Pn, 1 if accepted else 0, test, r


# --------------------------------------------------------------------------------------------
# Impedance control (link_firmware_sim.control, paper eq. 1)
# --------------------------------------------------------------------------------------------

#: packed target (:func:`pack_target`): p_d, v_d, a_d, w_d, wdot_d, R_d (row-major), f_ff, tau_ff
TARGET_SIZE = 30


def packed(obj, pack) -> np.ndarray:
    """``pack(obj)``, computed once per (frozen) object and kept in its ``__dict__`` like a
    ``functools.cached_property`` (targets change at 50 Hz, the controller runs at 500 Hz)."""
    d = obj.__dict__
    key = "_fast_" + pack.__name__
    a = d.get(key)
    if a is None:
        a = d[key] = pack(obj)
        a.setflags(write=False)
    return a


def pack_target(target) -> np.ndarray:
    """A :class:`~companion.messages.PoseTarget` as the (30,) array :func:`impedance_kernel` reads."""
    return np.concatenate((target.p_w_m, target.v_w_m_s, target.a_w_m_s2, target.omega_d_rad_s,
                           target.omega_dot_d_rad_s2, target.R_tuple, target.force_ff_w_n,
                           target.torque_ff_b_nm)).astype(float)


def pack_gains(gains) -> np.ndarray:
    """:class:`~link_firmware_sim.control.ImpedanceGains` as (16,): kp, kd, ki (3 each), kR, kw,
    kI, gamma_I, position and attitude integral limits, the position error's limit."""
    return np.array((*gains.kp_n_m, *gains.kd_ns_m, *gains.ki_n_ms, gains.kR_nm, gains.kw_nms, gains.kI_nm_s,
                     gains.gamma_I, gains.pos_integral_limit_ms, gains.att_integral_limit_rad,
                     gains.pos_error_limit_m), dtype=float)


def pack_inertia(inertia) -> np.ndarray:
    """:class:`~companion.skeleton.body.LinkInertia` as (4,): mass, principal inertia."""
    return np.array((inertia.mass_kg, *inertia.inertia_kgm2), dtype=float)


@jit
def _clamp(c, limit):
    return min(max(c, -limit), limit)


@jit
def impedance_kernel(p, v, q, w, tgt, gains, inertia, pos, att, dt_s, gravity, out):
    """control.impedance_control: ``out[:6] = U = [u; tau]``, ``out[6:9]`` the position integral,
    ``out[9:12]`` the attitude integral (same operations in the same order)."""
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    R = (
        1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy),
        2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx),
        2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy),
    )
    m = inertia[0]
    Jx, Jy, Jz = inertia[1], inertia[2], inertia[3]
    pos_lim, att_lim = gains[13], gains[14]
    f_w = np.empty(3)
    e = np.empty(3)
    for i in range(3):
        e[i] = p[i] - tgt[i]
    n = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    if n > gains[15]:  # control.limit_length
        k = gains[15] / n
        for i in range(3):
            e[i] = e[i] * k
    for i in range(3):
        e_p = e[i]
        pi = _clamp(pos[i] + e_p * dt_s, pos_lim)
        out[6 + i] = pi
        ag = tgt[6 + i] + (gravity if i == 2 else 0.0)
        f_w[i] = m * ag - gains[3 + i] * (v[i] - tgt[3 + i]) - gains[i] * e_p - gains[6 + i] * pi + tgt[24 + i]
    for i in range(3):
        out[i] = R[i] * f_w[0] + R[3 + i] * f_w[1] + R[6 + i] * f_w[2]
    Rd = tgt[15:24]
    RtRd = np.empty(9)
    for i in range(3):
        for j in range(3):
            RtRd[3 * i + j] = R[i] * Rd[j] + R[3 + i] * Rd[3 + j] + R[6 + i] * Rd[6 + j]
    e_R = (RtRd[5] - RtRd[7], RtRd[6] - RtRd[2], RtRd[1] - RtRd[3])
    wd = tgt[9:12]
    wdd = tgt[12:15]
    tff = tgt[27:30]
    w_db = np.empty(3)
    rd = np.empty(3)
    tau_ff = np.empty(3)
    for i in range(3):
        w_db[i] = RtRd[3 * i] * wd[0] + RtRd[3 * i + 1] * wd[1] + RtRd[3 * i + 2] * wd[2]
        rd[i] = RtRd[3 * i] * wdd[0] + RtRd[3 * i + 1] * wdd[1] + RtRd[3 * i + 2] * wdd[2]
        tau_ff[i] = RtRd[3 * i] * tff[0] + RtRd[3 * i + 1] * tff[1] + RtRd[3 * i + 2] * tff[2]
    e_w = (w[0] - w_db[0], w[1] - w_db[1], w[2] - w_db[2])
    gI = gains[12]
    for i in range(3):
        out[9 + i] = _clamp(att[i] + (e_w[i] + gI * e_R[i]) * dt_s, att_lim)
    Jw = (Jx * w[0], Jy * w[1], Jz * w[2])
    gyro = (w[1] * Jw[2] - w[2] * Jw[1], w[2] * Jw[0] - w[0] * Jw[2], w[0] * Jw[1] - w[1] * Jw[0])
    wx = (w[1] * w_db[2] - w[2] * w_db[1], w[2] * w_db[0] - w[0] * w_db[2], w[0] * w_db[1] - w[1] * w_db[0])
    ff = (Jx * (wx[0] - rd[0]), Jy * (wx[1] - rd[1]), Jz * (wx[2] - rd[2]))
    kR, kw, kI = gains[9], gains[10], gains[11]
    for i in range(3):
        out[3 + i] = gyro[i] - kR * e_R[i] - kw * e_w[i] - kI * out[9 + i] - ff[i] + tau_ff[i]
    return out


# --------------------------------------------------------------------------------------------
# Allocation with selective mapping (link_firmware_sim.allocation, thesis Prop. 1, (2.15), (2.17))
# --------------------------------------------------------------------------------------------


@jit
def _below_margin(b, x, thr):
    c = 0
    for k in range(4):
        if abs(b[k] + x) < thr:
            c += 1
    return c


_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


@jit
def _modulate_side(b, xi_pre, eps1, tmax, tol):
    """allocation._modulate_side: the exact solution of (2.15) for one side, within ``tmax``."""
    thr = eps1 - tol
    bmin = min(min(b[0], b[1]), min(b[2], b[3]))
    bmax = max(max(b[0], b[1]), max(b[2], b[3]))
    lo = -tmax - bmin
    hi = tmax - bmax
    if lo > hi:
        return 0.0
    if lo <= xi_pre <= hi and _below_margin(b, xi_pre, thr) <= 1:
        return xi_pre
    best = np.inf
    best_d = np.inf
    for k in range(10):
        if k < 8:
            x = -b[k // 2] + (eps1 if k % 2 else -eps1)
        else:
            x = lo if k == 8 else hi
            if not math.isfinite(x):
                continue
        d = abs(x - xi_pre)
        if lo <= x <= hi and (d < best_d or (d == best_d and x < best)) and _below_margin(b, x, thr) <= 1:
            best = x
            best_d = d
    if best_d == np.inf:
        return _least_within_margin(b, xi_pre, lo, hi)
    return best


@jit
def _second_smallest_magnitude(b, x):
    m1 = np.inf
    m2 = np.inf
    for k in range(4):
        v = abs(b[k] + x)
        if v < m1:
            m2 = m1
            m1 = v
        elif v < m2:
            m2 = v
    return m2


@jit
def _least_within_margin(b, xi_pre, lo, hi):
    """allocation._least_within_margin (the same candidates in the same order)."""
    best = lo
    best_f = -np.inf
    best_d = np.inf
    for k in range(12):
        if k == 0:
            x = lo
        elif k == 1:
            x = hi
        elif k < 6:
            x = -b[k - 2]
        else:
            i, j = _PAIRS[k - 6]
            x = -(b[i] + b[j]) * 0.5
        if not (lo <= x <= hi):
            continue
        f = _second_smallest_magnitude(b, x)
        d = abs(x - xi_pre)
        if f > best_f or (f == best_f and (d < best_d or (d == best_d and x < best))):
            best = x
            best_f = f
            best_d = d
    return best


#: the size of :func:`allocate_kernel`'s ``meta``
ALLOC_META = 12


@jit
def _side_range(lam, nu, o):
    """``(min, max)`` of side ``o``'s (0 or 4) ``diag(nu) lambda``."""
    mx = -np.inf
    mn = np.inf
    for i in range(4):
        val = nu[i] * lam[o + i]
        mx = max(mx, val)
        mn = min(mn, val)
    return mn, mx


@jit
def _pinv_times(B_pinv, U, lo):
    """``lo = B^+ U``."""
    for i in range(8):
        s = 0.0
        for k in range(6):
            s += B_pinv[i, k] * U[k]
        lo[i] = s


@jit
def allocate_kernel(U_in, keep, B_pinv, reduced_by_side, nu, xi_pre, eps0, eps1, tmax, selective, scale_to_limit, tol,
                    out, meta):
    """Allocator.allocate: ``out`` (5, 8) rows command, lambda_o, lambda_alpha, lambda_beta,
    lambda_gamma; ``meta`` (:data:`ALLOC_META`) = (e_r, e_l, near_r, near_l, saturated, scale,
    the wrench allocated (6)); ``xi_pre`` (2,) is updated; ``keep``: the wrench
    allocation.scaled_to_limit keeps whole (zeros: none)."""
    U = np.empty(6)
    for k in range(6):
        U[k] = U_in[k]
    lo = out[1]
    _pinv_times(B_pinv, U, lo)
    scale = 1.0
    xi_limit = np.inf
    if scale_to_limit:  # allocation.scaled_to_limit
        xi_limit = tmax
        mn_r, mx_r = _side_range(lo, nu, 0)
        mn_l, mx_l = _side_range(lo, nu, 4)
        if max(mx_r - mn_r, mx_l - mn_l) > 2.0 * tmax:
            K = np.empty(6)
            for k in range(6):
                K[k] = keep[k]
            a = np.empty(8)
            _pinv_times(B_pinv, K, a)
            mn_r, mx_r = _side_range(a, nu, 0)
            mn_l, mx_l = _side_range(a, nu, 4)
            for i in range(8):
                a[i] = a[i] * nu[i % 4]
            if not max(mx_r - mn_r, mx_l - mn_l) <= 2.0 * tmax:  # beyond the rotors too: none
                for k in range(6):
                    K[k] = 0.0
                for i in range(8):
                    a[i] = 0.0
            D = np.empty(6)
            for k in range(6):
                D[k] = U_in[k] - K[k]
            d = np.empty(8)
            _pinv_times(B_pinv, D, d)
            for i in range(8):
                d[i] = d[i] * nu[i % 4]
            for o in range(0, 8, 4):
                for i in range(4):
                    for j in range(4):
                        dd = d[o + i] - d[o + j]
                        if dd > 0.0:
                            scale = min(scale, (2.0 * tmax - (a[o + i] - a[o + j])) / dd)
            scale = max(scale, 0.0)
            for k in range(6):
                U[k] = K[k] + scale * D[k]
            _pinv_times(B_pinv, U, lo)
    meta[5] = scale
    for k in range(6):
        meta[6 + k] = U[k]
    b = np.empty(8)
    faded_to_limit = False
    for side in range(2):
        o = 4 * side
        mn, mx = _side_range(lo, nu, o)
        xi1 = -0.5 * (mx + mn)  # (2.12)
        for i in range(4):
            b[o + i] = nu[i] * lo[o + i] + xi1
            out[2, o + i] = nu[i] * b[o + i]
    if not selective:
        for i in range(8):
            out[3, i] = out[2, i]
            out[4, i] = out[2, i]
        meta[0] = 1.0
        meta[1] = 1.0
        meta[2] = -1.0
        meta[3] = -1.0
    else:
        for side in range(2):
            o = 4 * side
            xi2 = _modulate_side(b[o:o + 4], xi_pre[side], eps1, xi_limit, tol)  # (2.15)
            xi_pre[side] = xi2
            mags = np.empty(4)
            for i in range(4):
                bb = b[o + i] + xi2
                out[3, o + i] = nu[i] * bb
                mags[i] = abs(bb)
            j = 0
            for i in range(1, 4):
                if mags[i] < mags[j]:
                    j = i
            mmin = mags[j]
            if mmin >= eps1 - tol:  # (2.17), clear
                e = 1.0
                for i in range(4):
                    out[4, o + i] = out[3, o + i]
                meta[2 + side] = -1.0
            else:
                e = (mmin - eps0) / (eps1 - eps0)
                if not e > 0.0:
                    e = 0.0
                red = np.empty(4)
                over = False
                for i in range(4):
                    s = 0.0
                    for k in range(6):
                        s += reduced_by_side[side, j, i, k] * U[k]
                    red[i] = s
                    out[4, o + i] = s + e * (out[3, o + i] - s)
                    if abs(out[4, o + i]) > tmax:
                        over = True
                if scale_to_limit and over:  # allocation._fade_within_limit
                    for i in range(4):
                        d = out[3, o + i] - red[i]
                        if d > 0.0:
                            e = max(e, (-tmax - red[i]) / d)
                        elif d < 0.0:
                            e = max(e, (tmax - red[i]) / d)
                    e = min(e, 1.0)
                    for i in range(4):
                        out[4, o + i] = red[i] + e * (out[3, o + i] - red[i])
                    faded_to_limit = True
                meta[2 + side] = j + o
            meta[side] = e
    sat = 0.0 if scale == 1.0 and not faded_to_limit else 1.0
    for i in range(8):
        g = out[4, i]
        out[0, i] = min(max(g, -tmax), tmax)
        if abs(g) > tmax:
            sat = 1.0
    meta[4] = sat
    return out


# --------------------------------------------------------------------------------------------
# One firmware tick (link_firmware_sim.firmware.LinkFirmware.on_imu, armed, eq. 1, no update due)
# --------------------------------------------------------------------------------------------

#: layout of :func:`tick_kernel`'s ``out``: thrust commands, ``U = [u; tau]``, the position and
#: attitude integrals, ``|u|``, the control estimate's position, 1 if ``U`` is finite (else 0), the
#: allocation's ``scale`` and ``saturated`` (1 or 0; with ``U`` finite)
TICK_OUT = {"command": slice(0, 8), "U": slice(8, 14), "pos_int": slice(14, 17), "att_int": slice(17, 20),
            "force_norm": 20, "p_ctrl": slice(21, 24), "finite": 24, "scale": 25, "saturated": 26}
TICK_OUT_SIZE = 27


def pack_correction(correction) -> np.ndarray:
    """A :class:`~companion.messages.Correction` as (9,): ``dp``, ``dv``, ``dtheta``."""
    return np.concatenate((correction.dp_w_m, correction.dv_w_m_s, correction.dtheta_w_rad)).astype(float)


@jit
def tick_kernel(x, P, predict, gyro, accel, dt_s, densities, baro_density, gravity_w, wgt, corr, tgt, gains,
                inertia, pos, att, gravity, B_pinv, reduced_by_side, nu, xi_pre, eps0, eps1, tmax, selective,
                scale_to_limit, tol, out):
    """The fast loop's tick in one call, with the operations of the functions it fuses in their
    order: if ``predict``, :func:`ekf_predict_kernel` (paper eq. 2's propagation; else ``x, P`` are
    already propagated and updated), the control estimate (EKF output
    plus ``wgt`` times the correction ``corr`` = ``[dp; dv; dtheta]``, the attitude by
    ``so3.retract``: :meth:`LinkFirmware.control_estimate`), the body rate ``gyro - b_g``,
    :func:`impedance_kernel` (paper eq. 1) and, when ``U`` is finite, :func:`allocate_kernel`
    (thesis Prop. 1, (2.15), (2.17); ``xi_pre`` updated). Returns the predicted ``(x, P)``;
    ``out`` (:data:`TICK_OUT`) gets the rest."""
    if predict:
        xn, Pn = ekf_predict_kernel(x, P, gyro, accel, dt_s, densities, baro_density, gravity_w)
    else:
        xn, Pn = x, P
    p = np.empty(3)
    v = np.empty(3)
    q = np.empty(4)
    for i in range(4):
        q[i] = xn[6 + i]
    if wgt > 0.0:
        for i in range(3):
            p[i] = xn[i] + wgt * corr[i]
            v[i] = xn[3 + i] + wgt * corr[3 + i]
        _retract_into(q, 0, 0.5 * (wgt * corr[6]), 0.5 * (wgt * corr[7]), 0.5 * (wgt * corr[8]))
    else:
        for i in range(3):
            p[i] = xn[i]
            v[i] = xn[3 + i]
    w = np.empty(3)
    for i in range(3):
        w[i] = gyro[i] - xn[13 + i]
    ctrl = np.empty(12)
    impedance_kernel(p, v, q, w, tgt, gains, inertia, pos, att, dt_s, gravity, ctrl)
    finite = True
    for i in range(6):
        out[8 + i] = ctrl[i]
        if not math.isfinite(ctrl[i]):
            finite = False
    for i in range(6):
        out[14 + i] = ctrl[6 + i]
    out[20] = math.sqrt(ctrl[0] * ctrl[0] + ctrl[1] * ctrl[1] + ctrl[2] * ctrl[2])
    for i in range(3):
        out[21 + i] = p[i]
    out[24] = 1.0 if finite else 0.0
    if finite:
        alloc = np.empty((5, 8))
        meta = np.empty(ALLOC_META)
        # the link's weight at the control estimate's attitude, kept whole at the limit:
        # control.weight_wrench, R^T m g e3 = m g (the third row of R(q))
        mg = inertia[0] * gravity
        keep = np.zeros(6)
        keep[0] = (2.0 * (q[1] * q[3] - q[0] * q[2])) * mg
        keep[1] = (2.0 * (q[2] * q[3] + q[0] * q[1])) * mg
        keep[2] = (1.0 - 2.0 * (q[1] * q[1] + q[2] * q[2])) * mg
        allocate_kernel(ctrl[:6], keep, B_pinv, reduced_by_side, nu, xi_pre, eps0, eps1, tmax, selective,
                        scale_to_limit, tol, alloc, meta)
        for i in range(8):
            out[i] = alloc[0, i]
        out[25] = meta[5]
        out[26] = meta[4]
    return xn, Pn


@jit
def attitude_tick_kernel(x, P, q_meas, att_Rm, gate_sigma, gyro, accel, dt_s, densities, baro_density, gravity_w,
                         wgt, corr, tgt, gains, inertia, pos, att, gravity, B_pinv, reduced_by_side, nu, xi_pre, eps0,
                         eps1, tmax, selective, scale_to_limit, tol, out):
    """:func:`tick_kernel` for a tick with an attitude reference ``q_meas`` queued, as the firmware
    runs it step by step: :func:`ekf_predict_kernel`, :func:`attitude_update_kernel` (covariance
    ``att_Rm``, gate ``gate_sigma``; the state's ekf.X_Q and the error's ekf.E_TH block), then the
    tick without the propagation (its arguments from ``gyro`` on, without ``predict``). Returns
    ``(x, P, status)``, the update's status: 1 accepted, 0 rejected by the gate, -1 an invalid
    quaternion (non-finite or zero), when nothing was changed or written and the caller takes the
    step-by-step path (which raises the specification's error)."""
    xp, Pp = ekf_predict_kernel(x, P, gyro, accel, dt_s, densities, baro_density, gravity_w)
    xu, Pu, status, _, _ = attitude_update_kernel(xp, Pp, q_meas, att_Rm, gate_sigma, 6, 6)
    if status < 0:
        return x, P, status
    xn, Pn = tick_kernel(xu, Pu, False, gyro, accel, dt_s, densities, baro_density, gravity_w, wgt, corr, tgt, gains,
                         inertia, pos, att, gravity, B_pinv, reduced_by_side, nu, xi_pre, eps0, eps1, tmax, selective,
                         scale_to_limit, tol, out)
    return xn, Pn, status


# --------------------------------------------------------------------------------------------
# One tick from the same-host simulator link's bytes to its answer's (link_firmware_sim.vehicle)
# --------------------------------------------------------------------------------------------

#: the simulator link's records (:mod:`link_firmware_sim.simlink`: a 1-byte kind, then the MAVLink
#: payload in wire order, little-endian) as :func:`hil_tick_kernel` reads and writes them; the
#: simlink module checks these offsets against the dialect's layouts when it is imported. They are
#: literals in this file, not derived from the dialect, on purpose: numba freezes a global into the
#: machine code it caches on disk, and its cache follows this file's changes only.
#: HIL_SENSOR: kind 0, ``time_usec`` (uint64), ``xacc..zacc`` then ``xgyro..zgyro`` (floats, body
#: FRD), ..., ``fields_updated`` (uint32)
HIL_SENSOR_RECORD = {"kind": 0, "size": 66, "time_usec": 1, "acc": 9, "gyro": 21, "fields_updated": 61}
#: HIL_ACTUATOR_CONTROLS: kind 3, ``time_usec`` and ``flags`` (uint64), ``controls`` (16 floats), ``mode`` (uint8)
HIL_ACTUATOR_RECORD = {"kind": 3, "size": 82, "time_usec": 1, "flags": 9, "controls": 17, "mode": 81}
# the same numbers as the kernel's compile-time constants
_SENSOR_KIND, _SENSOR_SIZE, _SENSOR_T, _SENSOR_ACC, _SENSOR_GYRO, _SENSOR_BITS = HIL_SENSOR_RECORD.values()
_ACT_KIND, _ACT_SIZE, _ACT_T, _ACT_FLAGS, _ACT_CONTROLS, _ACT_MODE = HIL_ACTUATOR_RECORD.values()
#: SKELETON_AHRS_REFERENCE: kind 2, ``time_usec`` (uint64), ``q`` (4 floats, body FRD to local NED)
HIL_AHRS_RECORD = {"kind": 2, "size": 25, "time_usec": 1, "q": 9}
_AHRS_KIND, _AHRS_SIZE, _AHRS_T, _AHRS_Q = HIL_AHRS_RECORD.values()
#: ``hil.decode_ahrs``'s tolerance on the reference quaternion's norm (a literal: ``tests/test_fast_paths.py``
#: checks it is hil's)
AHRS_NORM_TOLERANCE = 1e-3
#: ``ahrs`` of :func:`hil_tick_kernel` and :func:`hil_loop_kernel`: the attitude references they
#: fused, counted (accepted, rejected by the gate), and the newest one's ``time_usec`` and quaternion
#: (body FLU to ENU, normalised: what ``hil.decode_ahrs`` returns); the kernels add to the counts
AHRS_OUT = {"accepted": 0, "rejected": 1, "t_us": 2, "q": slice(3, 7)}
AHRS_OUT_SIZE = 7
#: the HIL_SENSOR ``fields_updated`` bits of a magnetometer or barometer sample (``hil``:
#: HIL_SENSOR_MAG, abs_pressure, pressure_alt; a literal for the same reason, and
#: ``tests/test_fast_paths.py`` checks it is hil's): such a tick takes the decoding path
HIL_BARO_MAG_BITS = 0x1C0 | (1 << 9) | (1 << 11)


@jit
def sensor_record_at(rec, n):
    """Where the HIL_SENSOR record of a packet of ``n`` bytes the record tick takes starts: 0 for
    [HIL_SENSOR], :data:`HIL_AHRS_RECORD`'s size for [SKELETON_AHRS_REFERENCE, HIL_SENSOR] (the
    attitude reference's ticks); -1 for any other packet."""
    if n == _SENSOR_SIZE and rec[0] == _SENSOR_KIND:
        return 0
    if n == _AHRS_SIZE + _SENSOR_SIZE and rec[0] == _AHRS_KIND and rec[_AHRS_SIZE] == _SENSOR_KIND:
        return _AHRS_SIZE
    return -1


@jit
def _ahrs_record(rec, frame, q):
    """``hil.decode_ahrs`` of the SKELETON_AHRS_REFERENCE record at the start of ``rec``, with the
    same numbers: its quaternion (body FRD to local NED) finite and of norm 1 within
    :data:`AHRS_NORM_TOLERANCE`, normalised and turned into body FLU to ENU
    (``frames.quat_ned_frd_to_enu_flu``: ``frame[:4] (x) q (x) frame[4:]``), into ``q``. False (``q``
    undefined) for a quaternion the decoder rejects."""
    qf = np.empty(4, np.float32)
    qf.view(np.uint8)[:] = rec[_AHRS_Q:_AHRS_Q + 16]
    m = np.empty(4)
    for i in range(4):
        if not math.isfinite(qf[i]):
            return False
        m[i] = np.float64(qf[i])
    n = math.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3])
    if abs(n - 1.0) > AHRS_NORM_TOLERANCE:
        return False
    for i in range(4):
        m[i] = m[i] / n
    e2n = np.empty(4)
    _quat_mul_into(frame[:4], m, e2n)
    _quat_mul_into(e2n, frame[4:], q)
    return True


@jit
def hil_tick_kernel(rec, thrust_max_n, mode, answer, gyro, x, P, dt_s, densities, baro_density, gravity_w, wgt,
                    corr, tgt, gains, inertia, pos, att, gravity, B_pinv, reduced_by_side, nu, xi_pre, eps0, eps1,
                    tmax, selective, scale_to_limit, tol, att_Rm, gate_sigma, ahrs_frame, ahrs, out):
    """The vehicle's common lockstep tick from bytes to bytes: a same-host simulator-link packet
    ``rec`` (uint8) holding one HIL_SENSOR record with an IMU sample only (no barometer or
    magnetometer bits) and finite accelerations and rates, after a SKELETON_AHRS_REFERENCE record
    on the attitude reference's ticks, to its HIL_ACTUATOR_CONTROLS record in ``answer`` (uint8,
    :data:`HIL_ACTUATOR_RECORD`'s size).

    The steps of the decoding path, with the same numbers: ``hil.decode_hil_sensor`` (body FRD to
    FLU), :func:`tick_kernel` with the propagation (its arguments from ``x`` to ``tol``, without
    ``predict``, ``gyro`` and ``accel``), ``hil.encode_actuators`` (each command over
    ``thrust_max_n``, clipped to -1..1, as a float; ``mode``; the sample's ``time_usec`` echoed).
    With an attitude reference (:func:`_ahrs_record`, ``ahrs_frame`` the frame change's two
    quaternions) the propagation, then :func:`attitude_update_kernel` (covariance ``att_Rm``, gate
    ``gate_sigma``), then the tick without the propagation, as the firmware runs a queued
    measurement; ``ahrs`` (:data:`AHRS_OUT`) counts it and holds its time and quaternion.
    ``gyro`` (3,) gets the body rate (FLU). Returns ``(x, P, taken)``: with ``taken`` false (another
    kind or size, baro/mag bits, a non-finite value, a reference the decoder rejects, an answer
    buffer of another size) nothing was changed or written and the caller decodes the packet the
    general way. The fields sit at odd offsets: they are copied byte-wise into aligned arrays, never
    read or written through a misaligned view."""
    s0 = sensor_record_at(rec, rec.shape[0])
    if s0 < 0 or answer.shape[0] != _ACT_SIZE:
        return x, P, False  # (the answer's size checked too: numba does not check the writes' bounds)
    bits = np.empty(1, np.uint32)
    bits.view(np.uint8)[:] = rec[s0 + _SENSOR_BITS:s0 + _SENSOR_BITS + 4]
    if bits[0] & HIL_BARO_MAG_BITS:
        return x, P, False
    imu = np.empty(6, np.float32)  # xacc, yacc, zacc, xgyro, ygyro, zgyro: adjacent in the record
    imu.view(np.uint8)[:] = rec[s0 + _SENSOR_ACC:s0 + _SENSOR_ACC + 24]
    for i in range(6):
        if not math.isfinite(imu[i]):
            return x, P, False
    accel = np.empty(3)
    g = np.empty(3)
    for i in range(3):
        sign = 1.0 if i == 0 else -1.0  # frames.flu_frd: (x, -y, -z)
        accel[i] = sign * np.float64(imu[i])
        g[i] = sign * np.float64(imu[3 + i])
    if s0 == 0:
        xn, Pn = tick_kernel(x, P, True, g, accel, dt_s, densities, baro_density, gravity_w, wgt, corr, tgt, gains,
                             inertia, pos, att, gravity, B_pinv, reduced_by_side, nu, xi_pre, eps0, eps1, tmax,
                             selective, scale_to_limit, tol, out)
    else:
        qm = np.empty(4)
        if not dt_s > 0.0 or not _ahrs_record(rec, ahrs_frame, qm):
            return x, P, False  # (the decoding path raises for a step that is not positive)
        xn, Pn, status = attitude_tick_kernel(x, P, qm, att_Rm, gate_sigma, g, accel, dt_s, densities, baro_density,
                                              gravity_w, wgt, corr, tgt, gains, inertia, pos, att, gravity, B_pinv,
                                              reduced_by_side, nu, xi_pre, eps0, eps1, tmax, selective, scale_to_limit,
                                              tol, out)
        ahrs[0 if status == 1 else 1] += 1.0  # (status -1, an invalid quaternion, cannot pass _ahrs_record)
        tb = np.empty(1, np.uint64)
        tb.view(np.uint8)[:] = rec[_AHRS_T:_AHRS_T + 8]
        ahrs[2] = tb[0]
        for i in range(4):
            ahrs[3 + i] = qm[i]
    for i in range(3):
        gyro[i] = g[i]
    controls = np.zeros(16, np.float32)
    for i in range(8):
        u = out[i] / thrust_max_n
        if u > 1.0:
            u = 1.0
        elif u < -1.0:
            u = -1.0
        controls[i] = np.float32(u)
    answer[0] = _ACT_KIND
    answer[_ACT_T:_ACT_T + 8] = rec[s0 + _SENSOR_T:s0 + _SENSOR_T + 8]
    answer[_ACT_FLAGS:_ACT_FLAGS + 8] = 0
    answer[_ACT_CONTROLS:_ACT_CONTROLS + 64] = controls.view(np.uint8)
    answer[_ACT_MODE] = mode
    return xn, Pn, True


# --------------------------------------------------------------------------------------------
# The vehicle's lockstep loop over quiet ticks, socket calls included (link_firmware_sim.vehicle)
# --------------------------------------------------------------------------------------------

#: ``info`` of :func:`hil_loop_kernel`: why it returned (one of the ``LOOP_*`` codes), the ticks it
#: computed, the answers it sent, the newest tick's sample time [us] and ``dt`` [s], the length of
#: a packet it received and left to the caller, and the bytes of the packets it took
LOOP_INFO = {"status": 0, "ticks": 1, "sent": 2, "t_us": 3, "dt": 4, "packet": 5, "taken_bytes": 6}
LOOP_INFO_SIZE = 7
#: nothing received is left over: the wait timed out or was interrupted, another descriptor (a
#: MAVLink port) is readable, the simulator's socket reported an error or hang-up, or ``max_ticks``
LOOP_IDLE = 0
#: a packet of ``info["packet"]`` bytes is in ``buf``, received but not taken (another kind or
#: size, baro/mag bits, a stale target, a GPS timeout due, ...): the caller decodes it
LOOP_PACKET = 1
#: the newest tick (``info["ticks"]`` >= 1) needs the caller's bookkeeping (the monitors, a stream or
#: log row due, ...), its answer already sent if ``info["sent"]`` counts it (else not: a non-finite
#: wrench, or a send that did not go through whole)
LOOP_TICKED = 2
_POLLIN = 0x1
_MSG_NOSIGNAL = 0x4000  # Linux's (the same-host link is Linux's: SOCK_SEQPACKET, SO_PEERCRED)

#: PX4's TCP simulator link carries the same messages in MAVLink 2 frames: the start byte, the
#: header's length (start byte to message id) and the checksum's (CRC-16/MCRF4XX over the frame
#: after the start byte, then the message's CRC extra)
MAV2_STX = 0xFD
MAV2_HEADER = 10
#: the messages of the common tick over TCP as :func:`hil_loop_kernel` reads (HIL_SENSOR,
#: SKELETON_AHRS_REFERENCE) and writes (HIL_ACTUATOR_CONTROLS) them: message id, CRC extra and the
#: payload's size (its record's less the kind byte). Literals for the same reason as the records'
#: offsets; :mod:`.simlink` checks them against the dialect when it is imported.
MAV_HIL_SENSOR = {"msgid": 107, "crc_extra": 108, "size": 65}
MAV_HIL_AHRS = {"msgid": 57002, "crc_extra": 112, "size": 24}
MAV_HIL_ACTUATOR = {"msgid": 93, "crc_extra": 47, "size": 81}
_MS_ID, _MS_EXTRA, _MS_SIZE = MAV_HIL_SENSOR.values()
_MA_ID, _MA_EXTRA, _MA_SIZE = MAV_HIL_AHRS.values()
_MO_ID, _MO_EXTRA, _MO_SIZE = MAV_HIL_ACTUATOR.values()
#: the longest answer's frame (an unsigned MAVLink 2 HIL_ACTUATOR_CONTROLS, no trailing zero)
FRAME_BYTES = MAV2_HEADER + _MO_SIZE + 2
#: ``framing`` of :func:`hil_loop_kernel` and :func:`frames_to_records` (int64): ``on`` 0 for the
#: same-host link's records, else MAVLink 2 frames on a TCP stream, read by the vehicle
#: (:data:`FRAMES_TO_VEHICLE`: HIL_SENSOR, SKELETON_AHRS_REFERENCE) or by the simulator
#: (:data:`FRAMES_TO_SIMULATOR`: HIL_ACTUATOR_CONTROLS); the peer's system and component (the one
#: sender whose frames are taken) and its last sequence number, kept up to date; this end's
#: system, component and next sequence number, kept up to date; the bytes of the newest answer's
#: frame that its send took (-1: none) and the frame's length (the rest is the caller's to send);
#: the sequence number of the newest frame read (for the caller to keep once it takes them)
FRAMING = {"on": 0, "src_sys": 1, "src_comp": 2, "seq_in": 3, "sys": 4, "comp": 5, "seq_out": 6, "sent": 7,
           "length": 8, "seq_read": 9}
FRAMING_SIZE = 10
_F_ON, _F_SRC_SYS, _F_SRC_COMP, _F_SEQ_IN, _F_SYS, _F_COMP, _F_SEQ_OUT, _F_SENT, _F_LENGTH, _F_SEQ_READ = FRAMING.values()
FRAMES_TO_VEHICLE = 1
FRAMES_TO_SIMULATOR = 2


@jit
def _crc_step(crc, byte):
    """MAVLink's checksum (CRC-16/MCRF4XX) ``crc`` continued by one byte."""
    tmp = (byte ^ (crc & 0xFF)) & 0xFF
    tmp = (tmp ^ (tmp << 4)) & 0xFF
    return ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF


@jit
def crc_mcrf4xx(data, start, end, crc):
    """MAVLink's checksum (CRC-16/MCRF4XX, pymavlink's ``x25crc``) of ``data[start:end]`` (uint8)
    continued from ``crc`` (0xFFFF to start one)."""
    for i in range(start, end):
        crc = _crc_step(crc, np.int64(data[i]))
    return crc


@jit
def frames_to_records(buf, n, rec, framing):
    """The same-host link's packet (into ``rec``; its length returned) that the first ``n`` bytes
    of ``buf`` carry as MAVLink 2 frames, or -1 unless those bytes are exactly a run of whole,
    unsigned frames (no incompatibility or compatibility flag), each of the kinds of ``framing``'s
    side (:data:`FRAMES_TO_VEHICLE`: HIL_SENSOR or SKELETON_AHRS_REFERENCE;
    :data:`FRAMES_TO_SIMULATOR`: HIL_ACTUATOR_CONTROLS) with a payload of 1 to its size bytes
    (MAVLink 2 cuts a payload's trailing zeros: they are put back), a good checksum, from
    ``framing``'s sender and numbered on from its last sequence number without a gap. Anything
    else (another message, a frame cut at either end, a duplicate or a lost frame, another sender,
    a bad checksum) is left to pymavlink's parser, which counts what it must. The newest frame's sequence number goes to
    ``framing["seq_read"]``, for the caller to keep once it takes the packet."""
    i = 0
    m = 0
    seq = framing[_F_SEQ_IN]
    while i < n:
        if n - i < MAV2_HEADER + 2 or buf[i] != MAV2_STX or buf[i + 2] != 0 or buf[i + 3] != 0:
            return -1
        length = np.int64(buf[i + 1])
        end = i + MAV2_HEADER + length
        if end + 2 > n or length == 0:
            return -1
        if (np.int64(buf[i + 4]) != (seq + 1) & 0xFF or buf[i + 5] != framing[_F_SRC_SYS]
                or buf[i + 6] != framing[_F_SRC_COMP]):
            return -1
        msgid = np.int64(buf[i + 7]) | (np.int64(buf[i + 8]) << 8) | (np.int64(buf[i + 9]) << 16)
        if framing[_F_ON] == FRAMES_TO_SIMULATOR:
            if msgid != _MO_ID:
                return -1
            kind, size, extra = _ACT_KIND, _MO_SIZE, _MO_EXTRA
        elif msgid == _MS_ID:
            kind, size, extra = _SENSOR_KIND, _MS_SIZE, _MS_EXTRA
        elif msgid == _MA_ID:
            kind, size, extra = _AHRS_KIND, _MA_SIZE, _MA_EXTRA
        else:
            return -1
        if length > size or m + 1 + size > rec.shape[0]:
            return -1
        crc = _crc_step(crc_mcrf4xx(buf, i + 1, end, 0xFFFF), extra)
        if np.int64(buf[end]) != (crc & 0xFF) or np.int64(buf[end + 1]) != crc >> 8:
            return -1
        rec[m] = kind
        rec[m + 1:m + 1 + length] = buf[i + MAV2_HEADER:end]
        rec[m + 1 + length:m + 1 + size] = 0
        m += 1 + size
        seq = np.int64(buf[i + 4])
        i = end + 2
    framing[_F_SEQ_READ] = seq
    return m


@jit
def record_to_frame(answer, frame, framing):
    """The HIL_ACTUATOR_CONTROLS record ``answer`` as the MAVLink 2 frame pymavlink packs (unsigned,
    from ``framing``'s system and component, with its next sequence number, which moves on; the
    payload's trailing zeros cut, one byte kept) into ``frame``; returns the frame's length."""
    plen = _MO_SIZE
    while plen > 1 and answer[plen] == 0:  # (the payload's byte j is the record's j + 1)
        plen -= 1
    frame[0] = MAV2_STX
    frame[1] = plen
    frame[2] = 0
    frame[3] = 0
    frame[4] = framing[_F_SEQ_OUT] & 0xFF
    frame[5] = framing[_F_SYS]
    frame[6] = framing[_F_COMP]
    frame[7] = _MO_ID & 0xFF
    frame[8] = (_MO_ID >> 8) & 0xFF
    frame[9] = _MO_ID >> 16
    frame[MAV2_HEADER:MAV2_HEADER + plen] = answer[1:1 + plen]
    end = MAV2_HEADER + plen
    crc = _crc_step(crc_mcrf4xx(frame, 1, end, 0xFFFF), _MO_EXTRA)
    frame[end] = crc & 0xFF
    frame[end + 1] = crc >> 8
    framing[_F_SEQ_OUT] = (framing[_F_SEQ_OUT] + 1) & 0xFF
    return end + 2

if ENABLED:
    from llvmlite import ir as _ir
    from numba import types as _types
    from numba.core import cgutils as _cgutils
    from numba.extending import intrinsic as _intrinsic

    _I32, _I64, _P8 = _ir.IntType(32), _ir.IntType(64), _ir.IntType(8).as_pointer()

    def _data_ptr(context, builder, array_type, value):
        return builder.bitcast(context.make_array(array_type)(context, builder, value).data, _P8)

    def _libc_call(builder, name, ret, params, args):
        """A call of the C library's ``name`` by symbol (numba caches code that links libc by name)."""
        fn = _cgutils.get_or_insert_function(builder.module, _ir.FunctionType(ret, params), name)
        return builder.call(fn, args)

    @_intrinsic
    def _c_poll(typingctx, fds, nfds, timeout_ms):
        """``poll(2)`` on ``fds``: int32 pairs ``(fd, events | revents << 16)``, a ``struct pollfd`` each."""
        def codegen(context, builder, sig, args):
            return _libc_call(builder, "poll", _I32, [_P8, _I64, _I32],
                              [_data_ptr(context, builder, sig.args[0], args[0]), args[1], args[2]])
        return _types.int32(fds, _types.int64, _types.int32), codegen

    def _c_transfer(name: str):
        """The C library's ``name`` (``recv`` or ``send``: ``(fd, buf, n, flags)``, the first ``n``
        bytes of ``buf``, uint8) as an intrinsic."""
        def call(typingctx, fd, buf, n, flags):
            def codegen(context, builder, sig, args):
                return _libc_call(builder, name, _I64, [_I32, _P8, _I64, _I32],
                                  [args[0], _data_ptr(context, builder, sig.args[1], args[1]), args[2], args[3]])
            return _types.int64(_types.int32, buf, _types.int64, _types.int32), codegen
        call.__name__ = call.__qualname__ = f"_c_{name}"
        return _intrinsic(call)

    _c_recv, _c_send = _c_transfer("recv"), _c_transfer("send")
else:  # the numpy path never runs the loop (LinkFirmware.hil_loop is off without the kernels)
    def _c_poll(fds, nfds, timeout_ms):
        raise RuntimeError("the lockstep loop needs the compiled kernels")

    _c_recv = _c_send = _c_poll


@jit
def hil_loop_kernel(pfd, n_fds, timeout_ms, max_ticks, buf, thrust_max_n, mode, answer, gyro, x, P, t_prev_s,
                    dt_default_s, target_time_s, target_stale_s, corr_time_s, corr_hold_s, corr_stale_s, gps_fix_s,
                    gps_timeout_s, due_us, arm_height_m, takeoff_m, densities, baro_density, gravity_w, corr, tgt, gains,
                    inertia, pos, att, gravity, B_pinv, reduced_by_side, nu, xi_pre, eps0, eps1, tmax, selective,
                    scale_to_limit, tol, att_Rm, gate_sigma, ahrs_frame, ahrs, out, info, framing, rec, frame):
    """The vehicle's lockstep over its quiet ticks in one call, the waits and the socket calls in it
    (C library's ``poll``, ``recv``, ``send``): the simulator's socket is ``pfd``'s first
    descriptor (non-blocking), the vehicle's MAVLink ports the others. Each turn waits for the
    simulator (at most ``timeout_ms``), receives one packet into ``buf`` and, when
    :func:`hil_tick_kernel` takes it, sends its answer at once.

    The simulator's link is the same-host link (``SOCK_SEQPACKET``: a packet of records), or with
    ``framing["on"]`` (:data:`FRAMING`) PX4's TCP link: what one receive brings is taken when it is
    exactly the MAVLink 2 frames of such a packet (:func:`frames_to_records`, into ``rec``: the
    whole frames the simulator writes at once; anything else, e.g. a read that cuts a frame, is
    handed over as a packet, for pymavlink's parser), and the answer goes out as its MAVLink 2
    frame (:func:`record_to_frame`, in ``frame``; a send that takes only part of it is the caller's
    to finish, ``framing["sent"]``); the sequence numbers both ways are kept in ``framing``.

    A tick is quiet when what :meth:`~link_firmware_sim.firmware.LinkFirmware.on_hil_record` and
    the vehicle do after the kernel changes nothing, so that leaving it out is exact: the wrench is
    finite, the allocation not saturated, no take-off to detect (the control estimate's height at
    most ``takeoff_m`` above ``arm_height_m``, infinite once airborne), no stream or log row due (``t_us < due_us``). What the caller finds
    before a tick, the kernel checks for each: the target still fresh (``t - target_time_s <=
    target_stale_s``), no GPS timeout due (``t - gps_fix_s < gps_timeout_s``), and it computes the
    correction's weight (:meth:`~link_firmware_sim.firmware.LinkFirmware.correction_weight`: 1
    until ``corr_hold_s``, then a linear fade to 0 at ``corr_stale_s``; ``corr_time_s`` NaN: no
    correction) and ``dt`` (since ``t_prev_s``; ``dt_default_s`` if not positive) as the firmware
    does. It returns at the first tick that is not quiet (:data:`LOOP_TICKED`: the caller does that
    tick's bookkeeping, which also stands for the quiet ticks' before it, as those change nothing
    it would not set again), at a packet it does not take (:data:`LOOP_PACKET`), and when there is
    nothing to do (:data:`LOOP_IDLE`: timeout, a MAVLink port readable, the simulator's socket in
    error, ``max_ticks`` quiet ticks). Returns ``(x, P)``; the integrals ``pos``, ``att`` and
    ``xi_pre`` are updated in place, ``out`` and ``gyro`` hold the newest tick's, ``ahrs``
    (:data:`AHRS_OUT`) counts the attitude references fused and holds the newest, ``info``
    (:data:`LOOP_INFO`) the rest."""
    info[0] = LOOP_IDLE
    info[1] = 0.0
    info[2] = 0.0
    info[5] = 0.0
    info[6] = 0.0
    while info[1] < max_ticks:
        for k in range(n_fds):
            pfd[2 * k + 1] = _POLLIN
        r = _c_poll(pfd, n_fds, timeout_ms)
        if r <= 0:
            return x, P  # timeout, or interrupted (a signal: the caller's handler runs)
        for k in range(1, n_fds):
            if pfd[2 * k + 1] >> 16 != 0:
                return x, P  # a MAVLink port has something: the caller reads it
        if (pfd[1] >> 16) != _POLLIN:
            return x, P  # nothing from the simulator yet, or an error / hang-up: the caller's recv sees it
        n = _c_recv(pfd[0], buf, buf.shape[0], 0)
        if n <= 0:
            return x, P  # EAGAIN, or the peer closed: the caller's recv sees it again
        if framing[_F_ON] != 0:
            m = frames_to_records(buf, n, rec, framing)
            if m < 0:
                info[0] = LOOP_PACKET
                info[5] = n
                return x, P
            pkt = rec[:m]
        else:
            m = n
            pkt = buf[:n]
        s0 = sensor_record_at(pkt, m)
        if s0 < 0:
            info[0] = LOOP_PACKET
            info[5] = n
            return x, P
        tb = np.empty(1, np.uint64)
        tb.view(np.uint8)[:] = pkt[s0 + _SENSOR_T:s0 + _SENSOR_T + 8]
        t_us = tb[0]
        t_s = t_us * 1e-6  # (hil.seconds)
        if not (t_s - target_time_s <= target_stale_s) or not (t_s - gps_fix_s < gps_timeout_s):
            info[0] = LOOP_PACKET
            info[5] = n
            return x, P
        wgt = 0.0  # LinkFirmware.correction_weight
        if not math.isnan(corr_time_s):
            age = t_s - corr_time_s
            if age <= corr_hold_s:
                wgt = 1.0
            elif age >= corr_stale_s:
                wgt = 0.0
            else:
                wgt = (corr_stale_s - age) / (corr_stale_s - corr_hold_s)
        dt = t_s - t_prev_s
        if dt <= 0.0:
            dt = dt_default_s
        xn, Pn, taken = hil_tick_kernel(pkt, thrust_max_n, mode, answer, gyro, x, P, dt, densities,
                                        baro_density, gravity_w, wgt, corr, tgt, gains, inertia, pos, att, gravity,
                                        B_pinv, reduced_by_side, nu, xi_pre, eps0, eps1, tmax, selective,
                                        scale_to_limit, tol, att_Rm, gate_sigma, ahrs_frame, ahrs, out)
        if not taken:
            info[0] = LOOP_PACKET
            info[5] = n
            return x, P
        x, P = xn, Pn
        if framing[_F_ON] != 0:
            framing[_F_SEQ_IN] = framing[_F_SEQ_READ]  # the frames taken: their sender's numbers seen
        info[1] += 1.0
        info[6] += n
        info[3] = t_us
        info[4] = dt
        t_prev_s = t_s
        sent = False
        if out[24] != 0.0:  # a finite wrench: the answer goes out
            if framing[_F_ON] != 0:
                length = record_to_frame(answer, frame, framing)
                framing[_F_LENGTH] = length
                framing[_F_SENT] = _c_send(pfd[0], frame, length, _MSG_NOSIGNAL)
                sent = framing[_F_SENT] == length
            else:
                sent = _c_send(pfd[0], answer, _ACT_SIZE, _MSG_NOSIGNAL) == _ACT_SIZE
        if sent:
            info[2] += 1.0
        else:
            info[0] = LOOP_TICKED  # not sent (whole): the caller's send (or its error) takes over
            return x, P
        for i in range(3):
            pos[i] = out[14 + i]
            att[i] = out[17 + i]
        if out[26] != 0.0 or out[23] - arm_height_m > takeoff_m or t_us >= due_us:
            info[0] = LOOP_TICKED
            return x, P
    return x, P


# --------------------------------------------------------------------------------------------


def warm_up() -> float:
    """Compile (first run) or load from the cache (later runs) every kernel, through the paths the
    firmware calls them by (so with the argument types it passes); returns the seconds it took."""
    if not ENABLED:
        return 0.0
    from companion.messages import PoseTarget
    from companion.skeleton.body import LinkInertia
    from companion.skeleton.rotors import RotorGeometry

    from .allocation import Allocator
    from .control import ControlIntegrals, ImpedanceGains, impedance_control_compiled
    from .ekf import EkfConfig, LinkEkf

    t0 = time.perf_counter()
    z3 = np.zeros(3)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    ekf = LinkEkf(z3, z3, q, EkfConfig(), compiled=True)
    for _ in range(2):  # without, then with the barometer's offset
        ekf.predict(z3, np.array([0.0, 0.0, 9.8]), 0.002)
        ekf.update_position(z3)
        ekf.update_velocity(z3)
        ekf.update_attitude(q)
        ekf.update_heading(0.0)
        ekf.update_mag(np.array([0.2, 0.0, -0.4]))
        ekf.update_baro(0.0)
    U, _ = impedance_control_compiled(z3, z3, q, z3, PoseTarget.hold(z3, q), ImpedanceGains(),
                                      LinkInertia(1.8, (0.01, 0.2, 0.2)), ControlIntegrals(), 0.002)
    Allocator(RotorGeometry.odar(), compiled=True).allocate(U)
    # the fused tick (tick_kernel) as the firmware calls it: armed, without and with a correction
    # and a queued measurement
    from companion.messages import Correction

    from .firmware import FirmwareConfig, LinkFirmware

    fw = LinkFirmware(0, FirmwareConfig(), LinkInertia(1.8, (0.01, 0.2, 0.2)), RotorGeometry.odar())
    fw.initialize(0.0, z3, z3, q)
    fw.arm(0.0)
    fw.set_target(0.0, PoseTarget.hold(z3, q))
    accel = np.array([0.0, 0.0, 9.8])
    fw.on_imu(0.002, z3, accel)
    fw.on_correction(0.002, Correction(0, 0.0, z3 + 0.01, z3, z3))
    fw.on_attitude(0.004, q)
    fw.on_imu(0.004, z3, accel)
    # the vehicle's record tick (hil_tick_kernel) from a same-host simulator-link packet
    from .hil import encode_hil_sensor
    from .simlink import encode_packet

    from .hil import encode_ahrs

    record = np.frombuffer(encode_packet([encode_hil_sensor(0.006, accel, z3)]), dtype=np.uint8)
    answer = np.zeros(HIL_ACTUATOR_RECORD["size"], dtype=np.uint8)
    fw.on_hil_record(0.006, record, answer, 8.0, 128)
    sensor_record_at(record, len(record))  # (the vehicle finds the sample's time with it)
    # ... and its lockstep loop (hil_loop_kernel), over a socket pair: one tick, then no packet
    import socket

    from .simlink import RECV_BYTES

    sim, harness = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        sim.setblocking(False)
        harness.send(encode_packet([encode_hil_sensor(0.008, accel, z3)]))
        harness.send(encode_packet([encode_ahrs(0.010, q), encode_hil_sensor(0.010, accel, z3)]))
        fds = np.array([sim.fileno(), 0], dtype=np.int32)
        fw.on_hil_loop(fds, 1, 0, 4, np.zeros(RECV_BYTES, dtype=np.uint8), answer, 8.0, 128, 2**62, sim.send,
                       np.zeros(AHRS_OUT_SIZE))
    finally:
        sim.close()
        harness.close()
    # ... over a stream of MAVLink 2 frames (PX4's TCP link): one tick (its frames and its answer's)
    from companion.mavlink.dialect import load_dialect

    mav = load_dialect().MAVLink(None, srcSystem=255, srcComponent=190)
    sim, harness = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sim.setblocking(False)
        harness.send(encode_hil_sensor(0.012, accel, z3).pack(mav))
        framing = np.zeros(FRAMING_SIZE, dtype=np.int64)
        framing[:7] = (FRAMES_TO_VEHICLE, 255, 190, 255, 1, 1, 0)
        fds = np.array([sim.fileno(), 0], dtype=np.int32)
        fw.on_hil_loop(fds, 1, 0, 4, np.zeros(RECV_BYTES, dtype=np.uint8), answer, 8.0, 128, 2**62, sim.send,
                       np.zeros(AHRS_OUT_SIZE), framing, np.zeros(RECV_BYTES, dtype=np.uint8),
                       np.zeros(FRAME_BYTES, dtype=np.uint8))
    finally:
        sim.close()
        harness.close()
    # ... and the simulator's reader of the answers' frames (link_firmware_sim.simlink.FrameReader)
    frame = np.zeros(FRAME_BYTES, dtype=np.uint8)
    length = record_to_frame(answer, frame, framing)
    framing[:4] = (FRAMES_TO_SIMULATOR, 1, 1, 255)
    frames_to_records(frame, length, np.zeros(RECV_BYTES, dtype=np.uint8), framing)
    return time.perf_counter() - t0

"""Optional compiled kernels (numba) of the companion's hottest numpy paths, beside their specification.

The numpy functions stay the specification; a kernel here computes the same numbers with plain
loops over scalars, compiled by numba (``njit(cache=True)``), and
``tests/test_fast_paths.py`` checks it against its specification on random inputs (agreement to
1e-12). Today one kernel: :func:`feedforward_kernel`, the whole-chain inverse dynamics of
:meth:`~companion.skeleton.dynamics.ChainModel.solve` after the joints' passive torques (the
target source calls it at 50 Hz; interpreted it was a quarter of a batch flight's companion).

numba is not an onboard dependency: it comes with the ``sim`` extra. Without it (the Raspberry Pi
install), or with ``SKELETON_JIT=0`` in the environment, :data:`ENABLED` is false, :func:`jit`
returns the function unchanged and every caller runs the numpy specification.

Compilation happens at the first call and is cached on disk (``__pycache__`` beside this file, or
``NUMBA_CACHE_DIR``); :func:`warm_up` compiles (or loads) every kernel here once. The simulator's
firmware kernels (``link_firmware_sim._fast``) use the same :func:`jit`.
"""

from __future__ import annotations

import logging
import os
import time

import numpy as np

__all__ = ["ENABLED", "jit", "warm_up", "feedforward_kernel"]

log = logging.getLogger(__name__)


def _want_jit() -> bool:
    return os.environ.get("SKELETON_JIT", "1").strip().lower() not in ("0", "false", "no", "off")


try:
    if not _want_jit():
        raise ImportError("SKELETON_JIT=0")
    import numba

    #: the kernels are compiled (numba importable and not turned off with ``SKELETON_JIT=0``)
    ENABLED = True

    def jit(fn):
        """``numba.njit`` as every kernel uses it: cached on disk, numpy's float semantics (a
        division by zero gives inf / nan, as in the numpy specification, instead of raising), no
        fast-math (IEEE arithmetic, so the kernels reorder no sums within one expression)."""
        return numba.njit(cache=True, error_model="numpy", nogil=True)(fn)

except ImportError as exc:  # the onboard install (no numba) or turned off
    ENABLED = False
    log.info("compiled kernels off (%s): the numpy path runs", exc)

    def jit(fn):
        return fn


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
                a0, a1, a2 = (arm_r[j, 0], arm_r[j, 1], arm_r[j, 2]) if side == 0 else (arm_l[j, 0], arm_l[j, 1],
                                                                                        arm_l[j, 2])
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
            a0, a1, a2 = (arm_r[j, 0], arm_r[j, 1], arm_r[j, 2]) if side == 0 else (arm_l[j, 0], arm_l[j, 1], arm_l[j, 2])
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
    return time.perf_counter() - t0

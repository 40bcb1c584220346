"""A bending chain's targets (poses at five instants and their central differences), as a kernel.

The specification is :meth:`companion.trajectory.ChainTrajectory.target_arrays` (its numpy code).
"""

from __future__ import annotations

import math

import numpy as np

from .jit import jit
from .so3 import rotmat_quadratic_into

__all__ = ["trajectory_kernel"]


@jit
def trajectory_kernel(theta, center, shape, h, out):
    """:meth:`~companion.trajectory.ChainTrajectory.target_arrays` (its numpy form is the
    specification): ``theta`` (5,) the bend angles and ``center`` (5, 3) the chain's middle point at
    ``t + k h``, ``k = -2..2``; ``shape = (share, base_q, d)``: link ``i`` is pitched by ``theta
    share[i]`` after ``base_q``, the links joined tip to tip (``d`` (3,), centre to right tip, body
    frame). ``out = (p, q, R, v, acc, w, wd)`` gets at ``t`` every link's centre ``p`` (n, 3),
    attitude ``q`` (n, 4) and ``R`` (n, 3, 3), velocity ``v``, acceleration ``acc``, body rate ``w =
    (R^T dR/dt)^v`` and its derivative ``wd``, all by central differences."""
    share, base_q, d = shape
    p, q, R, v, acc, w, wd = out
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
            rotmat_quadratic_into(Q5[k], i, R5[k, i])
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

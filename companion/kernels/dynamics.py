"""The chain's inverse dynamics (the targets' feed-forward), as kernels: the joints' passive
torques, and the rest after them.

The specification is :meth:`companion.skeleton.dynamics.ChainModel.solve` (its numpy code).
"""

from __future__ import annotations

import numpy as np

from .jit import jit
from .so3 import rotmat_log

__all__ = ["passive_torques_kernel", "feedforward_kernel"]


@jit
def passive_torques_kernel(R, w, stiffness, damping, tau_j):
    """:meth:`~companion.skeleton.dynamics.ChainModel.solve`'s passive joint torques on the child
    (the compliant cable's stiffness and damping), world frame: ``tau_j`` (n-1, 3) <- ``R_{j+1}
    (-stiffness Log(R_j^T R_{j+1}) - damping (w_{j+1} - R_rel^T w_j))`` of the attitudes ``R``
    (n, 3, 3) and body rates ``w`` (n, 3)."""
    rel = np.empty((3, 3))
    c = np.empty(3)
    for j in range(R.shape[0] - 1):
        for a in range(3):
            for b in range(3):
                rel[a, b] = R[j, 0, a] * R[j + 1, 0, b] + R[j, 1, a] * R[j + 1, 1, b] + R[j, 2, a] * R[j + 1, 2, b]
        l0, l1, l2 = rotmat_log(rel)
        for k in range(3):
            w_rel = w[j + 1, k] - (rel[0, k] * w[j, 0] + rel[1, k] * w[j, 1] + rel[2, k] * w[j, 2])
            c[k] = -stiffness * (l0 if k == 0 else l1 if k == 1 else l2) - damping * w_rel
        for k in range(3):
            tau_j[j, k] = R[j + 1, k, 0] * c[0] + R[j + 1, k, 1] * c[1] + R[j + 1, k, 2] * c[2]


@jit
def feedforward_kernel(motion, R, tau_j, link, weights, out):
    """:meth:`~companion.skeleton.dynamics.ChainModel.solve` from the joints' passive torques on:
    ``motion = (p, w, wd, acc)`` (n, 3) each, the centres, body rates and their derivatives and the
    centre accelerations; ``R`` (n, 3, 3) the attitudes; ``tau_j`` (n-1, 3) the passive joint
    torques (world); ``link = (d, J, mass, gravity, scale)``: the centre-to-right-tip offset (3,),
    the principal inertia (3,), the mass, gravity and the moment weight (1 / half link length);
    ``weights`` (n,) each link's rotor-wrench weight in the least squares. ``out = (force_ff,
    torque_ff, F, rotor)`` gets (n, 3) each minus the joints' wrench on each link (zeros on entry),
    ``F`` (n-1, 3) the joint forces and ``rotor`` (n, 6)."""
    p, w, wd, acc = motion
    d, J, mass, gravity, scale = link
    force_ff, torque_ff, F, rotor = out
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

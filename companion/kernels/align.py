"""The step's time alignment of a chain's link states and its corrections' attitude part, as kernels.

The specifications are :func:`companion.corrections.align_states` (its numpy code: each link's
state propagated to the step time with its own velocity and body rate) and
:func:`companion.estimation.so3.attitude_error` of stacked quaternions (what
:func:`companion.corrections.compute_corrections` gives each link as its attitude correction).
"""

from __future__ import annotations

import math

from .jit import jit
from .so3 import quat_log, quat_mul

__all__ = ["align_kernel", "attitude_errors_kernel"]


@jit
def align_kernel(t_s, stamps_s, p, v, q, w, p_out, q_out):
    """Every link's state at ``t_s`` from its own at ``stamps_s[i]``: ``p_out[i] = p[i] + v[i] dt``
    and ``q_out[i] = q[i] (x) Exp(w[i] dt)``, ``dt = t_s - stamps_s[i]`` (``p``, ``v``, ``w`` (n, 3),
    ``q`` (n, 4)); ``Exp`` as ``so3.quat_from_rotvec``, its ``sin(a/2)/a`` by its Taylor series below
    1e-8 rad."""
    for i in range(p.shape[0]):
        dt = t_s - stamps_s[i]
        for k in range(3):
            p_out[i, k] = p[i, k] + v[i, k] * dt
        rx, ry, rz = w[i, 0] * dt, w[i, 1] * dt, w[i, 2] * dt
        angle = math.sqrt(rx * rx + ry * ry + rz * rz)
        k = 0.5 - angle * angle / 48.0 if angle < 1e-8 else math.sin(0.5 * angle) / angle
        (q_out[i, 0], q_out[i, 1], q_out[i, 2],
         q_out[i, 3]) = quat_mul(q[i, 0], q[i, 1], q[i, 2], q[i, 3], math.cos(0.5 * angle), k * rx, k * ry, k * rz)


@jit
def attitude_errors_kernel(q_to, q_from, out):
    """``out[i]`` (n, 3) <- the world-frame rotation vector taking ``q_from[i]`` to ``q_to[i]``:
    ``Log(q_to (x) conj(q_from))``, angle in [0, pi] (``so3.attitude_error``)."""
    for i in range(q_to.shape[0]):
        dw, dx, dy, dz = quat_mul(q_to[i, 0], q_to[i, 1], q_to[i, 2], q_to[i, 3],
                                  q_from[i, 0], -q_from[i, 1], -q_from[i, 2], -q_from[i, 3])
        out[i, 0], out[i, 1], out[i, 2] = quat_log(dw, dx, dy, dz)

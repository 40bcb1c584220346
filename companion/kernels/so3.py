"""Scalar quaternion and rotation kernels, the one set both packages' kernels use.

Quaternions are Hamilton, scalar first, ``(w, x, y, z)``, body to world (the conventions of
:mod:`companion.estimation.so3`, whose numpy functions are the specification). Each kernel takes
and returns plain floats (tuples), so that the kernels calling it compile it inline.

Two forms of ``R(q)`` are kept, as their specifications have them: :func:`rotmat_unit` (the
``1 - 2 (y^2 + z^2)`` form of :func:`~companion.estimation.so3.rotmat_tuple`, for a unit
quaternion) and :func:`rotmat_quadratic` (``w^2 + x^2 - y^2 - z^2``, the quadratic form of the
stacked :func:`~companion.estimation.so3.quat_to_rotmat`; ``|q|^2 R`` for any quaternion). They agree
to rounding on unit quaternions; each caller keeps the one its specification computes.
"""

from __future__ import annotations

import math

from .jit import jit

__all__ = ["quat_mul", "rotmat_unit", "rotmat_quadratic", "rotmat_quadratic_into", "retract", "small_angle_quat",
           "quat_exp", "quat_log", "rotmat_log"]


@jit
def quat_mul(aw, ax, ay, az, bw, bx, by, bz):
    """The Hamilton product ``a (x) b`` (``so3.quat_mul`` of one pair)."""
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


@jit
def rotmat_unit(w, x, y, z):
    """``R(q)`` of a unit quaternion, row-major 9-tuple (``so3.rotmat_tuple``)."""
    return (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@jit
def rotmat_quadratic(w, x, y, z):
    """``R(q)`` in its quadratic form, row-major 9-tuple (``so3.quat_to_rotmat`` of a stack)."""
    return (w * w + x * x - y * y - z * z, 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), w * w - x * x + y * y - z * z, 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z)


@jit
def rotmat_quadratic_into(q, i, R):
    """``R`` (3, 3) <- :func:`rotmat_quadratic` of the quaternion ``q[i]`` (``q``: (n, 4))."""
    (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1],
     R[2, 2]) = rotmat_quadratic(q[i, 0], q[i, 1], q[i, 2], q[i, 3])


@jit
def retract(w, x, y, z, hx, hy, hz):
    """``normalise((1, h) (x) q)``, ``h = dtheta / 2``: a world-frame attitude error injected
    (``so3.retract`` of one quaternion; ``(1, h)``'s own normalisation cancels)."""
    rw, rx, ry, rz = quat_mul(1.0, hx, hy, hz, w, x, y, z)
    inv = 1.0 / math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    return rw * inv, rx * inv, ry * inv, rz * inv


@jit
def small_angle_quat(hx, hy, hz):
    """``(1, h)`` normalised, ``h = dtheta / 2`` (``so3.small_angle_quat``)."""
    inv = 1.0 / math.sqrt(1.0 + hx * hx + hy * hy + hz * hz)
    return inv, hx * inv, hy * inv, hz * inv


@jit
def quat_exp(rx, ry, rz):
    """``Exp(r)``: the unit quaternion of the rotation vector ``r`` (``(1, r / 2)`` below 1e-8 rad)."""
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-8:
        w, k = 1.0, 0.5
    else:
        w, k = math.cos(0.5 * angle), math.sin(0.5 * angle) / angle
    return w, k * rx, k * ry, k * rz


@jit
def quat_log(w, x, y, z):
    """The rotation vector of a unit quaternion, angle in [0, pi] (``so3.quat_to_rotvec``)."""
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    k = 2.0 * math.atan2(s, w) / s if s > 1e-12 else 2.0 / max(w, 1e-300)
    return k * x, k * y, k * z


@jit
def rotmat_log(R):
    """The rotation vector of the rotation matrix ``R`` (3, 3), angle in [0, pi]: its unit
    quaternion by Shepperd's method (``so3.rotmat_to_quat``'s pivot), then :func:`quat_log` (what
    ``pin.log3`` computes, well conditioned at every angle)."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr >= R[0, 0] and tr >= R[1, 1] and tr >= R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + tr)
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        w, x, y, z = (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] >= R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        w, x, y, z = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        w, x, y, z = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s
    return quat_log(w, x, y, z)

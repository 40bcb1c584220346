"""Eq. 1 (the paper's impedance controller) as a kernel.

The specification is :func:`link_firmware_sim.controllers.impedance.impedance_control`; the kernel
computes the same numbers with plain loops over scalars (``tests/unit/test_fast_paths.py``). Its gains,
the link's inertia and its integrals are one array (``CTL_*`` of :mod:`.layouts`), the target
another (``TGT_*``).
"""

from __future__ import annotations

import math

import numpy as np

from companion.kernels.jit import jit
from companion.kernels.so3 import rotmat_unit

from .layouts import (CTL_ATT_INT, CTL_ATT_INT_LIMIT, CTL_GAMMA_I, CTL_GRAVITY, CTL_J, CTL_KD, CTL_KI, CTL_KI_ATT,
                      CTL_KP, CTL_KR, CTL_KW, CTL_MASS, CTL_POS_ERROR_LIMIT, CTL_POS_INT, CTL_POS_INT_LIMIT,
                      TGT_A, TGT_FORCE_FF, TGT_R, TGT_TORQUE_FF, TGT_V, TGT_W, TGT_WDOT)

__all__ = ["impedance_kernel"]


@jit
def _clamp(c, limit):
    return min(max(c, -limit), limit)


@jit
def impedance_kernel(p, v, q, w, tgt, ctl, dt_s, U):
    """Eq. 1 at the control estimate ``p``, ``v`` (3,), ``q`` (4,) and the body rate ``w`` (3,),
    towards the target ``tgt`` (``TGT_*``), with the controller ``ctl`` (``CTL_*``) over ``dt_s``:
    ``U`` (6,) <- ``[u; tau]``; the integrals in ``ctl`` are updated in place."""
    R = rotmat_unit(q[0], q[1], q[2], q[3])
    m = ctl[CTL_MASS]
    Jx, Jy, Jz = ctl[CTL_J], ctl[CTL_J + 1], ctl[CTL_J + 2]
    pos_lim, att_lim = ctl[CTL_POS_INT_LIMIT], ctl[CTL_ATT_INT_LIMIT]
    f_w = np.empty(3)
    e = np.empty(3)
    for i in range(3):
        e[i] = p[i] - tgt[i]
    n = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    limit = ctl[CTL_POS_ERROR_LIMIT]
    if n > limit:  # controllers.common.limit_length
        k = limit / n
        for i in range(3):
            e[i] = e[i] * k
    for i in range(3):
        e_p = e[i]
        pi = _clamp(ctl[CTL_POS_INT + i] + e_p * dt_s, pos_lim)
        ctl[CTL_POS_INT + i] = pi
        ag = tgt[TGT_A + i] + (ctl[CTL_GRAVITY] if i == 2 else 0.0)
        f_w[i] = (m * ag - ctl[CTL_KD + i] * (v[i] - tgt[TGT_V + i]) - ctl[CTL_KP + i] * e_p - ctl[CTL_KI + i] * pi
                  + tgt[TGT_FORCE_FF + i])
    for i in range(3):
        U[i] = R[i] * f_w[0] + R[3 + i] * f_w[1] + R[6 + i] * f_w[2]
    RtRd = np.empty(9)
    for i in range(3):
        for j in range(3):
            RtRd[3 * i + j] = R[i] * tgt[TGT_R + j] + R[3 + i] * tgt[TGT_R + 3 + j] + R[6 + i] * tgt[TGT_R + 6 + j]
    e_R = (RtRd[5] - RtRd[7], RtRd[6] - RtRd[2], RtRd[1] - RtRd[3])
    w_db = np.empty(3)
    rd = np.empty(3)
    tau_ff = np.empty(3)
    for i in range(3):
        w_db[i] = RtRd[3 * i] * tgt[TGT_W] + RtRd[3 * i + 1] * tgt[TGT_W + 1] + RtRd[3 * i + 2] * tgt[TGT_W + 2]
        rd[i] = RtRd[3 * i] * tgt[TGT_WDOT] + RtRd[3 * i + 1] * tgt[TGT_WDOT + 1] + RtRd[3 * i + 2] * tgt[TGT_WDOT + 2]
        tau_ff[i] = (RtRd[3 * i] * tgt[TGT_TORQUE_FF] + RtRd[3 * i + 1] * tgt[TGT_TORQUE_FF + 1]
                     + RtRd[3 * i + 2] * tgt[TGT_TORQUE_FF + 2])
    e_w = (w[0] - w_db[0], w[1] - w_db[1], w[2] - w_db[2])
    gI = ctl[CTL_GAMMA_I]
    for i in range(3):
        ctl[CTL_ATT_INT + i] = _clamp(ctl[CTL_ATT_INT + i] + (e_w[i] + gI * e_R[i]) * dt_s, att_lim)
    Jw = (Jx * w[0], Jy * w[1], Jz * w[2])
    gyro = (w[1] * Jw[2] - w[2] * Jw[1], w[2] * Jw[0] - w[0] * Jw[2], w[0] * Jw[1] - w[1] * Jw[0])
    wx = (w[1] * w_db[2] - w[2] * w_db[1], w[2] * w_db[0] - w[0] * w_db[2], w[0] * w_db[1] - w[1] * w_db[0])
    ff = (Jx * (wx[0] - rd[0]), Jy * (wx[1] - rd[1]), Jz * (wx[2] - rd[2]))
    kR, kw, kI = ctl[CTL_KR], ctl[CTL_KW], ctl[CTL_KI_ATT]
    for i in range(3):
        U[3 + i] = gyro[i] - kR * e_R[i] - kw * e_w[i] - kI * ctl[CTL_ATT_INT + i] - ff[i] + tau_ff[i]

"""The allocation with selective mapping (thesis Prop. 1, (2.12), (2.15), (2.17)) as a kernel.

The specification is :meth:`link_firmware_sim.allocation.Allocator.allocate`'s numpy path (with
the functions of :mod:`link_firmware_sim.allocation.mapping` it runs); the kernel computes the same
numbers with plain loops over scalars (``tests/unit/test_fast_paths.py``). The allocator's thresholds,
null vector and modulation state are one array (``ALLOC_*`` of :mod:`.layouts`).
"""

from __future__ import annotations

import math

import numpy as np

from companion.kernels.jit import jit

from .layouts import (ALLOC_EPS0, ALLOC_EPS1, ALLOC_FAILED, ALLOC_NU, ALLOC_SCALE_TO_LIMIT, ALLOC_SELECTIVE, ALLOC_TEST,
                      ALLOC_TEST_WRENCH, ALLOC_TMAX, ALLOC_TOL, ALLOC_XI_PRE)

__all__ = ["ALLOC_META", "allocate_kernel"]


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
    """``allocation.mapping._modulate_side``: the exact solution of (2.15) for one side, within ``tmax``."""
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
    """``allocation.mapping._least_within_margin`` (the same candidates in the same order)."""
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
def _rows_times(R, V, o, out):
    """``out[o:o + 4] = R V`` (``R``: (4, 6))."""
    for i in range(4):
        s = 0.0
        for k in range(6):
            s += R[i, k] * V[k]
        out[o + i] = s


@jit
def allocate_kernel(U_in, keep, alloc, out, meta):
    """``Allocator.allocate`` of the wrench ``U_in`` (6,) with ``alloc = (B_pinv, reduced_by_side,
    state)``: ``B^+`` (8, 6), each side's rows of the single-rotor reduced pseudo-inverses (2, 4, 4,
    6) and the allocator's state (``ALLOC_*``: thresholds, null vector, ``xi''_pre``, updated).
    ``out`` (5, 8) gets the rows command, lambda_o, lambda_alpha, lambda_beta, lambda_gamma;
    ``meta`` (:data:`ALLOC_META`) = (e_r, e_l, near_r, near_l, saturated, scale, the wrench
    allocated (6)); ``keep``: the wrench ``allocation.scaled_to_limit`` keeps whole (zeros: none)."""
    B_pinv, reduced_by_side, state = alloc
    eps0, eps1, tmax, tol = state[ALLOC_EPS0], state[ALLOC_EPS1], state[ALLOC_TMAX], state[ALLOC_TOL]
    selective, scale_to_limit = state[ALLOC_SELECTIVE] != 0.0, state[ALLOC_SCALE_TO_LIMIT] != 0.0
    nu = state[ALLOC_NU:ALLOC_NU + 4]
    # a rotor left out as failed (Allocator.remove_rotor): its side fs runs the rows R of B^+_{\j},
    # the others produce the wrench less its test thrust's
    failed = int(state[ALLOC_FAILED])
    fs = failed // 4 if failed >= 0 else -1
    R = reduced_by_side[max(fs, 0), max(failed, 0) % 4]
    U = np.empty(6)
    for k in range(6):
        U[k] = U_in[k] - (state[ALLOC_TEST_WRENCH + k] if fs >= 0 else 0.0)
    lo = out[1]
    _pinv_times(B_pinv, U, lo)
    scale = 1.0
    xi_limit = np.inf
    if scale_to_limit:  # allocation.mapping.scaled_to_limit
        xi_limit = tmax
        mn_r, mx_r = _side_range(lo, nu, 0)
        mn_l, mx_l = _side_range(lo, nu, 4)
        if fs < 0 and max(mx_r - mn_r, mx_l - mn_l) > 2.0 * tmax:  # (with a rotor out: clipped)
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
        if fs >= 0:  # the removed rotor's side without it, the rotor at its test thrust
            _rows_times(R, U, 4 * fs, out[3])
            _rows_times(R, U, 4 * fs, out[4])
            out[3, failed] = state[ALLOC_TEST]
            out[4, failed] = state[ALLOC_TEST]
            meta[fs] = 0.0
            meta[2 + fs] = failed
    else:
        for side in range(2):
            o = 4 * side
            if side == fs:  # the removed rotor faded out of its side for good (no null space left)
                state[ALLOC_XI_PRE + side] = 0.0
                for i in range(4):
                    out[3, o + i] = out[2, o + i]
                _rows_times(R, U, o, out[4])
                out[4, failed] = state[ALLOC_TEST]
                meta[2 + side] = failed
                meta[side] = 0.0
                continue
            xi2 = _modulate_side(b[o:o + 4], state[ALLOC_XI_PRE + side], eps1, xi_limit, tol)  # (2.15)
            state[ALLOC_XI_PRE + side] = xi2
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
                if scale_to_limit and over:  # allocation.mapping._fade_within_limit
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

"""The rotor and reversible-ESC model's compiled kernels: :class:`sitl.plant.rotor.RotorBank`'s
numpy code is their specification (what runs without numba, and what ``tests/unit/test_fast_paths.py``
compares them with through reversals, stops and restarts).

A leaf: it imports numpy and the project's jit switch only.
"""

from __future__ import annotations

import numpy as np

from companion.kernels.jit import jit

__all__ = ["step_kernel", "set_command_kernel", "relax_kernel"]


@jit
def step_kernel(thrust, command, state, params):
    """:meth:`sitl.plant.rotor.RotorBank.step` (not steady) rotor by rotor, from the thrusts and the
    clipped commands [N]: ``state`` the bank's arrays ``(spinning, direction, restarting,
    restart_left_s, out_sign, zero_crossings)``, updated in place; ``params`` ``(min_thrust_n,
    restart_dwell_s, esc_epsilon_n, decay, dt_s)``. Returns the new thrusts as a new array."""
    spinning, direction, restarting, restart_left, out_sign, zero_crossings = state
    min_thrust, dwell, eps, decay, dt_s = params
    new = np.empty_like(thrust)
    for i in range(len(thrust)):
        c = command[i]
        if min_thrust > 0.0 and not abs(c) >= min_thrust:
            c = 0.0
        was_spinning = spinning[i]
        keep = was_spinning and c * direction[i] > 0.0
        target = c if keep else 0.0
        wanted = (not was_spinning) and c != 0.0
        starting = wanted and not restarting[i]
        if starting:
            restart_left[i] = dwell
        now_restarting = wanted and (restarting[i] or starting)
        ready = now_restarting and restart_left[i] <= 0.0
        if now_restarting and not ready:
            restart_left[i] -= dt_s
        restarting[i] = now_restarting and not ready
        if ready:
            spinning[i] = True
            direction[i] = np.sign(c)
            target = c
        lam = target + (thrust[i] - target) * decay
        outside = abs(lam) > eps
        if spinning[i] and not keep and not ready and not outside:  # spun down into the dead band: stopped
            spinning[i] = False
            direction[i] = 0.0
        sgn = np.sign(lam)
        if outside:
            if out_sign[i] != 0.0 and sgn != out_sign[i]:
                zero_crossings[i] += 1
            out_sign[i] = sgn
        new[i] = lam
    return new


@jit
def set_command_kernel(command, limit, out, spinning, direction, out_sign, margin):
    """:meth:`sitl.plant.rotor.RotorBank.set_command`: ``out`` <- the command clipped to ``+-limit`` (NaN stays
    NaN, as ``np.clip``); returns whether the bank is steady (every rotor spinning, tracking a
    command of its own sign of at least ``margin``, its last thrust sign its direction) and the
    largest clipped command magnitude (NaN if a command is NaN, as ``max(cmd.max(), -cmd.min())``)."""
    steady = True
    peak = 0.0 if len(command) else -np.inf
    nan = False
    for i in range(len(command)):
        c = command[i]
        if c < -limit:
            c = -limit
        elif c > limit:
            c = limit
        out[i] = c
        if c != c:
            nan = True
        elif abs(c) > peak:
            peak = abs(c)
        if not (spinning[i] and c * direction[i] >= margin and out_sign[i] == direction[i]):
            steady = False
    return steady, (np.nan if nan else peak)


@jit
def relax_kernel(command, thrust, decay):
    """The steady step of :meth:`sitl.plant.rotor.RotorBank.step`: ``command + (thrust - command) decay``."""
    new = np.empty_like(thrust)
    for i in range(len(thrust)):
        new[i] = command[i] + (thrust[i] - command[i]) * decay
    return new

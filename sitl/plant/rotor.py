"""Bidirectional rotor and reversible-ESC model (thesis sec. 2.4.2).

Each rotor's thrust ``lambda`` follows its command ``lambda_d`` with first-order dynamics,
except when the command asks it to reverse: a sensorless BLDC/ESC cannot drive the motor
through zero speed, so the rotor first spins down to (near) zero thrust and only then spins
up the other way (the "ESC-induced singularity"). The thesis models it as::

    dlambda/dt = k (0 - lambda)          if lambda_d lambda < 0 and |lambda| > eps
                 k (lambda_d - lambda)   otherwise

That is this model with its two extra parameters at zero (the default). They add what the
thesis's text gives as the cause (back-EMF sensing fails near zero speed; the ESC needs a
start-up "bootstrapping"), seen as the hesitation of Fig. 2-4:

* ``min_thrust_n``: the ESC cannot sustain a speed below this thrust magnitude; a smaller
  command stops the motor (it spins down to zero);
* ``restart_dwell_s``: a stopped motor asked to spin (either direction) stays at zero for
  this long before it spins up.

Per rotor: *spinning* in a direction, it tracks commands of that sign (``|command| >=
min_thrust_n``) and spins down towards zero for anything else; once below ``esc_epsilon_n``
it is *stopped*; a stopped rotor asked to spin goes through the restart dwell, then spins up
in the commanded direction. Each step integrates the first-order law exactly (``lambda``
relaxes exponentially towards its current target). Commands are clipped to
``+-thrust_max_n``; thrust sign changes are counted, and per link (``rotors_per_link``) the
time with a rotor commanded at the limit (``limit_s``: the firmware's allocation at the edge of
what the link can do, :func:`link_firmware_sim.allocation.scaled_to_limit`). The MuJoCo
harness feeds ``thrust_n`` to the rotor actuators.

The numpy code of :meth:`RotorBank.step` is the specification; with numba installed the bank steps
by :func:`sitl.kernels.rotor.step_kernel`, the same per-rotor logic compiled (``tests/unit/test_fast_paths.py``
checks it against the numpy code through reversals, stops and restarts).
"""

from __future__ import annotations

import math
import numpy as np

from companion.kernels.jit import ENABLED as _COMPILED_DEFAULT
from companion.skeleton.rotors import RotorParams
from sitl.kernels.rotor import relax_kernel, set_command_kernel, step_kernel

__all__ = ["RotorParams", "RotorBank", "warm_up"]


class RotorBank:
    """All rotors of a skeleton (any count), stepped together at the physics rate."""

    def __init__(self, n_rotors: int, params: RotorParams = RotorParams(), *, compiled: bool | None = None,
                 rotors_per_link: int | None = None):
        self.params = params
        per = rotors_per_link or n_rotors
        if n_rotors % per:
            raise ValueError(f"{n_rotors} rotors are not links of {per}")
        self._per_link = per
        #: per link: simulated seconds with some rotor commanded at +-thrust_max_n
        self.limit_s = np.zeros(n_rotors // per)
        self._at_limit: np.ndarray | None = None
        self._compiled = _COMPILED_DEFAULT if compiled is None else bool(compiled)
        self.thrust_n = np.zeros(n_rotors)
        self.command_n = np.zeros(n_rotors)
        self.zero_crossings = np.zeros(n_rotors, dtype=np.int64)
        self._spinning = np.zeros(n_rotors, dtype=bool)
        self._direction = np.zeros(n_rotors)  # +1 / -1 while spinning
        self._restarting = np.zeros(n_rotors, dtype=bool)
        self._restart_left_s = np.zeros(n_rotors)
        self._out_sign = np.zeros(n_rotors)  # sign of the last thrust outside the dead band
        self._decay = {}
        self._steady = False

    def set_command(self, command_n: np.ndarray) -> None:
        """Commanded thrusts [N]; clipped to the thrust limit."""
        limit = self.params.thrust_max_n
        if self._compiled:
            self._steady, peak = set_command_kernel(np.asarray(command_n, dtype=float), limit, self.command_n,
                                                     self._spinning, self._direction, self._out_sign,
                                                     max(self.params.min_thrust_n, 1e-12))
            self._count_limit(limit, peak)
            return
        np.clip(np.asarray(command_n, dtype=float), -limit, limit, out=self.command_n)
        self._count_limit(limit)
        # Steady: every rotor spins and tracks a sustainable command of its own sign, so a
        # step is pure first-order relaxation (no stop, restart or sign change can happen).
        cmd = self.command_n
        self._steady = bool(
            self._spinning.all()
            and np.all(cmd * self._direction >= max(self.params.min_thrust_n, 1e-12))
            and np.array_equal(self._out_sign, self._direction)
        )

    def _count_limit(self, limit: float, peak: float | None = None) -> None:
        """Which links have a rotor commanded at the limit (``peak``: the largest command magnitude,
        NaN if a command is NaN, when the caller has it)."""
        cmd = self.command_n
        edge = limit * (1.0 - 1e-6)  # a command scaled onto the limit, to rounding (and float32 on the wire)
        if peak is None:
            peak = max(cmd.max(), -cmd.min())  # (NaN if a command is)
        if peak >= edge:
            self._at_limit = (np.abs(cmd) >= edge).reshape(-1, self._per_link).any(axis=1)
        else:
            self._at_limit = None

    def prime(self, thrust_n: np.ndarray) -> None:
        """Start with every rotor already spinning at ``thrust_n`` (an in-air start)."""
        self.set_command(thrust_n)
        self.thrust_n = self.command_n.copy()
        self._spinning = np.abs(self.thrust_n) > self.params.esc_epsilon_n
        self._direction = np.where(self._spinning, np.sign(self.thrust_n), 0.0)
        self._out_sign = self._direction.copy()

    def _decay_factor(self, dt_s: float) -> float:
        decay = self._decay.get(dt_s)
        if decay is None:
            decay = self._decay[dt_s] = math.exp(-dt_s / self.params.time_constant_s)
        return decay

    def step(self, dt_s: float) -> np.ndarray:
        """Advance every rotor by ``dt_s`` and return the thrusts [N]."""
        if self._at_limit is not None:
            self.limit_s[self._at_limit] += dt_s
        if self._steady:
            cmd = self.command_n
            if self._compiled:
                self.thrust_n = relax_kernel(cmd, self.thrust_n, self._decay_factor(dt_s))
            else:
                self.thrust_n = cmd + (self.thrust_n - cmd) * self._decay_factor(dt_s)
            return self.thrust_n
        p = self.params
        if self._compiled:
            state = (self._spinning, self._direction, self._restarting, self._restart_left_s, self._out_sign,
                     self.zero_crossings)
            params = (float(p.min_thrust_n), float(p.restart_dwell_s), float(p.esc_epsilon_n),
                      self._decay_factor(dt_s), float(dt_s))
            self.thrust_n = step_kernel(self.thrust_n, self.command_n, state, params)
            return self.thrust_n
        lam = self.thrust_n
        cmd = self.command_n
        if p.min_thrust_n > 0.0:
            cmd = np.where(np.abs(cmd) >= p.min_thrust_n, cmd, 0.0)
        spinning = self._spinning
        # Spinning rotors track commands of their own sign; anything else spins them down.
        keep = spinning & (cmd * self._direction > 0.0)
        target = np.where(keep, cmd, 0.0)
        # Stopped rotors asked to spin go through the restart, then spin up that way.
        wanted = ~spinning & (cmd != 0.0)
        starting = wanted & ~self._restarting
        self._restart_left_s[starting] = p.restart_dwell_s
        restarting = wanted & (self._restarting | starting)  # a restart no longer wanted is dropped
        ready = restarting & (self._restart_left_s <= 0.0)
        self._restart_left_s[restarting & ~ready] -= dt_s
        self._restarting = restarting & ~ready
        if ready.any():
            spinning[ready] = True
            self._direction[ready] = np.sign(cmd[ready])
            target = np.where(ready, cmd, target)
        new = target + (lam - target) * self._decay_factor(dt_s)
        eps = p.esc_epsilon_n
        outside = np.abs(new) > eps
        # A rotor spinning down that reaches the dead band has stopped.
        stopped = spinning & ~keep & ~ready & ~outside
        spinning[stopped] = False
        self._direction[stopped] = 0.0
        new_sign = np.sign(new)
        self.zero_crossings += outside & (self._out_sign != 0.0) & (new_sign != self._out_sign)
        self._out_sign = np.where(outside, new_sign, self._out_sign)
        self.thrust_n = new
        return new


def warm_up() -> None:
    """Load (or compile) the bank's kernels through the paths :meth:`RotorBank.step` calls them by:
    a run's first physics tick then costs no more than any other (without numba: nothing)."""
    if not _COMPILED_DEFAULT:
        return
    bank = RotorBank(8, compiled=True)
    bank.set_command(np.full(8, -1.0))  # stopped rotors asked to spin: the full step
    bank.step(0.001)
    bank.prime(np.ones(8))  # spinning, tracking their commands: the steady step
    bank.set_command(np.ones(8))
    bank.step(0.001)

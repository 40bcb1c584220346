"""Motor failures seen in the ESCs' telemetry, as PX4's failure detector sees them (``FD_ACT_EN``),
and left out of the allocation, as its control allocator does with ``CA_FAILURE_MODE = 1``.

Each tick the ESCs report what each rotor runs at (on a Pixhawk: ESC telemetry, rpm turned into
thrust; in SITL: the thrust the motor applies, which an injected ``motor off`` makes zero). A rotor
commanded at least :data:`MIN_COMMAND_N` whose ESC reports it under :data:`STOPPED_N` for
:data:`TIMEOUT_S` without a break has failed: the detector names it once. A gap in the telemetry
(none for :data:`MAX_GAP_S`) starts every timer again. What the firmware then does with it (the
eight-rotor ODAR link flies on seven: :meth:`~.allocation.Allocator.remove_rotor`) is
:meth:`~.firmware.LinkFirmware.on_esc_telemetry`'s.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MIN_COMMAND_N", "STOPPED_N", "TIMEOUT_S", "MAX_GAP_S", "MotorFailureDetector"]

#: a rotor commanded at least this much [N] (in either direction) is expected to turn
MIN_COMMAND_N = 0.5
#: an ESC reporting less than this [N] has its rotor stopped
STOPPED_N = 0.05
#: stopped this long while commanded [s]: failed (PX4's FD_ACT_MOT_TOUT)
TIMEOUT_S = 0.1
#: telemetry this far apart [s]: a gap, the timers start again
MAX_GAP_S = 0.02


class MotorFailureDetector:
    """The failed rotors of one link (0-based, :attr:`failed`), from its ESC telemetry."""

    def __init__(self, n_rotors: int = 8):
        self.n_rotors = n_rotors
        self._since = np.full(n_rotors, math.nan)  # when each rotor started not to follow [s]
        self._last_s = -math.inf
        #: the rotors found failed, in the order found
        self.failed: list[int] = []

    def update(self, t_s: float, command_n, reported_n) -> list[int]:
        """The tick at ``t_s``: the thrusts commanded and the ESCs' report [N], (n_rotors,) each.
        Returns the rotors newly found failed (each once)."""
        command_n, reported_n = np.asarray(command_n, dtype=float), np.asarray(reported_n, dtype=float)
        if t_s - self._last_s > MAX_GAP_S:
            self._since[:] = math.nan
        self._last_s = t_s
        lagging = (np.abs(command_n) >= MIN_COMMAND_N) & (np.abs(reported_n) < STOPPED_N)
        self._since[~lagging] = math.nan
        start = lagging & np.isnan(self._since)
        self._since[start] = t_s
        new = [int(i) for i in np.flatnonzero(lagging & (t_s - self._since >= TIMEOUT_S - 1e-9))
               if int(i) not in self.failed]
        self.failed.extend(new)
        return new

    def reset(self) -> None:
        """Forget every failure and timer (the firmware disarmed)."""
        self._since[:] = math.nan
        self._last_s = -math.inf
        self.failed.clear()

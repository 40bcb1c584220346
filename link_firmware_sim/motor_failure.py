"""Motor failures seen in the ESCs' telemetry, as PX4's failure detector sees them (``FD_ACT_EN``),
and left out of the allocation, as its control allocator does with ``CA_FAILURE_MODE = 1``.

Each tick the ESCs report what each rotor runs at (on a Pixhawk: ESC telemetry, rpm turned into
thrust; in SITL: the thrust the motor applies, which an injected ``motor off`` makes zero). A rotor
commanded at least :data:`MIN_COMMAND_N` whose ESC reports it under :data:`STOPPED_N` for
:data:`TIMEOUT_S` without a break has failed: the detector names it once. A gap in the telemetry
(none for :data:`MAX_GAP_S`) starts every timer again. A failed rotor commanded at least
:data:`MIN_COMMAND_N` (the firmware keeps it at :data:`TEST_THRUST_N`) whose ESC reports it turning
(at least half its command) for :data:`RECOVER_S` works again: the detector names it once more.
What the firmware does with either is :meth:`MotorFailureDetector.answer`: the eight-rotor ODAR
link flies on seven (:meth:`~.allocation.Allocator.remove_rotor`) until the rotor turns again.
"""

from __future__ import annotations

import math

import numpy as np

from .events import StatusEvent

__all__ = ["MIN_COMMAND_N", "STOPPED_N", "TIMEOUT_S", "MAX_GAP_S", "RECOVER_S", "TEST_THRUST_N",
           "MotorFailureDetector"]

#: a rotor commanded at least this much [N] (in either direction) is expected to turn
MIN_COMMAND_N = 0.5
#: an ESC reporting less than this [N] has its rotor stopped
STOPPED_N = 0.05
#: stopped this long while commanded [s]: failed (PX4's FD_ACT_MOT_TOUT)
TIMEOUT_S = 0.1
#: telemetry this far apart [s]: a gap, the timers start again
MAX_GAP_S = 0.02
#: a failed rotor turning again this long [s]: it works
RECOVER_S = 0.5
#: what a failed rotor is commanded [N], so that its telemetry tells whether it turns again
TEST_THRUST_N = 0.8


class MotorFailureDetector:
    """The failed rotors of one link (0-based, :attr:`failed`), from its ESC telemetry."""

    def __init__(self, n_rotors: int = 8):
        self.n_rotors = n_rotors
        # since when each rotor has not followed its command (working rotors) or has (failed ones) [s]
        self._since = np.full(n_rotors, math.nan)
        self._last_s = -math.inf
        #: the rotors failed now, in the order found
        self.failed: list[int] = []

    def update(self, t_s: float, command_n, reported_n) -> tuple[list[int], list[int]]:
        """The tick at ``t_s``: the thrusts commanded and the ESCs' report [N], (n_rotors,) each.
        Returns the rotors newly found failed and those found working again (each once)."""
        command_n, reported_n = np.asarray(command_n, dtype=float), np.asarray(reported_n, dtype=float)
        if t_s - self._last_s > MAX_GAP_S:
            self._since[:] = math.nan
        self._last_s = t_s
        commanded = np.abs(command_n) >= MIN_COMMAND_N
        stopped = commanded & (np.abs(reported_n) < STOPPED_N)
        turning = commanded & (np.abs(reported_n) >= 0.5 * np.abs(command_n))
        failed = np.zeros(self.n_rotors, dtype=bool)
        failed[self.failed] = True
        # the working rotors' timer runs while stopped, the failed ones' while turning
        watch = np.where(failed, turning, stopped)
        self._since[~watch] = math.nan
        self._since[watch & np.isnan(self._since)] = t_s
        held = t_s - self._since
        new = [int(i) for i in np.flatnonzero(~failed & watch & (held >= TIMEOUT_S - 1e-9))]
        back = [int(i) for i in np.flatnonzero(failed & watch & (held >= RECOVER_S - 1e-9))]
        self._since[new + back] = math.nan
        self.failed = [i for i in self.failed if i not in back] + new
        return new, back

    def reset(self) -> None:
        """Forget every failure and timer (the firmware disarmed)."""
        self._since[:] = math.nan
        self._last_s = -math.inf
        self.failed.clear()

    def answer(self, t_s: float, command_n, reported_n, allocator, remove: bool) -> list[StatusEvent]:
        """The firmware's answer to the tick's telemetry (:meth:`update`), as STATUSTEXT events: a
        rotor found failed is left out of ``allocator`` (a
        :class:`~.allocation.Allocator`) with ``remove`` (SKL_CA_FAIL, as PX4's
        ``CA_FAILURE_MODE = 1``; one rotor at most), commanded :data:`TEST_THRUST_N`, else only
        reported; one found working again rejoins."""
        failed, back = self.update(t_s, command_n, reported_n)
        events = []
        for rotor in failed:
            if not remove:
                text = f"Motor {rotor + 1} failed: SKL_CA_FAIL off, still used"
            elif allocator.remove_rotor(rotor, TEST_THRUST_N):
                text = f"Motor {rotor + 1} failed: flying on the other seven"
            else:
                text = f"Motor {rotor + 1} failed: not handled, {allocator.removed_rotor + 1} out"
            events.append(StatusEvent("reset", text))
        for rotor in back:
            if allocator.removed_rotor == rotor:
                allocator.restore_rotors()
            events.append(StatusEvent("recovered", f"Motor {rotor + 1} turns again: flying on all eight"))
        return events

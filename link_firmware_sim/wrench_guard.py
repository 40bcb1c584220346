"""A wrench the controller returns that is not finite is refused, never allocated.

Every input that could make one is validated where it is decoded (commands, sensor samples,
targets, corrections), so only a numerical failure inside the firmware reaches this guard. The
firmware then holds the last finite thrust commands for that tick, resets the controller (its
integrals are where such a failure stays) and reports it as a STATUSTEXT: at the first refusal of
an episode and then at most once per :data:`REPORT_EVERY_S` while refusals go on. The tick and
the process go on either way.
"""

from __future__ import annotations

import math

import numpy as np

from .events import StatusEvent

__all__ = ["REPORT_EVERY_S", "WrenchGuard"]

#: while wrenches keep being refused, a STATUSTEXT at most this often [s]
REPORT_EVERY_S = 1.0


class WrenchGuard:
    """The last finite thrust commands (:attr:`command`), the refusals counted, and whether the
    newest tick's wrench was refused (:attr:`holding`: its commands are the held ones)."""

    def __init__(self, n_rotors: int = 8):
        self.command = np.zeros(n_rotors)  # [N], the newest finite tick's
        self.refused = 0
        self.holding = False
        self._reported_s = -math.inf

    def passed(self, command: np.ndarray) -> None:
        """A finite wrench's thrust commands (copied: the caller may reuse its buffer)."""
        self.command[:] = command
        self.holding = False

    def refuse(self, t_s: float) -> tuple[np.ndarray, list[StatusEvent]]:
        """A refused wrench at ``t_s``: the commands to hold (a copy of the last finite ones) and
        the event to report, if one is due."""
        self.refused += 1
        report = not self.holding or t_s - self._reported_s >= REPORT_EVERY_S
        self.holding = True
        events = []
        if report:
            self._reported_s = t_s
            events.append(StatusEvent("fault", f"Wrench not finite: command held ({self.refused})"))
        return self.command.copy(), events

    def report(self) -> dict:
        """What a vehicle writes at the end (``link<i>_ports.json``)."""
        return {"refused": self.refused, "holding": self.holding}

"""Is a link's state stamp plausible? Replays, stamps from the future, reboots (pure).

Every state a link sends carries its EKF time on the link's clock. The companion's cycle clock
is the newest *accepted* stamp, so one frame stamped 1000 s ahead must not be accepted: it would
move the cycle clock and every later (honest) state would look 1000 s old. :class:`StampGate`
keeps, per link, the last accepted stamp and when it arrived (``now_s``, the caller's monotonic
clock) and judges each new stamp ``t``:

* ``t <= last``: a replay (or a reordered datagram): rejected;
* ``t - last > clock_rate_max * (now - arrived) + margin``: further ahead than the link's clock
  can have run since the last accepted state (``clock_rate_max`` bounds the link's clock rate
  against the caller's: 1 +- 1e-4 for crystals, the pace of a SITL run; ``margin`` covers the
  transit delay of the last accepted frame): rejected;
* otherwise accepted.

A link that reboots restarts its clock near zero, and a gate that accepted a forged stamp
within the window would reject the honest stream: both look like a stream rejected for a while.
So once nothing from the link has been accepted for ``reboot_silence_s``, rejected stamps are
watched for a new clock: ``reboot_frames`` consecutive stamps that are each plausible against
the previous one (the same rule) re-base the gate on that clock (:attr:`StampVerdict.REBASED`,
accepted). A forger cannot re-base a link that keeps streaming: its accepted states keep the
silence from ever starting. With MAVLink signing required the forger cannot send states at all.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from .configfile import require_positive

__all__ = ["StampWindow", "StampVerdict", "StampGate"]


@dataclass(frozen=True)
class StampWindow:
    """The gate's parameters (see the module docstring)."""

    margin_s: float = 0.25
    clock_rate_max: float = 1.1
    reboot_silence_s: float = 1.0
    reboot_frames: int = 10

    def __post_init__(self) -> None:
        require_positive(self, "margin_s", "clock_rate_max", "reboot_silence_s", "reboot_frames")

    def plausible(self, t_us: int, after_us: int, elapsed_s: float) -> bool:
        """``t_us`` may follow ``after_us`` when ``elapsed_s`` have passed between their arrivals."""
        return 0 < t_us - after_us <= (self.clock_rate_max * max(elapsed_s, 0.0) + self.margin_s) * 1e6


class StampVerdict(Enum):
    ACCEPTED = "accepted"
    REBASED = "rebased"  # accepted: the first stamp of a new clock (a reboot)
    REPLAY = "replay"  # not newer than the last accepted
    FUTURE = "future"  # further ahead than the clock can have run


class StampGate:
    """One link's stamp gate (see the module docstring)."""

    def __init__(self, window: StampWindow = StampWindow()):
        self.window = window
        self.last_us: int | None = None
        self.last_s = 0.0
        self._candidate: tuple[int, float, int] | None = None  # (stamp, arrival, consecutive count)

    def check(self, t_us: int, now_s: float) -> StampVerdict:
        t_us = int(t_us)
        if self.last_us is None:
            return self._accept(t_us, now_s, StampVerdict.ACCEPTED)
        if self.window.plausible(t_us, self.last_us, now_s - self.last_s):
            return self._accept(t_us, now_s, StampVerdict.ACCEPTED)
        verdict = StampVerdict.REPLAY if t_us <= self.last_us else StampVerdict.FUTURE
        if now_s - self.last_s < self.window.reboot_silence_s:
            self._candidate = None
            return verdict
        cand = self._candidate
        if cand is not None and self.window.plausible(t_us, cand[0], now_s - cand[1]):
            cand = (t_us, now_s, cand[2] + 1)
        else:
            cand = (t_us, now_s, 1)
        self._candidate = cand
        if cand[2] >= self.window.reboot_frames:
            return self._accept(t_us, now_s, StampVerdict.REBASED)
        return verdict

    def _accept(self, t_us: int, now_s: float, verdict: StampVerdict) -> StampVerdict:
        self.last_us, self.last_s, self._candidate = t_us, now_s, None
        return verdict

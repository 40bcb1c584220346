"""What the companion engine knows of each link (:class:`LinkTrack`), how long a link has been
carried (:class:`CarryClock`), and the rate-limited warnings about a link
(:class:`LinkWarnings`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..messages import LinkState
from ..plausibility import StampGate
from ..quantiles import Quantiles
from .silence import StreamLoss

__all__ = ["LAG_LIMIT_US", "OFF_BASE_LIMIT_US", "CarryClock", "LinkTrack", "LinkWarnings", "usec"]

log = logging.getLogger(__name__)

#: A link whose newest state is this far behind the step time, and that has sent nothing for as
#: long, is silent: not waited for, and not used.
LAG_LIMIT_US = 100_000
#: A link whose newest state is this far behind the cycle clock is on another clock (a Pixhawk
#: rebooted onto its boot clock), even if it keeps sending: not used, and no part of the clock.
OFF_BASE_LIMIT_US = 1_000_000


def usec(t_s: float) -> int:
    """``t_s`` seconds in whole microseconds (rounded)."""
    return int(round(t_s * 1e6))


@dataclass
class CarryClock:
    """How long a link has been carried (its rotors taken to be off), on the time base: the
    stretches so far and the one going on, and how many there were."""

    total_s: float = 0.0
    since_s: float | None = None
    stretches: int = 0

    @property
    def on(self) -> bool:
        return self.since_s is not None

    def switch(self, on: bool, t: float) -> float | None:
        """Start or end a stretch at ``t``; the length of the one that ended (``None``: none)."""
        if on and self.since_s is None:
            self.since_s = t
            self.stretches += 1
        elif not on and self.since_s is not None:
            ended, self.since_s = t - self.since_s, None
            self.total_s += ended
            return ended
        return None

    def seconds(self, t: float) -> float:
        """Carried so far, a stretch still going on included (to ``t``)."""
        return self.total_s + (t - self.since_s if self.since_s is not None else 0.0)


@dataclass
class LinkTrack:
    """What the engine knows of one link (``index`` in the chain, ``row`` in this engine)."""

    index: int
    row: int
    system_id: int
    state: LinkState | None = None
    flags: int = 0
    rejected: int = 0
    states: int = 0
    states_at_report: int = 0
    last_state_s: float | None = None
    arm_sent_s: float = -np.inf
    arm_tries: int = 0  # ARM commands since the link last reported armed
    armed_ack: bool = False
    #: it reported armed since its stream last broke off (a silence of ``carry_silence_s``, or a new
    #: clock: it may have powered off and on): disarmed after that, someone disarmed it (its pilot,
    #: a failsafe) while it kept streaming
    was_armed: bool = False
    disarm_logged: bool = False
    stream_sent_s: float = -np.inf
    stream_acked: bool = False
    correction_seq: int = -1
    #: every correction latency it reported [ms], in fixed memory
    latencies_ms: Quantiles = field(default_factory=Quantiles)
    latency_window_ms: list = field(default_factory=list)
    clock_samples_us: list = field(default_factory=list)
    gps_wait_logged: bool = False
    #: the link's clock + offset = the engine's time base (0 with ``time_base = "flight_controller"``)
    offset_us: int | None = None
    stamps: StampGate | None = None
    #: states rejected for their stamp: not newer than the last (replays), too far ahead
    replayed: int = 0
    future: int = 0
    reboots: int = 0
    gps_fault_steps: int = 0  # steps it took part in one way (its GPS flagged faulty)
    #: steps it was corrected along a neighbour left out (:mod:`.bridge`), though alone in the step
    bridged_steps: int = 0
    #: cycles this link took no part in, by reason (see :data:`~companion.engine.selection.EXCLUSION_REASONS`)
    excluded: dict = field(default_factory=dict)
    excluded_at_report: int = 0
    #: why it was left out of the last step ("" = used)
    status: str = ""
    readmit_cycles: int = 0
    #: it has been armed for ``carry_spinup_s`` (it has flown); since when it reports armed;
    #: carried: its rotors taken to be off (``carry_silence_s``, ``carry_spinup_s``)
    flown: bool = False
    armed_since_s: float | None = None
    disarmed_states: int = 0  # accepted states in a row that report it disarmed
    believed_armed: bool = False
    after_silence: bool = False
    stamp_rejected_s: float = -np.inf  # the last replayed or future state, on the time base
    carried: CarryClock = field(default_factory=CarryClock)
    #: how much of its state stream is lost on the way (its silence threshold grows with it)
    loss: StreamLoss | None = None

    def to_link_clock_us(self, t_us: int) -> int:
        return t_us - (self.offset_us or 0)

    def quiet(self, now_s: float, silence_s: float, clock_rate_max: float) -> bool:
        """Nothing accepted from it for ``silence_s`` of the time base, measured on the
        companion's own clock ``now_s`` (``silence_s / clock_rate_max``, the time base running at
        most that much faster): what no stamp, forged or not, can move."""
        return self.last_state_s is None or now_s - self.last_state_s >= silence_s / clock_rate_max


class LinkWarnings:
    """Warnings about a link, rate-limited per link and kind: the first, then at most one every 5 s
    of the caller's clock."""

    def __init__(self):
        self._logged_s: dict[tuple[int, str], float] = {}

    def warn(self, lk: LinkTrack, kind: str, now_s: float, fmt: str, *args) -> None:
        key = (lk.row, kind)
        if now_s - self._logged_s.get(key, -np.inf) >= 5.0:
            self._logged_s[key] = now_s
            log.warning("link %d: " + fmt, lk.index + 1, *args)

"""A link's clock over MAVLink's TIMESYNC, so that a stock autopilot reads this companion's stamps
(the pure core; :class:`~companion.daemon.CompanionDaemon` sends and receives the messages).

TIMESYNC carries two nanosecond stamps. A request has ``tc1 = 0`` and the sender's clock in
``ts1``; the answer echoes ``ts1`` and puts the answerer's clock in ``tc1``. The sender then has
its round trip (now less ``ts1``) and, taking the two legs as equal, the answerer's clock less its
own at the middle of the trip: ``tc1 - (ts1 + now) / 2``.

PX4 sends a request ten times a second on USB and on an onboard link and, once 500 answers with a round trip
under 10 ms have converged its estimate, stamps an external-vision ODOMETRY with the sender's
``time_usec`` plus that offset (until then: its arrival). This companion stamps the corrected pose
with the time of the autopilot's own state it corrected, on the autopilot's clock: to keep that
stamp as it is, it answers on the autopilot's clock too. It learns that clock from requests of its
own (:meth:`LinkTimesync.request`, :meth:`LinkTimesync.on_answer`): the median offset of the last
answers with a short round trip. Until it has enough of them it does not answer, and PX4 keeps
stamping on arrival.

Every stamp is an input to validate: an answer to no request of ours, or one whose round trip is
negative or too long, is counted and dropped; a request stamped far from the estimate, or a run
of answers far from it (the autopilot rebooted, its clock restarted), starts the estimate afresh
without answering on the old clock; requests are answered at a bounded rate.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

__all__ = ["LinkTimesync", "TimesyncConfig"]

_INT64_MAX = 2**63 - 1


@dataclass(frozen=True)
class TimesyncConfig:
    """How a companion synchronises with a link's clock (nanoseconds and seconds as named)."""

    #: longest round trip of an answer the estimate takes (PX4 takes 10 ms too)
    max_rtt_ns: int = 10_000_000
    #: answers the estimate is the median of
    window: int = 15
    #: answers needed before the companion answers the link's requests
    min_samples: int = 5
    #: an answer this far from the estimate is an outlier; ``restart_after`` of them in a row: a new clock
    max_deviation_ns: int = 100_000_000
    restart_after: int = 5
    #: request period while synchronising, and once synchronised or after ``outstanding`` requests
    #: unanswered in a row [s]
    period_s: float = 0.1
    period_synced_s: float = 1.0
    #: shortest interval between two answers to the link's requests [s] (PX4 asks at 10 Hz)
    min_answer_interval_s: float = 0.01
    #: our requests still awaiting an answer that are remembered
    outstanding: int = 32


@dataclass
class LinkTimesync:
    """One link's clock as this companion learns it over TIMESYNC; every method takes the
    companion's clock ``now_ns`` (monotonic nanoseconds)."""

    config: TimesyncConfig = field(default_factory=TimesyncConfig)
    #: counters: answers taken, refused (to no request of ours, a round trip out of bounds, an
    #: outlier), estimates restarted (a run of outliers, or a request stamped far from the estimate),
    #: the link's requests answered and not answered (not synchronised yet, or too soon after the last)
    counts: dict = field(default_factory=lambda: dict.fromkeys(
        ("taken", "unknown", "slow", "outlier", "restarts", "answered", "unsynced", "too_soon"), 0))

    def __post_init__(self):
        self._sent: deque[int] = deque(maxlen=self.config.outstanding)
        self._offsets: deque[int] = deque(maxlen=self.config.window)
        self._rtts: deque[int] = deque(maxlen=self.config.window)
        self._outliers = 0
        self._unanswered = 0  # our requests since the last answer taken
        self._since_ns: int | None = None  # our first request since the last (re)start
        self._next_request_ns: int | None = None
        self._last_answer_ns: int | None = None

    @property
    def synchronised(self) -> bool:
        return len(self._offsets) >= self.config.min_samples

    @property
    def offset_ns(self) -> int | None:
        """The link's clock less this companion's (the median of the last answers; ``None``: none yet)."""
        if not self._offsets:
            return None
        ordered = sorted(self._offsets)
        return ordered[len(ordered) // 2]

    @property
    def rtt_ns(self) -> int | None:
        """The median round trip of the answers in the estimate."""
        return sorted(self._rtts)[len(self._rtts) // 2] if self._rtts else None

    def request(self, now_ns: int) -> int | None:
        """The ``ts1`` of a request to send now (``tc1 = 0``), or ``None`` when none is due."""
        if self._next_request_ns is not None and now_ns < self._next_request_ns:
            return None
        # (quick while learning; a link that never answers, a simulated one, is asked once a second)
        quick = not self.synchronised and self._unanswered < self.config.outstanding
        period = self.config.period_s if quick else self.config.period_synced_s
        self._next_request_ns = now_ns + int(period * 1e9)
        self._sent.append(now_ns)
        self._unanswered += 1
        if self._since_ns is None:
            self._since_ns = now_ns
        return now_ns

    def on_answer(self, tc1_ns: int, ts1_ns: int, now_ns: int) -> bool:
        """An answer (``tc1 > 0``) received at ``now_ns``: ``True`` if the estimate took it."""
        cfg, counts = self.config, self.counts
        if not 0 < tc1_ns <= _INT64_MAX or ts1_ns not in self._sent:
            counts["unknown"] += 1  # to no request of ours (another sender's, a replay, a forgery), or no clock
            return False
        self._sent.remove(ts1_ns)
        rtt = now_ns - ts1_ns
        if not 0 <= rtt <= cfg.max_rtt_ns:
            counts["slow"] += 1
            return False
        offset = tc1_ns - (ts1_ns + now_ns) // 2
        estimate = self.offset_ns
        if estimate is not None and abs(offset - estimate) > cfg.max_deviation_ns:
            self._outliers += 1
            counts["outlier"] += 1
            if self._outliers < cfg.restart_after:
                return False
            self.restart(now_ns)  # the link's clock restarted (a reboot): learn it again
        self._outliers = self._unanswered = 0
        self._offsets.append(offset)
        self._rtts.append(rtt)
        counts["taken"] += 1
        if not self.synchronised and self._next_request_ns is not None:  # (quick again, if it had slowed)
            self._next_request_ns = min(self._next_request_ns, ts1_ns + int(cfg.period_s * 1e9))
        return True

    def answer(self, ts1_ns: int, now_ns: int) -> tuple[int, int] | None:
        """``(tc1, ts1)`` answering the link's request ``ts1_ns``: the link's own clock now, as
        estimated; ``None`` (counted) before the estimate is ready, too soon after the last answer,
        or when the request's own stamp (the link's clock when it asked) is far from the estimate:
        the link rebooted and its clock restarted, so the estimate starts afresh (answering on the
        old clock would feed its new timesync a wrong offset)."""
        if not self.synchronised:
            self.counts["unsynced"] += 1
            return None
        tc1 = now_ns + self.offset_ns
        if abs(tc1 - ts1_ns) > self.config.max_deviation_ns:
            self.restart(now_ns)
            return None
        interval = int(self.config.min_answer_interval_s * 1e9)
        if self._last_answer_ns is not None and 0 <= now_ns - self._last_answer_ns < interval:
            self.counts["too_soon"] += 1
            return None
        self._last_answer_ns = now_ns
        self.counts["answered"] += 1
        return tc1, ts1_ns

    def restart(self, now_ns: int) -> None:
        """Forget the estimate (the link's clock restarted) and ask again at once."""
        self._offsets.clear()
        self._rtts.clear()
        self._outliers = 0
        self._next_request_ns = now_ns
        self._since_ns = None
        self.counts["restarts"] += 1

    def waiting_s(self, now_ns: int) -> float:
        """Seconds since this companion began asking without being synchronised (0 when it is)."""
        if self.synchronised or self._since_ns is None:
            return 0.0
        return (now_ns - self._since_ns) * 1e-9

    def report(self) -> dict:
        """The counters, whether synchronised, and the estimate's offset and round trip [ms]."""
        offset, rtt = self.offset_ns, self.rtt_ns
        return {**self.counts, "synchronised": self.synchronised,
                "offset_ms": None if offset is None else offset * 1e-6, "rtt_ms": None if rtt is None else rtt * 1e-6}

"""How long a link must be unheard before the companion takes its rotors to be off, given how
lossy its state stream is.

On a clean wire a link unheard for ``carry_silence_s`` has lost power. On a lossy one, runs of
lost states that long happen by chance: with each state lost with probability p, independently,
a stream of f states per second starts a run of n or more lost states about f (1 - p) p^n times a
second. :class:`StreamLoss` estimates p from the gaps between the stamps of a link's accepted
states; :func:`silence_threshold_s` lengthens ``carry_silence_s`` (which lets through runs of
:data:`BASE_RUN` lost states) by one state period for each further lost state that a run must
reach to be expected no more than once in :data:`FALSE_CARRY_PERIOD_S`, up to
``carry_silence_max_s``: the cap bounds how late a dead link on a bad wire is carried, whatever
its stream or a forger's stamps did before. Its default is ``carry_silence_s``: a fixed silence,
since carrying a dead link late costs more than carrying a live one for a state period.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["BASE_RUN", "FALSE_CARRY_PERIOD_S", "LOSS_WINDOW_STATES", "StreamLoss", "silence_threshold_s"]

#: Lost states in a row that ``carry_silence_s`` lets through on its own (with a state period
#: to spare for the order in which the links' states arrive).
BASE_RUN = 1
#: A live link on a lossy wire is taken for dead (a run of lost states as long as its silence
#: threshold) no more often than once in this long on average [s].
FALSE_CARRY_PERIOD_S = 600.0
#: The loss estimate weighs the gaps of about the last this many expected states.
LOSS_WINDOW_STATES = 500


@dataclass
class StreamLoss:
    """The fraction of a link's states lost on the way, from the gaps between the stamps of the
    states accepted from it (each stamp expected ``period_us`` after the last): exponentially
    weighted over about :data:`LOSS_WINDOW_STATES` expected states. A gap of more than
    ``outage_states`` states is a silence (the link was down, or carried through it), not
    random loss, and is not counted; a new clock (:meth:`restart`) starts the gaps afresh."""

    period_us: float
    outage_states: int
    received: float = 0.0
    lost: float = 0.0
    last_us: int | None = None

    @classmethod
    def of_stream(cls, state_rate_hz: float, carry_silence_max_s: float) -> StreamLoss:
        """The estimate for a stream of ``state_rate_hz`` states per second whose gaps longer
        than ``carry_silence_max_s`` are silences."""
        return cls(1e6 / state_rate_hz, math.ceil(carry_silence_max_s * state_rate_hz))

    def restart(self) -> None:
        """The link's stamps start on a new clock (it rebooted): no gap to its last one."""
        self.last_us = None

    def on_stamp(self, stamp_us: int) -> None:
        """An accepted state stamped ``stamp_us`` (on the link's clock, newer than its last)."""
        last, self.last_us = self.last_us, stamp_us
        if last is None:
            return
        gap = round((stamp_us - last) / self.period_us)
        if gap < 1 or gap - 1 > self.outage_states:
            return
        keep = (1.0 - 1.0 / LOSS_WINDOW_STATES) ** gap
        self.received = self.received * keep + 1.0
        self.lost = self.lost * keep + (gap - 1)

    @property
    def fraction(self) -> float:
        """The estimated probability that a state is lost (0 before two states)."""
        total = self.received + self.lost
        return self.lost / total if total > 0.0 else 0.0


def silence_threshold_s(loss: float, carry_silence_s: float, carry_silence_max_s: float, state_rate_hz: float) -> float:
    """The silence after which a link whose stream loses ``loss`` of its states is taken to have
    lost power: ``carry_silence_s`` plus one state period per lost state beyond :data:`BASE_RUN`
    in the shortest run that a live link's stream of ``state_rate_hz`` states per second starts no
    more than once in :data:`FALSE_CARRY_PERIOD_S`; at most ``carry_silence_max_s`` (and never
    less than ``carry_silence_s``)."""
    if carry_silence_max_s <= carry_silence_s:  # fixed (the default)
        return carry_silence_s
    if not 0.0 < loss < 1.0:
        return carry_silence_s if loss <= 0.0 else carry_silence_max_s
    # f (1 - p) p^n <= 1 / T  <=>  n >= log(1 / (T f (1 - p))) / log(p)
    runs_per_period = FALSE_CARRY_PERIOD_S * state_rate_hz * (1.0 - loss)
    n = 0 if runs_per_period <= 1.0 else math.ceil(-math.log(runs_per_period) / math.log(loss) - 1e-9)
    return min(carry_silence_s + max(0, n - BASE_RUN) / state_rate_hz, carry_silence_max_s)

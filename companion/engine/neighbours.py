"""Neighbour camera measurements waiting for the step that applies them.

A camera on one link seeing its neighbour's marker gives a relative pose
(:class:`~companion.estimation.neighbour.NeighbourMeasurement`), taken at its capture time and
delivered some tens of milliseconds later. :class:`NeighbourQueue` keeps each one, on this
engine's rows, until the next step whose segment holds both links: the step applies it before its
constraint application (:func:`~companion.corrections.compute_corrections`), comparing it with
the links' states taken back to its capture (its ``age_s``). One older than :data:`MAX_AGE_S` at
the step is dropped, as one between links of different segments is (a link left out, a cut joint).
Everything is counted (:meth:`NeighbourQueue.counts`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..estimation.neighbour import NeighbourMeasurement

__all__ = ["MAX_AGE_S", "NeighbourQueue"]

#: a measurement captured longer than this before the step is dropped [s]: two steps at 20 Hz
#: plus a camera's latency
MAX_AGE_S = 0.25


class NeighbourQueue:
    """The measurements received (on this engine's rows, each with its capture time on the
    engine's time base), not yet applied; and per pair of links the newest one a step accepted,
    which later steps apply again while it is at most ``hold_s`` old and no newer one for the pair
    has come (0: each measurement once).

    The step is memoryless: it starts from the links' EKF states, which do not take the
    corrections in (they are added to the EKF's output), so a measurement a step applied says
    nothing to the next one. Applying it again is then no double counting: each step fuses the
    states of its instant with the newest relative pose of each pair, taken back to its capture
    by its age. Without it, a camera slower than the step corrects only the steps its frames
    fall into."""

    def __init__(self, max_age_s: float = MAX_AGE_S, hold_s: float = 0.0):
        self.max_age_s = float(max_age_s)
        self.hold_s = min(float(hold_s), self.max_age_s)
        self._pending: list[tuple[float, NeighbourMeasurement]] = []
        #: (observer, observed) -> (capture time, measurement) of the newest accepted
        self._held: dict[tuple[int, int], tuple[float, NeighbourMeasurement]] = {}
        #: what the last :meth:`take` gave out, in order: (pair, capture time, measurement, fresh)
        self._given: list[tuple[tuple[int, int], float, NeighbourMeasurement, bool]] = []
        self._counts = {"received": 0, "applied": 0, "not_applied": 0, "too_old": 0, "left_out": 0,
                        "reapplied": 0}

    def add(self, t_capture_s: float, measurement: NeighbourMeasurement) -> None:
        """A measurement between two of this engine's rows, captured at ``t_capture_s``."""
        self._counts["received"] += 1
        self._pending.append((float(t_capture_s), measurement))

    def refuse(self) -> None:
        """A measurement the engine cannot apply (not between two of its rows, or a step that
        takes none): counted as received and left out."""
        self._counts["received"] += 1
        self._counts["left_out"] += 1

    def take(self, segments, t_s: float) -> list[list[NeighbourMeasurement]]:
        """For each of ``segments`` (rows, in chain order) the measurements between two of its
        rows, numbered from its first (all of them leave the queue), then the held ones of the
        pairs that got none (within ``hold_s`` of ``t_s``); those captured more than
        :attr:`max_age_s` before ``t_s``, and those no segment holds, are dropped and counted."""
        out: list[list[NeighbourMeasurement]] = [[] for _ in segments]
        given: list[list[tuple]] = [[] for _ in segments]
        fresh_pairs = set()
        for t_capture, m in self._pending:
            if t_s - t_capture > self.max_age_s:
                self._counts["too_old"] += 1
                continue
            k = self._segment(segments, m)
            if k is None:
                self._counts["left_out"] += 1
                continue
            pair = (int(m.observer), int(m.observed))
            fresh_pairs.add(pair)
            out[k].append(replace(m.numbered_from(segments[k][0]), age_s=max(t_s - t_capture, 0.0)))
            given[k].append((pair, t_capture, m, True))
        self._pending.clear()
        for pair, (t_capture, m) in list(self._held.items()):
            if pair in fresh_pairs:
                continue
            k = self._segment(segments, m) if t_s - t_capture <= self.hold_s else None
            if k is None:
                del self._held[pair]  # too old to hold, or its links no longer stepped together
                continue
            out[k].append(replace(m.numbered_from(segments[k][0]), age_s=max(t_s - t_capture, 0.0)))
            given[k].append((pair, t_capture, m, False))
        self._given = [g for seg in given for g in seg]
        return out

    @staticmethod
    def _segment(segments, m: NeighbourMeasurement) -> int | None:
        """The index of the segment that holds both of ``m``'s links, or ``None``."""
        for k, seg in enumerate(segments):
            if m.observer in seg and m.observed in seg:
                return k
        return None

    def applied(self, accepted: np.ndarray) -> None:
        """What a step did with the measurements it was given, the next of them in the order
        :meth:`take` gave them (``neighbour_accepted`` of a segment's result): applied, or not
        (gated, or between two of its groups). A new one accepted is held for later steps; a held
        one that the gate refuses now is no longer held."""
        accepted = np.asarray(accepted, dtype=bool)
        done, self._given = self._given[:len(accepted)], self._given[len(accepted):]
        for ok, (pair, t_capture, m, fresh) in zip(accepted, done):
            if fresh:
                self._counts["applied" if ok else "not_applied"] += 1
                if ok and self.hold_s > 0.0 and t_capture >= self._held.get(pair, (-np.inf,))[0]:
                    self._held[pair] = (t_capture, m)
            elif ok:
                self._counts["reapplied"] += 1
            else:
                self._held.pop(pair, None)

    def counts(self) -> dict[str, int]:
        """``received``; ``applied``; ``not_applied`` (given to a step: gated, or between two of
        its groups); ``too_old`` at the step; ``left_out`` (no segment held both links);
        ``pending``: received and waiting for the next step (at the end of a run: never applied);
        ``reapplied``: applications of held measurements by later steps (not in the others)."""
        return {**self._counts, "pending": len(self._pending)}

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
    engine's time base), not yet applied."""

    def __init__(self, max_age_s: float = MAX_AGE_S):
        self.max_age_s = float(max_age_s)
        self._pending: list[tuple[float, NeighbourMeasurement]] = []
        self._counts = {"received": 0, "applied": 0, "not_applied": 0, "too_old": 0, "left_out": 0}

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
        rows, numbered from its first (all of them leave the queue); those captured more than
        :attr:`max_age_s` before ``t_s``, and those no segment holds, are dropped and counted."""
        out: list[list[NeighbourMeasurement]] = [[] for _ in segments]
        for t_capture, m in self._pending:
            if t_s - t_capture > self.max_age_s:
                self._counts["too_old"] += 1
                continue
            for k, seg in enumerate(segments):
                if m.observer in seg and m.observed in seg:
                    out[k].append(replace(m.numbered_from(seg[0]), age_s=max(t_s - t_capture, 0.0)))
                    break
            else:
                self._counts["left_out"] += 1
        self._pending.clear()
        return out

    def applied(self, accepted: np.ndarray) -> None:
        """What a step did with the measurements it was given (``neighbour_accepted`` of its
        result): applied, or not (gated, or between two of its groups)."""
        accepted = np.asarray(accepted, dtype=bool)
        self._counts["applied"] += int(accepted.sum())
        self._counts["not_applied"] += int((~accepted).sum())

    def counts(self) -> dict[str, int]:
        """``received``; ``applied``; ``not_applied`` (given to a step: gated, or between two of
        its groups); ``too_old`` at the step; ``left_out`` (no segment held both links);
        ``pending``: received and waiting for the next step (at the end of a run: never applied)."""
        return {**self._counts, "pending": len(self._pending)}

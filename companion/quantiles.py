"""Percentiles of a long stream of non-negative values in fixed memory.

A daemon that reports the median and the 99th percentile of its correction latency or step time
over a whole flight cannot keep every sample: a link's states arrive at 50 Hz, 180,000 of them an
hour. :class:`Quantiles` counts the samples in logarithmic bins instead (as HdrHistogram and
DDSketch do): bin ``k`` holds the values in ``[lo (1 + rel)^k, lo (1 + rel)^(k + 1))``, values
below ``lo`` share a bin for zero, and the exact minimum, maximum and sum are kept. A percentile
is the geometric middle of the bin holding that rank (linear interpolation between ranks, as
:func:`numpy.percentile`), clamped to the minimum and maximum (the first and last ranks are them): within ``rel / 2`` of the value
:func:`numpy.percentile` gives for values in ``[lo, hi]``, whatever the number of samples.
Non-finite and negative samples are counted apart (:attr:`Quantiles.refused`), never binned.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Quantiles"]


class Quantiles:
    """Counts of values in ``[lo, hi]`` at relative resolution ``rel`` (module docstring); values
    above ``hi`` go into the top bin (the maximum stays exact)."""

    def __init__(self, lo: float = 1e-3, hi: float = 1e6, rel: float = 2e-3):
        if not (0.0 < lo < hi and math.isfinite(hi)) or not 0.0 < rel < 1.0:
            raise ValueError(f"need 0 < lo < hi < inf and 0 < rel < 1, got lo={lo}, hi={hi}, rel={rel}")
        self.lo, self.hi, self.rel = float(lo), float(hi), float(rel)
        self._log_step = math.log1p(rel)
        self._bins = int(math.ceil(math.log(hi / lo) / self._log_step)) + 1
        self.counts = np.zeros(self._bins + 1, dtype=np.int64)  # [0]: below lo
        self.count = 0
        self.refused = 0
        self.min = math.inf
        self.max = -math.inf
        self.total = 0.0  # the binned samples' sum

    def add(self, value: float) -> None:
        """One sample (a non-finite or negative one is only counted in :attr:`refused`)."""
        x = float(value)
        if not (x >= 0.0 and math.isfinite(x)):
            self.refused += 1
            return
        if x < self.lo:
            k = 0
        else:
            k = min(int(math.log(x / self.lo) / self._log_step), self._bins - 1) + 1
        self.counts[k] += 1
        self.count += 1
        self.total += x
        self.min = min(self.min, x)
        self.max = max(self.max, x)

    def merge(self, other: Quantiles) -> Quantiles:
        """A new sketch with both sketches' samples (same ``lo``, ``hi``, ``rel``)."""
        if (self.lo, self.hi, self.rel) != (other.lo, other.hi, other.rel):
            raise ValueError("sketches with different bins cannot be merged")
        out = Quantiles(self.lo, self.hi, self.rel)
        out.counts = self.counts + other.counts
        out.count, out.refused = self.count + other.count, self.refused + other.refused
        out.min, out.max = min(self.min, other.min), max(self.max, other.max)
        out.total = self.total + other.total
        return out

    def _value_at_rank(self, rank: int, cumulative: np.ndarray) -> float:
        if rank == 0:
            return self.min
        if rank == self.count - 1:
            return self.max
        k = int(np.searchsorted(cumulative, rank, side="right"))
        if k == 0:
            mid = 0.0
        else:
            mid = self.lo * math.exp((k - 0.5) * self._log_step)
        return min(max(mid, self.min), self.max)

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (0 to 100; NaN without samples)."""
        if not 0.0 <= q <= 100.0:
            raise ValueError(f"q must be in [0, 100], got {q}")
        if self.count == 0:
            return math.nan
        cumulative = np.cumsum(self.counts)
        h = q / 100.0 * (self.count - 1)
        below, above = math.floor(h), math.ceil(h)
        a = self._value_at_rank(below, cumulative)
        b = a if above == below else self._value_at_rank(above, cumulative)
        return a + (h - below) * (b - a)

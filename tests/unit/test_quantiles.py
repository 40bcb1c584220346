"""Percentiles in fixed memory (companion.quantiles): within rel / 2 of numpy's, whatever the count."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.quantiles import Quantiles


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(1e-3, 1e5), min_size=1, max_size=300), st.floats(0.0, 100.0))
def test_a_percentile_is_within_half_the_resolution_of_numpys(values, q):
    sketch = Quantiles(rel=2e-3)
    for v in values:
        sketch.add(v)
    exact = float(np.percentile(values, q))
    assert sketch.percentile(q) == pytest.approx(exact, rel=1e-3 + 1e-12)


@pytest.mark.parametrize("q", [0.0, 50.0, 99.0, 100.0])
def test_merged_sketches_answer_for_all_their_samples(q):
    rng = np.random.default_rng(3)
    a, b = rng.lognormal(1.0, 1.0, 500), rng.uniform(0.0, 40.0, 700)
    left, right = Quantiles(), Quantiles()
    for v in a:
        left.add(v)
    for v in b:
        right.add(v)
    both = left.merge(right)
    assert both.count == 1200 and both.total == pytest.approx(a.sum() + b.sum(), rel=1e-12)  # the exact sum
    assert both.percentile(q) == pytest.approx(np.percentile(np.concatenate((a, b)), q), rel=1e-3)
    with pytest.raises(ValueError, match="different bins"):
        left.merge(Quantiles(rel=1e-2))


def test_memory_is_fixed_and_bad_samples_are_counted_apart():
    sketch = Quantiles()
    size = sketch.counts.nbytes
    for v in (math.nan, -1.0, math.inf, 0.0, 2e6):
        sketch.add(v)
    for v in np.random.default_rng(0).exponential(5.0, 20_000):
        sketch.add(v)
    assert sketch.counts.nbytes == size and sketch.refused == 3 and sketch.count == 20_002
    assert math.isfinite(sketch.total) and sketch.total > 2e6  # the refused samples are not in the sum
    assert sketch.percentile(0.0) == 0.0 and sketch.percentile(100.0) == 2e6  # the extremes stay exact
    assert math.isnan(Quantiles().percentile(50.0))
    with pytest.raises(ValueError):
        sketch.percentile(101.0)
    with pytest.raises(ValueError):
        Quantiles(lo=1.0, hi=0.5)

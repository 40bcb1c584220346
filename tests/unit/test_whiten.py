"""Errors whitened by their covariances (companion.estimation.whiten), which the chain's and the
slung load's NEES both use: the Cholesky solve where a sample can be whitened, NaN where it cannot."""

from __future__ import annotations

import numpy as np
import pytest

from companion.estimation.whiten import whitened


@pytest.mark.parametrize("lead", [(5,), (4, 3), (2, 3, 2)])
def test_whitened_is_the_cholesky_solve_over_any_leading_axes(lead):
    rng = np.random.default_rng(len(lead))
    d = 3
    A = rng.normal(size=lead + (d, d))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(d)
    e = rng.normal(size=lead + (d,))
    w = whitened(e, P)
    L = np.linalg.cholesky(P)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", L, w), e, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.sum(w * w, axis=-1), np.einsum("...i,...ij,...j->...", e, np.linalg.inv(P), e),
                               rtol=1e-9)


@pytest.mark.parametrize("bad", ["negative variance", "singular", "infinite", "nan error"])
def test_a_sample_that_cannot_be_whitened_is_nan_and_leaves_the_others(bad):
    P = np.tile(np.diag([1e-2, 4e-2, 1e-2]), (3, 1, 1))
    e = np.full((3, 3), 0.1)
    if bad == "negative variance":
        P[1, 0, 0] = -1.0
    elif bad == "singular":
        P[1] = np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    elif bad == "infinite":
        P[1, 2, 2] = np.inf
    else:
        e[1, 0] = np.nan
    w = whitened(e, P)
    assert np.isnan(w[1]).all()
    np.testing.assert_allclose(w[[0, 2]], [[1.0, 0.5, 1.0]] * 2)


def test_the_chains_nees_is_nan_for_a_diverged_block_instead_of_raising():
    """sitl.metrics.nees_whitened raised numpy's LinAlgError for a finite covariance block that
    is not positive definite."""
    from sitl.metrics import nees_whitened

    q = np.tile([1.0, 0.0, 0.0, 0.0], (2, 4))
    P = np.tile(np.eye(3) * 0.01, (2, 4, 3, 1, 1))
    P[1, 2, 0] = -np.eye(3)
    w = nees_whitened(np.full((2, 4, 3), 0.1), np.zeros((2, 4, 3)), q.reshape(2, 4, 4), np.zeros((2, 4, 3)),
                      np.zeros((2, 4, 3)), q.reshape(2, 4, 4), P)
    bad = np.zeros((2, 4, 3), dtype=bool)
    bad[1, 2, 0] = True
    assert w.shape == (2, 4, 3, 3) and np.isnan(w[bad]).all() and np.isfinite(w[~bad]).all()

"""Errors whitened by their covariances, the building block of the NEES: ``L^-1 e`` with
``P = L L^T``, NaN where a sample cannot be whitened (a diverged or unknown estimate).

Pure numpy: :func:`whitened`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["whitened"]


def whitened(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``L^-1 e`` per sample (``P = L L^T``, the Cholesky factor) for errors ``e`` (..., d) and
    their covariances ``P`` (..., d, d), over any leading axes. NaN (all ``d`` components) for a
    sample whose error is not finite or whose covariance is not finite and positive definite. For
    a consistent estimate the components are independent unit normals; their squared norm is the
    NEES."""
    e = np.asarray(e, dtype=float)
    P = np.asarray(P, dtype=float)
    out = np.full(e.shape, np.nan)
    ok = np.all(np.isfinite(e), axis=-1) & np.all(np.isfinite(P), axis=(-2, -1))
    ok[ok] = np.all(np.linalg.eigvalsh(P[ok]) > 0.0, axis=-1)
    if np.any(ok):
        out[ok] = np.linalg.solve(np.linalg.cholesky(P[ok]), e[ok][..., None])[..., 0]
    return out

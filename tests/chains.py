"""Random chain snapshots for the estimator tests (seeded)."""

from __future__ import annotations

import numpy as np

from companion.estimation.constraints import tip_offsets
from companion.estimation.so3 import quat_normalize, retract


def consistent_chain(rng: np.random.Generator, n: int, half_length: float = 0.5, spread: float = 0.4):
    """A chain that satisfies eq. 3 exactly: random attitudes, body rates and base state."""
    q = quat_normalize(np.array([1.0, 0.0, 0.0, 0.0]) + spread * rng.normal(size=(n, 4)))
    w = rng.normal(scale=0.6, size=(n, 3))
    d = np.tile([half_length, 0.0, 0.0], (n, 1)) + rng.normal(scale=0.02, size=(n, 3))
    a, b = tip_offsets(q, w, d)
    p = np.zeros((n, 3))
    v = np.zeros((n, 3))
    p[0] = rng.normal(scale=3.0, size=3)
    v[0] = rng.normal(scale=1.0, size=3)
    for i in range(1, n):
        p[i] = p[i - 1] + a[i - 1] + a[i]
        v[i] = v[i - 1] + b[i - 1] + b[i]
    return p, v, q, w, d


def random_covariances(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    """SPD (n, 9, 9) blocks, EKF-like magnitudes: 0.1 on p and v, 0.01 on attitude."""
    A = rng.normal(scale=0.15, size=(n, 9, 9))
    base = np.diag([0.1] * 6 + [0.01] * 3)
    return scale * (A @ np.swapaxes(A, 1, 2) * 0.2 + base)


def perturbed_chain(rng: np.random.Generator, n: int, pos_sigma: float = 0.3, att_sigma: float = 0.05):
    """EKF-like estimates: a consistent chain plus independent errors on every link."""
    p, v, q, w, d = consistent_chain(rng, n)
    p = p + rng.normal(scale=pos_sigma, size=p.shape)
    v = v + rng.normal(scale=pos_sigma, size=v.shape)
    q = retract(q, rng.normal(scale=att_sigma, size=(n, 3)))
    return p, v, q, w, d, random_covariances(rng, n)

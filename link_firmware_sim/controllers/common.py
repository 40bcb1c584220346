"""What the pose controllers share: the position error's limit, the skew map's inverse and the
wrench that carries a link's weight."""

from __future__ import annotations

import math

import numpy as np

from companion.estimation.so3 import rotmat_tuple
from companion.skeleton.body import GRAVITY_M_S2, LinkInertia

__all__ = ["E3", "require_gains", "limit_length", "vee", "weight_wrench"]

#: the world's vertical (z up)
E3 = np.array([0.0, 0.0, 1.0])
_COUNTS = {1: "a", 3: "three", 6: "six"}


def require_gains(name: str, value, size: int = 1, positive: bool = False) -> None:
    """``ValueError`` unless ``value`` is a finite number (``size`` 1) or ``size`` finite numbers,
    non-negative (``positive``: > 0): a controller's gains, checked when its configuration is made."""
    values = (value,) if size == 1 else value
    ok = len(values) == size and all(math.isfinite(x) and (x > 0 if positive else x >= 0) for x in values)
    if not ok:
        kind = "positive" if positive else "non-negative"
        raise ValueError(f"{name} must be {_COUNTS[size]} finite {kind} number{'s' if size > 1 else ''}, got {value!r}")


def limit_length(e, limit: float) -> tuple:
    """``e`` (3 floats) as a tuple, shortened to length ``limit`` if longer (the position error's
    limit of eq. 1 and of sec. 2.3.2's controller, ``pos_error_limit_m``)."""
    n = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    if n <= limit:
        return tuple(e)
    k = limit / n
    return (e[0] * k, e[1] * k, e[2] * k)


def vee(S: np.ndarray) -> np.ndarray:
    """Inverse of the skew map: ``vee(S(w)) = w``."""
    return np.array([S[2, 1], S[0, 2], S[1, 0]])


def weight_wrench(inertia: LinkInertia, q_wxyz: np.ndarray) -> np.ndarray:
    """Body-frame wrench ``U = [R^T m g e3; 0]`` that carries the link's weight at attitude ``q``
    (``R^T e3`` is R's third row; the firmware's step-by-step path calls this every tick)."""
    mg = inertia.mass_kg * GRAVITY_M_S2
    r3 = rotmat_tuple(np.asarray(q_wxyz, dtype=float).tolist())[6:]
    return np.array((r3[0] * mg, r3[1] * mg, r3[2] * mg, 0.0, 0.0, 0.0))

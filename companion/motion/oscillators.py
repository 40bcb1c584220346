"""The oscillator core every CPG of the thesis's chapter 4 is built from (pure numpy).

Sec. 4.3 formulates its CPGs (the flying skeleton's eel-like one, the snake's and the
pivotboard's) on Kuramoto phase oscillators with amplitude and bias states as in Ijspeert's
salamander CPG. Three parts are common to all of them:

* the amplitude and bias filters, critically damped second-order systems::

      x'' = k (k/4 (target - x) - x')          (double pole at -k/2: no overshoot)

  (:func:`filter_acceleration`);
* the phase coupling of an oscillator to its neighbours, ``sum_j sin(phi_j - phi_i - phi_ij)``,
  as one sparse product over the coupled pairs (:class:`Coupling`, :func:`chain_coupling` for
  nearest neighbours with a constant lag: a travelling wave from the first to the last);
* the integration, one classical Runge-Kutta step of a state that adds and scales field by field
  (:func:`rk4_step`).

:class:`PhaseMap` holds a target phase difference as a function of the CPG's inputs, sampled on a
regular grid (the optimal phase differences of eq. 4.1, found by simulation sweeps), read by
multilinear interpolation.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np

__all__ = ["filter_acceleration", "Coupling", "chain_coupling", "rk4_step", "PhaseMap"]


def filter_acceleration(x, x_dot, target, k: float):
    """``x''`` of the critically damped filter ``x'' = k (k/4 (target - x) - x')``."""
    return k * (k / 4.0 * (target - x) - x_dot)


@dataclass(frozen=True)
class Coupling:
    """Phase couplings of ``n`` oscillators: pair ``p`` makes oscillator ``i[p]`` follow ``j[p]`` at
    the desired difference ``phi_j - phi_i = phi_ij[p]``; ``incidence`` (P, n) sums each
    oscillator's pairs in one product (read-only arrays)."""

    n: int
    i: np.ndarray
    j: np.ndarray
    phi_ij: np.ndarray
    incidence: np.ndarray

    @classmethod
    def of(cls, n: int, pairs: list[tuple[int, int, float]]) -> Coupling:
        """From ``(i, j, phi_ij)`` triples (``ValueError`` for an index outside ``0..n-1`` or a
        self-coupling)."""
        if any(not (0 <= a < n and 0 <= b < n) or a == b for a, b, _ in pairs):
            raise ValueError(f"couplings join two of the {n} oscillators, got {[(a, b) for a, b, _ in pairs]}")
        i = np.array([a for a, _, _ in pairs], dtype=int)
        j = np.array([b for _, b, _ in pairs], dtype=int)
        phi = np.array([float(x) for _, _, x in pairs])
        incidence = np.zeros((len(pairs), n))
        incidence[np.arange(len(pairs)), i] = 1.0
        for a in (i, j, phi, incidence):
            a.setflags(write=False)
        return cls(n, i, j, phi, incidence)

    def sum_sin(self, phi: np.ndarray) -> np.ndarray:
        """``sum_j sin(phi_j - phi_i - phi_ij)`` per oscillator (..., n)."""
        return np.sin(phi[..., self.j] - phi[..., self.i] - self.phi_ij) @ self.incidence


def chain_coupling(n: int, lag_rad: float) -> Coupling:
    """Nearest neighbours along a chain of ``n`` oscillators: ``i + 1`` lags ``i`` by ``lag_rad``
    (``phi_{i+1} - phi_i = -lag``), both ways."""
    pairs = [(k, k + 1, -lag_rad) for k in range(n - 1)] + [(k + 1, k, lag_rad) for k in range(n - 1)]
    return Coupling.of(n, sorted(pairs))


class _Addable(Protocol):
    def plus(self, h: float, d): ...


S = TypeVar("S", bound=_Addable)


def rk4_step(derivative: Callable[[S], S], state: S, dt_s: float) -> S:
    """One classical Runge-Kutta step of ``dt_s`` (``state.plus(h, d)`` is ``state + h d``)."""
    k1 = derivative(state)
    k2 = derivative(state.plus(0.5 * dt_s, k1))
    k3 = derivative(state.plus(0.5 * dt_s, k2))
    k4 = derivative(state.plus(dt_s, k3))
    h = dt_s / 6.0
    return state.plus(h, k1).plus(2 * h, k2).plus(2 * h, k3).plus(h, k4)


@dataclass(frozen=True)
class PhaseMap:
    """A target phase difference [rad] sampled on a regular grid of the CPG's inputs: ``axes``
    (one increasing tuple per input) and ``values`` (the grid's shape, flattened row-major);
    read by multilinear interpolation, inputs outside the grid clamped to its edges. An axis
    of one point makes the map constant along that input. ``ValueError`` for axes that do not
    increase, values of the wrong count, or anything not finite."""

    axes: tuple[tuple[float, ...], ...]
    values: tuple[float, ...]

    def __post_init__(self) -> None:
        if not self.axes:
            raise ValueError("axes: at least one input")
        for k, ax in enumerate(self.axes):
            if not ax or not all(math.isfinite(x) for x in ax) or any(b <= a for a, b in zip(ax, ax[1:])):
                raise ValueError(f"axes[{k}]: finite, strictly increasing, at least one point; got {list(ax)}")
        size = math.prod(len(ax) for ax in self.axes)
        if len(self.values) != size or not all(math.isfinite(v) for v in self.values):
            raise ValueError(f"values: {size} finite numbers for a grid of {[len(a) for a in self.axes]}, "
                             f"got {len(self.values)}")

    @classmethod
    def constant(cls, value_rad: float, n_inputs: int) -> PhaseMap:
        """The same phase difference for every input."""
        return cls(tuple((0.0,) for _ in range(n_inputs)), (float(value_rad),))

    def __call__(self, *inputs: float) -> float:
        if len(inputs) != len(self.axes):
            raise ValueError(f"the map takes {len(self.axes)} inputs, got {len(inputs)}")
        grid = np.asarray(self.values, dtype=float).reshape([len(ax) for ax in self.axes])
        for ax, x in zip(self.axes, inputs):  # reduce one axis at a time: linear between its points
            a = np.asarray(ax)
            if len(a) == 1:
                grid = grid[0]
                continue
            x = min(max(float(x), a[0]), a[-1])
            k = int(np.clip(np.searchsorted(a, x, side="right") - 1, 0, len(a) - 2))
            w = (x - a[k]) / (a[k + 1] - a[k])
            grid = (1.0 - w) * grid[k] + w * grid[k + 1]
        return float(grid)

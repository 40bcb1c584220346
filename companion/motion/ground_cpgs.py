"""The CPGs of the thesis's two ground robots (sec. 4.3.2 snake-like robot, sec. 4.3.3 pivotboard),
on the chapter's common oscillator core (:mod:`.oscillators`), pure numpy.

**Snake** (15 modules, joints alternately horizontal and vertical: ``n`` = 7 of each), per joint
pair ``i``::

    theta_h,i = a_i cos(phi_h,i) + b_i
    theta_v,i = -A_v,i sin(phi_v,i)
    a_i''     = k_a (k_a/4 (sigma_a,i A - a_i) - a_i')
    b_i''     = k_b (k_b/4 (sigma_b,i B - b_i) - b_i')
    phi_h,i'  = 2 pi f + sum_{j in N_h,i} w_h sin(phi_h,j - phi_h,i - phi_h,ij)
                       + w_hv sin(phi_v,i - 2 phi_h,i - phi_hv(A, B))
    phi_v,i'  = 4 pi f + sum_{j in N_v,i} w_v sin(phi_v,j - phi_v,i - phi_v,ij)
                       - w_hv sin(phi_v,i - 2 phi_h,i - phi_hv(A, B))

``A``, ``B``: the horizontal undulation's amplitude and bias (scalars); the vertical oscillators
run at twice the frequency ("sinus lifting"), locked to the horizontal ones at the phase
difference ``phi_hv(A, B)`` (eq. 4.1: the one that maximises the forward speed, a
:class:`~.oscillators.PhaseMap` of the inputs). The thesis leaves the neighbour sets and
desired lags to its Fig. 4-5: here nearest neighbours, ``phi_h,ij`` one wavelength over the
body (``lag_h_rad``) and ``phi_v,ij = 2 phi_h,ij``, consistent with the 2:1 lock. The coupled
chains have more than one stable locked state: from arbitrary phases they may lock "twisted",
the tail's vertical oscillators far off ``phi_hv`` (tests/unit/test_ground_cpgs.py), so the CPG
starts on the wave (:meth:`SnakeCpgState.at_rest`), from which input changes relock it.

**Pivotboard** (deck and two foot plates on revolute joints, ``i`` in ``{r, l}``)::

    theta_i  = a_i cos(phi_i) + b_i
    a_i''    = k_a (k_a/4 (A - a_i) - a_i')
    b_i''    = k_b (k_b/4 (sigma_b,i B - b_i) - b_i')          sigma_b,r = 1, sigma_b,l = 0
    phi_r'   = 2 pi f + w sin(phi_l - phi_r - phi(A, B, v_dot_d))
    phi_l'   = 2 pi f - w sin(phi_l - phi_r - phi(A, B, v_dot_d))

with ``phi(A, B, v_dot_d)`` the speed-maximising phase difference while accelerating
(``v_dot_d >= 0``, a :class:`~.oscillators.PhaseMap` of the three inputs) and zero while
decelerating: the board then slows down quickly, and since only the phase rates switch, the
joint angles stay continuous.

The thesis integrates its CPGs with a passive midpoint integrator in V-REP; these use the
classical Runge-Kutta step of :func:`~.oscillators.rk4_step` (4th order; at the 100 Hz and
faster steps used here far inside its stability region for the gains below).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from functools import cached_property

import numpy as np

from companion.configfile import require_positive

from .oscillators import Coupling, PhaseMap, chain_coupling, filter_acceleration, rk4_step

__all__ = ["SnakeCpgParams", "SnakeCpgState", "snake_derivative", "snake_step", "snake_joint_angles",
           "PivotCpgParams", "PivotCpgState", "pivot_phase_target", "pivot_derivative", "pivot_step",
           "pivot_joint_angles"]


class _VectorState:
    """A state of equal-length arrays (its dataclass fields) that adds and scales as one vector."""

    def vector(self) -> np.ndarray:
        return np.concatenate([getattr(self, f.name) for f in fields(self)])

    @classmethod
    def from_vector(cls, x: np.ndarray):
        return cls(*np.split(np.asarray(x, dtype=float), len(fields(cls))))

    def plus(self, h: float, d):
        """``self + h d``."""
        return type(self).from_vector(self.vector() + h * d.vector())


@dataclass(frozen=True)
class SnakeCpgParams:
    """The snake CPG's constants (sec. 4.3.2): ``n`` joints of each axis, frequency ``f`` [Hz],
    filter gains ``k_a``, ``k_b`` [1/s], couplings ``w_h``, ``w_v``, ``w_hv`` [1/s], shaping
    ``sigma_a``, ``sigma_b`` (empty: ones), the vertical amplitudes ``A_v`` [rad] (one value: every
    joint), the horizontal lag between neighbours ``lag_h_rad`` (0: one wavelength over the
    body) and the phase map ``phase_hv`` of ``(A, B)``."""

    n: int = 7
    frequency_hz: float = 1.0
    k_a: float = 4.0
    k_b: float = 4.0
    w_h: float = 4.0
    w_v: float = 4.0
    w_hv: float = 4.0
    sigma_a: tuple[float, ...] = ()
    sigma_b: tuple[float, ...] = ()
    A_v_rad: tuple[float, ...] = (math.radians(5.0),)
    lag_h_rad: float = 0.0
    phase_hv: PhaseMap = field(default_factory=lambda: PhaseMap.constant(0.0, 2))

    def __post_init__(self) -> None:
        if self.n < 2:
            raise ValueError(f"n must be >= 2, got {self.n}")
        require_positive(self, "frequency_hz", "k_a", "k_b")
        for name in ("w_h", "w_v", "w_hv", "lag_h_rad"):
            if not math.isfinite(getattr(self, name)) or getattr(self, name) < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {getattr(self, name)}")
        for name, allowed in (("sigma_a", (0, self.n)), ("sigma_b", (0, self.n)), ("A_v_rad", (1, self.n))):
            value = getattr(self, name)
            if len(value) not in allowed or not all(math.isfinite(v) for v in value):
                raise ValueError(f"{name}: finite, {' or '.join(str(k) for k in allowed)} values, got {list(value)}")
        if len(self.phase_hv.axes) != 2:
            raise ValueError(f"phase_hv: a map of (A, B), got {len(self.phase_hv.axes)} inputs")

    @property
    def lag(self) -> float:
        return self.lag_h_rad or 2.0 * math.pi / self.n

    # computed once per (frozen) instance: the derivative reads them at every Runge-Kutta stage
    @cached_property
    def shaping(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(sigma_a, sigma_b, A_v)``, each (n,), read-only."""
        out = (np.array(self.sigma_a or (1.0,) * self.n, dtype=float), np.array(self.sigma_b or (1.0,) * self.n, dtype=float),
               np.broadcast_to(np.asarray(self.A_v_rad, dtype=float), (self.n,)))
        for a in out[:2]:
            a.setflags(write=False)
        return out

    @cached_property
    def couplings(self) -> tuple[Coupling, Coupling]:
        """The horizontal and the vertical chains' couplings (the vertical lag twice the horizontal)."""
        return chain_coupling(self.n, self.lag), chain_coupling(self.n, 2.0 * self.lag)


@dataclass(frozen=True)
class SnakeCpgState(_VectorState):
    """Amplitudes ``a``, ``a_dot``, biases ``b``, ``b_dot`` and phases ``phi_h``, ``phi_v``, each (n,)."""

    a: np.ndarray
    a_dot: np.ndarray
    b: np.ndarray
    b_dot: np.ndarray
    phi_h: np.ndarray
    phi_v: np.ndarray

    @classmethod
    def at_rest(cls, params: SnakeCpgParams, phi_h0=None, phi_v0=None) -> SnakeCpgState:
        """Zero amplitude and bias; phases ``phi_h0``, ``phi_v0`` (default: already locked)."""
        k = np.arange(params.n)
        z = np.zeros(params.n)
        phi_h = -params.lag * k if phi_h0 is None else np.asarray(phi_h0, dtype=float)
        phi_v = 2.0 * phi_h + params.phase_hv(0.0, 0.0) if phi_v0 is None else np.asarray(phi_v0, dtype=float)
        return cls(z, z.copy(), z.copy(), z.copy(), np.array(phi_h, dtype=float), np.array(phi_v, dtype=float))



def snake_derivative(state: SnakeCpgState, params: SnakeCpgParams, A: float, B: float) -> SnakeCpgState:
    """The time derivative of the snake CPG's state at the inputs ``A``, ``B`` (module docstring)."""
    sigma_a, sigma_b, _ = params.shaping
    coupling_h, coupling_v = params.couplings
    hv = params.w_hv * np.sin(state.phi_v - 2.0 * state.phi_h - params.phase_hv(A, B))
    two_pi_f = 2.0 * math.pi * params.frequency_hz
    return SnakeCpgState(state.a_dot, filter_acceleration(state.a, state.a_dot, sigma_a * A, params.k_a),
                         state.b_dot, filter_acceleration(state.b, state.b_dot, sigma_b * B, params.k_b),
                         two_pi_f + params.w_h * coupling_h.sum_sin(state.phi_h) + hv,
                         2.0 * two_pi_f + params.w_v * coupling_v.sum_sin(state.phi_v) - hv)


def snake_step(state: SnakeCpgState, params: SnakeCpgParams, A: float, B: float, dt_s: float) -> SnakeCpgState:
    """One Runge-Kutta step of ``dt_s`` with ``A``, ``B`` held over it."""
    return rk4_step(lambda x: snake_derivative(x, params, A, B), state, dt_s)


def snake_joint_angles(state: SnakeCpgState, params: SnakeCpgParams) -> tuple[np.ndarray, np.ndarray]:
    """``(theta_h, theta_v)`` [rad], each (n,): the horizontal and the vertical joints' targets."""
    return state.a * np.cos(state.phi_h) + state.b, -params.shaping[2] * np.sin(state.phi_v)


@dataclass(frozen=True)
class PivotCpgParams:
    """The pivotboard CPG's constants (sec. 4.3.3): frequency ``f`` [Hz], filter gains ``k_a``,
    ``k_b`` and phase coupling ``w`` [1/s], and the accelerating phase map ``phase`` of
    ``(A, B, v_dot_d)``. The bias shaping is the thesis's: ``sigma_b = (1, 0)`` (right, left)."""

    frequency_hz: float = 1.0
    k_a: float = 4.0
    k_b: float = 4.0
    w: float = 4.0
    phase: PhaseMap = field(default_factory=lambda: PhaseMap.constant(math.radians(30.0), 3))

    SIGMA_B = (1.0, 0.0)

    def __post_init__(self) -> None:
        require_positive(self, "frequency_hz", "k_a", "k_b", "w")
        if len(self.phase.axes) != 3:
            raise ValueError(f"phase: a map of (A, B, v_dot_d), got {len(self.phase.axes)} inputs")


@dataclass(frozen=True)
class PivotCpgState(_VectorState):
    """Amplitudes ``a``, ``a_dot``, biases ``b``, ``b_dot`` and phases ``phi``, each (2,): right, left."""

    a: np.ndarray
    a_dot: np.ndarray
    b: np.ndarray
    b_dot: np.ndarray
    phi: np.ndarray

    @classmethod
    def at_rest(cls, phi0=(0.0, 0.0)) -> PivotCpgState:
        z = np.zeros(2)
        return cls(z, z.copy(), z.copy(), z.copy(), np.array(phi0, dtype=float))



def pivot_phase_target(params: PivotCpgParams, A: float, B: float, v_dot_d: float) -> float:
    """``phi(A, B, v_dot_d)``: the map's while accelerating (``v_dot_d >= 0``), zero while decelerating."""
    return params.phase(A, B, v_dot_d) if v_dot_d >= 0.0 else 0.0


def pivot_derivative(state: PivotCpgState, params: PivotCpgParams, A: float, B: float, v_dot_d: float) -> PivotCpgState:
    """The time derivative of the pivotboard CPG's state (module docstring)."""
    pull = params.w * math.sin(state.phi[1] - state.phi[0] - pivot_phase_target(params, A, B, v_dot_d))
    two_pi_f = 2.0 * math.pi * params.frequency_hz
    return PivotCpgState(state.a_dot, filter_acceleration(state.a, state.a_dot, A, params.k_a),
                         state.b_dot, filter_acceleration(state.b, state.b_dot, np.asarray(params.SIGMA_B) * B, params.k_b),
                         np.array([two_pi_f + pull, two_pi_f - pull]))


def pivot_step(state: PivotCpgState, params: PivotCpgParams, A: float, B: float, v_dot_d: float,
               dt_s: float) -> PivotCpgState:
    """One Runge-Kutta step of ``dt_s`` with the inputs held over it."""
    return rk4_step(lambda x: pivot_derivative(x, params, A, B, v_dot_d), state, dt_s)


def pivot_joint_angles(state: PivotCpgState) -> np.ndarray:
    """``(theta_r, theta_l)`` [rad]: the foot plates' joint targets."""
    return state.a * np.cos(state.phi) + state.b

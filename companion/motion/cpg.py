"""Eel-like central pattern generator of the flying skeleton (thesis sec. 4.3.1), pure numpy.

Per link ``i`` (thesis sec. 4.3.1, the four CPG equations)::

    a_i'' = k_a (k_a/4 (sigma_a,i A - a_i) - a_i')         amplitude, a_i in R^2
    b_i'' = k_b (k_b/4 (sigma_b,i B - b_i) - b_i')         bias, b_i in R^2
    phi_i' = 2 pi f + sum_j k_phi sin(phi_j - phi_i - phi_ij)   coupled phase oscillators
    w_i = S(e_1) [0; b_i + a_i sin(phi_i)],   R_BLi = exp(S(w_i))

``A, B in R^2`` are the commanded amplitude and bias: the first component undulates and bends
the chain horizontally (rotation about the body z axis), the second vertically (about -y). The
amplitude and bias dynamics are critically damped second-order filters, so a step in ``A`` or
``B`` moves the link attitudes with continuous angle and rate: gaits change smoothly (a
horizontal-to-vertical transition is a change of ``A`` from ``[A, 0]`` to ``[0, A]``). The
frequency ``f`` is a constant (the thesis keeps it fixed: it is redundant with ``A`` for the
forward speed). Its default, 0.25 Hz, suits a flying chain: with one-metre links and amplitudes
up to 0.6 rad the expected physics swims at up to about 0.7 m/s while the link targets
accelerate by under 1 m/s^2 and turn by under 50 deg/s (at 0.5 Hz: up to 1.4 m/s, 3 m/s^2 and 90
deg/s, beyond what the impedance controller of an 8-rotor link follows well). Neighbours are coupled with the desired phase difference ``phi_j - phi_i =
phi_ij``: ``-lag`` towards the tail and ``+lag`` towards the head, a travelling wave from head
(link 1) to tail.

Shaping (``sigma_a``, ``sigma_b``, ``lag``) follows eel (anguilliform) swimming: the amplitude
grows from head to tail and the body holds about one wavelength (thesis refs. [52], [53]); the
bias bends the chain into an arc (weights -1 at the head to +1 at the tail).

The output is the body-frame attitude of every link ``R_BLi`` and its body rate
``omega_BLi^Li = (R^T R')^v = J_r(w_i) w_i'`` (the right Jacobian of SO(3)), as sec. 4.4 needs.

The filters, the phase coupling and the integration are the chapter's common oscillator core
(:mod:`.oscillators`, shared with the snake's and the pivotboard's CPGs, :mod:`.ground_cpgs`).

Functional API: :func:`cpg_derivative`, :func:`cpg_step` (classical RK4), :func:`cpg_output`;
:class:`Cpg` is a thin stateful wrapper with the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from companion.configfile import require_positive
from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat, skew

from .oscillators import Coupling, chain_coupling, filter_acceleration, rk4_step

__all__ = ["CpgParams", "CpgState", "eel_shaping", "cpg_initial_state", "cpg_derivative", "cpg_step",
           "cpg_output", "so3_exp", "so3_right_jacobian", "Cpg"]

def eel_shaping(n_links: int, growth: float = 1.5) -> tuple[tuple[float, ...], tuple[float, ...], float]:
    """Anguilliform shaping: amplitude weights growing exponentially from head to tail (tail = 1),
    bias weights running linearly from -1 (head) to +1 (tail), so that ``B`` bends the chain into
    an arc (a bias equal on every link would only turn the straight chain inside ``{B}``), and a
    per-link phase lag holding one wavelength over the body."""
    x = np.linspace(0.0, 1.0, n_links)
    sigma_a = np.exp(growth * (x - 1.0))
    sigma_b = 2.0 * x - 1.0
    return tuple(float(s) for s in sigma_a), tuple(float(s) for s in sigma_b), 2.0 * math.pi / max(n_links, 1)


@dataclass(frozen=True)
class CpgParams:
    """Gains and shaping of the CPG (thesis sec. 4.3.1).

    ``frequency_hz``: the constant undulation frequency ``f``; ``k_a``, ``k_b`` [1/s]: amplitude
    and bias convergence gains (critically damped); ``k_phi`` [1/s]: phase coupling;
    ``sigma_a``, ``sigma_b``: per-link shaping weights (empty: :func:`eel_shaping`); ``lag_rad``:
    phase lag between neighbours (0: :func:`eel_shaping`'s one wavelength over the body).
    """

    n_links: int
    frequency_hz: float = 0.25
    k_a: float = 2.0
    k_b: float = 2.0
    k_phi: float = 2.0
    sigma_a: tuple[float, ...] = ()
    sigma_b: tuple[float, ...] = ()
    lag_rad: float = 0.0

    def __post_init__(self) -> None:
        if self.n_links < 2:
            raise ValueError(f"n_links must be >= 2, got {self.n_links}")
        require_positive(self, "frequency_hz", "k_a", "k_b", "k_phi")
        for name in ("sigma_a", "sigma_b"):
            value = getattr(self, name)
            if value and len(value) != self.n_links:
                raise ValueError(f"{name} has {len(value)} weights for {self.n_links} links")
            if not all(math.isfinite(v) for v in value):
                raise ValueError(f"{name} must be finite")
        if not math.isfinite(self.lag_rad):
            raise ValueError(f"lag_rad must be finite, got {self.lag_rad}")

    # The two below are computed once per (frozen) instance and read-only: the CPG's derivative
    # reads them at every Runge-Kutta stage (``cached_property`` writes the instance's ``__dict__``,
    # which a frozen dataclass allows; fields, equality and hashing are unchanged).
    @cached_property
    def shaping(self) -> tuple[np.ndarray, np.ndarray, float]:
        """``(sigma_a (n,), sigma_b (n,), lag)`` with the eel defaults filled in (read-only arrays)."""
        sa, sb, lag = eel_shaping(self.n_links)
        return (_frozen(np.asarray(self.sigma_a or sa, dtype=float)), _frozen(np.asarray(self.sigma_b or sb, dtype=float)),
                self.lag_rad or lag)

    @cached_property
    def coupling(self) -> np.ndarray:
        """(n, n) desired phase differences ``phi_ij`` (``nan`` where not coupled): nearest neighbours
        (read-only)."""
        lag = self.shaping[2]
        n = self.n_links
        phi = np.full((n, n), np.nan)
        idx = np.arange(n - 1)
        phi[idx, idx + 1] = -lag  # link i + 1 (towards the tail) lags link i
        phi[idx + 1, idx] = lag
        return _frozen(phi)

    @cached_property
    def coupled_pairs(self) -> Coupling:
        """:attr:`coupling` as the list of its coupled pairs (:class:`~.oscillators.Coupling`:
        nearest neighbours, the lag towards the tail)."""
        return chain_coupling(self.n_links, self.shaping[2])


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class CpgState:
    """CPG state: amplitudes ``a``, ``a_dot`` and biases ``b``, ``b_dot`` (..., n, 2), phases
    ``phi`` (..., n). Leading dimensions batch independent CPGs (one per parameter set)."""

    a: np.ndarray
    a_dot: np.ndarray
    b: np.ndarray
    b_dot: np.ndarray
    phi: np.ndarray

    def vector(self) -> np.ndarray:
        """All fields flattened (for comparisons)."""
        return np.concatenate([x.ravel() for x in (self.a, self.a_dot, self.b, self.b_dot, self.phi)])

    def plus(self, h: float, d: CpgState) -> CpgState:
        """``self + h d`` field by field."""
        return CpgState(self.a + h * d.a, self.a_dot + h * d.a_dot, self.b + h * d.b, self.b_dot + h * d.b_dot,
                        self.phi + h * d.phi)


def cpg_initial_state(params: CpgParams, phi0: np.ndarray | None = None, batch: tuple[int, ...] = ()) -> CpgState:
    """At rest (zero amplitude and bias); phases ``phi0`` (default: already locked to the lag);
    ``batch``: leading dimensions for that many independent CPGs."""
    n = params.n_links
    phi = -params.shaping[2] * np.arange(n) if phi0 is None else np.asarray(phi0, dtype=float)
    phi = np.broadcast_to(phi, batch + (n,)).copy()
    z = np.zeros(batch + (n, 2))
    return CpgState(z, z.copy(), z.copy(), z.copy(), phi)


def cpg_derivative(state: CpgState, params: CpgParams, A, B) -> CpgState:
    """Time derivative of the state (the first three equations of sec. 4.3.1); ``A``, ``B``:
    (..., 2), broadcast against the state's batch dimensions."""
    sigma_a, sigma_b, _ = params.shaping
    A = np.asarray(A, dtype=float)[..., None, :]
    B = np.asarray(B, dtype=float)[..., None, :]
    a_dd = filter_acceleration(state.a, state.a_dot, sigma_a[:, None] * A, params.k_a)
    b_dd = filter_acceleration(state.b, state.b_dot, sigma_b[:, None] * B, params.k_b)
    phi_dot = 2.0 * math.pi * params.frequency_hz + params.k_phi * params.coupled_pairs.sum_sin(state.phi)
    return CpgState(state.a_dot, a_dd, state.b_dot, b_dd, phi_dot)


def cpg_step(state: CpgState, params: CpgParams, A, B, dt_s: float) -> CpgState:
    """One classical Runge-Kutta step of ``dt_s`` with ``A``, ``B`` held over the step."""
    return rk4_step(lambda x: cpg_derivative(x, params, A, B), state, dt_s)


def so3_exp(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices (the estimation core's exponential map)."""
    return quat_to_rotmat(quat_from_rotvec(w))


def so3_right_jacobian(w: np.ndarray) -> np.ndarray:
    """(..., 3, 3) right Jacobian: ``(exp(S(w))^T d/dt exp(S(w)))^v = J_r(w) w'``."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    c1 = np.where(small, 0.5 - theta ** 2 / 24.0, (1.0 - np.cos(safe)) / safe ** 2)
    c2 = np.where(small, 1.0 / 6.0 - theta ** 2 / 120.0, (safe - np.sin(safe)) / safe ** 3)
    return np.eye(3) - c1 * K + c2 * (K @ K)


def cpg_output(state: CpgState, params: CpgParams, A, B) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(w (...,n,3), R_BL (...,n,3,3), omega_BL_L (...,n,3))``: the axis-angle of every link
    in the body frame, its attitude ``R_BLi = exp(S(w_i))`` and its body rate ``J_r(w_i) w_i'``."""
    d = cpg_derivative(state, params, A, B)
    s, c = np.sin(state.phi)[..., None], np.cos(state.phi)[..., None]
    u = state.b + state.a * s
    u_dot = d.b + d.a * s + state.a * c * d.phi[..., None]
    # S(e1) [0; u] = [0, -u_2, u_1]
    w = np.stack([np.zeros_like(u[..., 0]), -u[..., 1], u[..., 0]], axis=-1)
    w_dot = np.stack([np.zeros_like(u_dot[..., 0]), -u_dot[..., 1], u_dot[..., 0]], axis=-1)
    omega = np.einsum("...ij,...j->...i", so3_right_jacobian(w), w_dot)
    return w, so3_exp(w), omega


@dataclass
class Cpg:
    """Stateful wrapper: ``step(A, B, dt)`` then ``output()``; the same numbers as the functions."""

    params: CpgParams
    state: CpgState = field(default=None)  # type: ignore[assignment]
    A: np.ndarray = field(default_factory=lambda: np.zeros(2))
    B: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def __post_init__(self) -> None:
        if self.state is None:
            self.state = cpg_initial_state(self.params)

    def step(self, A, B, dt_s: float) -> None:
        self.A, self.B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
        self.state = cpg_step(self.state, self.params, self.A, self.B, dt_s)

    def output(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return cpg_output(self.state, self.params, self.A, self.B)

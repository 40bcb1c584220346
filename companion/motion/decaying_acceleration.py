"""The pivotboard's decaying-acceleration model (thesis sec. 4.5.3, eq. 4.2) and its fit.

Under a held CPG input the board's forward speed converges exponentially and its path's curvature
is constant::

    v_dot(t) = -d (v(t) - v_s)
    v(t)     = (v(t_0) - v_s) exp(-d (t - t_0)) + v_s                                    (4.2)
    omega(t) = c v(t)

``v_s`` [m/s] the speed it converges to, ``d`` [1/s] the decay rate, ``c`` [rad/m] the curvature;
``v`` and ``omega`` the forward and angular velocity averaged over one CPG period in the body
frame {B}.

:func:`fit_decaying_acceleration` fits the three to a run's period-averaged samples by least
squares, as the thesis does: for each ``d`` the model is linear in ``v(t_0)`` and ``v_s``
(solved exactly), and ``d`` is the one-dimensional minimiser of the residual (bounded, on a log
scale); ``c`` is the least-squares ratio of ``omega`` to ``v``.

**The first step of the inverse model** (sec. 4.5.3, Fig. 4-11): from a motion to the DA
parameters. A desired acceleration ``v_dot`` and angular velocity ``omega`` at the current speed
``v`` fix ``c = omega / v`` and, by eq. 4.2, ``v_s = v + v_dot / d``: a curve in ``(v_s, d, c)``
parametrised by ``d``. The autoencoder trained on the fitted parameters
(:class:`~.inverse.InverseModel`) knows the set they lie on; :func:`feasible_da` line-searches ``d``
for the curve's point nearest that set (the reconstruction ``AE(x)`` closest to ``x``). The same
search on the measured ``v_dot`` and ``omega`` gives the parameters the adaptation (eq. 4.3)
compares with the desired ones. Pure numpy and scipy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from .inverse import nearest_feasible

__all__ = ["DAModel", "DAFit", "fit_decaying_acceleration", "feasible_da"]


@dataclass(frozen=True)
class DAModel:
    """Eq. 4.2's parameters (module docstring)."""

    v_s_m_s: float
    d_per_s: float
    c_rad_per_m: float

    def __post_init__(self) -> None:
        if not all(math.isfinite(x) for x in (self.v_s_m_s, self.d_per_s, self.c_rad_per_m)) or self.d_per_s <= 0:
            raise ValueError(f"DAModel: finite parameters, d_per_s > 0; got {self}")

    def velocity(self, t_s, v0_m_s: float, t0_s: float = 0.0) -> np.ndarray:
        """``v(t)`` from ``v(t0) = v0`` (eq. 4.2)."""
        return (v0_m_s - self.v_s_m_s) * np.exp(-self.d_per_s * (np.asarray(t_s, dtype=float) - t0_s)) + self.v_s_m_s

    def acceleration(self, v_m_s) -> np.ndarray:
        """``v_dot = -d (v - v_s)``."""
        return -self.d_per_s * (np.asarray(v_m_s, dtype=float) - self.v_s_m_s)

    def angular_velocity(self, v_m_s) -> np.ndarray:
        """``omega = c v``."""
        return self.c_rad_per_m * np.asarray(v_m_s, dtype=float)


@dataclass(frozen=True)
class DAFit:
    """A fit: the model, ``v0_m_s`` (the fitted ``v(t_0)``), and the residuals' RMS of ``v`` [m/s]
    and of ``omega`` [rad/s] (the thesis's Fig. 4-10)."""

    model: DAModel
    v0_m_s: float
    v_rms_m_s: float
    omega_rms_rad_s: float


def _linear(t: np.ndarray, v: np.ndarray, d: float) -> tuple[np.ndarray, float]:
    """``(v0, v_s)`` minimising ``|| (v0 - v_s) e + v_s - v ||`` for ``e = exp(-d t)``, and the residual."""
    e = np.exp(-d * t)
    X = np.column_stack((e, 1.0 - e))
    coef, *_ = np.linalg.lstsq(X, v, rcond=None)
    r = X @ coef - v
    return coef, float(r @ r)


def fit_decaying_acceleration(t_s, v_m_s, omega_rad_s, d_bounds=(0.01, 20.0)) -> DAFit:
    """Eq. 4.2 fitted to samples ``(t, v, omega)`` from ``t[0]`` on (module docstring); ``ValueError``
    for fewer than four samples, a speed that never leaves zero, or anything not finite."""
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(v_m_s, dtype=float)
    w = np.asarray(omega_rad_s, dtype=float)
    if not (t.shape == v.shape == w.shape and t.ndim == 1 and t.size >= 4):
        raise ValueError(f"t, v, omega: one-dimensional, equal lengths, four samples or more; got {t.shape}, "
                         f"{v.shape}, {w.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v)) and np.all(np.isfinite(w))):
        raise ValueError("t, v, omega: finite samples")
    if not np.any(v):
        raise ValueError("v: a speed that never leaves zero fits no curvature")
    tau = t - t[0]
    res = minimize_scalar(lambda x: _linear(tau, v, math.exp(x))[1], bounds=tuple(math.log(b) for b in d_bounds),
                          method="bounded", options={"xatol": 1e-6})
    d = math.exp(float(res.x))
    (v0, v_s), sse = _linear(tau, v, d)
    c = float(w @ v / (v @ v))
    model = DAModel(float(v_s), d, c)
    return DAFit(model, float(v0), math.sqrt(sse / v.size), float(np.sqrt(np.mean((w - c * v) ** 2))))


def feasible_da(model, v_m_s: float, v_dot_m_s2: float, omega_rad_s: float, v_min_m_s: float = 0.01,
                points: int = 401) -> np.ndarray:
    """``[v_s, d, c]``: the DA parameters of the motion ``(v, v_dot, omega)`` on the feasible set
    of ``model`` (an :class:`~.inverse.InverseModel` whose ``xi`` is ``[v_s, d, c]``; module
    docstring). ``c = omega / v``, ``v`` no less than ``v_min_m_s`` (at rest the curvature is
    undefined); ``d`` is searched over ``points`` values within three standard deviations of the
    model's training mean (positive): :func:`~.inverse.nearest_feasible`. ``ValueError`` for inputs
    that are not finite."""
    if not all(math.isfinite(x) for x in (v_m_s, v_dot_m_s2, omega_rad_s)):
        raise ValueError(f"feasible_da: finite v, v_dot, omega; got {v_m_s}, {v_dot_m_s2}, {omega_rad_s}")
    c = omega_rad_s / max(v_m_s, v_min_m_s)
    mean, std = float(model.xi_mean[1]), float(model.xi_std[1])
    d = np.linspace(max(mean - 3.0 * std, 1e-3), mean + 3.0 * std, points)
    best = nearest_feasible(model, lambda d_: np.column_stack((v_m_s + v_dot_m_s2 / d_, d_, np.full_like(d_, c))), d)
    return np.array([v_m_s + v_dot_m_s2 / best, best, c])

"""A formation of independent vehicles carrying a slung load on a circle (the slung-load report's sec. IV-A).

The report's trajectory: the formation's centre flies a circle of radius ``circle_radius_m``
at ``speed_m_s`` (2 m at 1.5 m/s), and the formation yaws with the circle so that the same side
of the load always faces the circle's centre. Here:

* the centre starts at ``start_w_m`` (x, y; height ``altitude_m``) and holds there until
  ``start_s``; its arc length then ramps up smoothly over ``ramp_s`` (quintic-like: zero
  acceleration at both ends of the ramp) to the constant speed; the circle's centre is at
  ``start_w_m - (circle_radius_m, 0)``, so the centre moves along +y first;
* vehicle ``i`` sits at ``formation_radius_m`` from the centre at angle ``phi + 2 pi i / n``
  (``phi``: the centre's angle on the circle), at ``altitude_m``; its yaw is that angle plus
  ``heading_offset_deg`` (90 deg: the body x axis tangential, body y towards the load);
* optional feed-forward of the cables (:func:`cable_feedforward`): each vehicle's rotors add the
  force its cable pulls with when the load hangs in the nominal geometry and moves with the
  centre, ``sum_i T_i u_i = m_L (a_c + g e3)`` solved for the tensions ``T_i``.

Pure functions (no clocks): :func:`formation_state` and :func:`formation_targets`; velocities,
accelerations and body rates are central differences of the smooth pose function, as in
:class:`companion.trajectory.ChainTrajectory`. :class:`FormationTrajectory` is the companion's
target source for ``trajectory.kind = "formation"`` (:func:`companion.trajectory.make_trajectory`):
the targets of a :class:`~.config.LoadConfig`'s formation carrying its load, on the companion's
trajectory time (from its first targets: :class:`companion.engine.targets.Targets`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.configfile import require_nonnegative, require_positive
from companion.estimation.so3 import quat_from_euler_zyx
from companion.messages import PoseTarget
from companion.skeleton.body import GRAVITY_M_S2

__all__ = ["CircleFormationConfig", "FormationState", "formation_state", "cable_feedforward", "formation_targets",
           "FormationTrajectory"]


@dataclass(frozen=True)
class CircleFormationConfig:
    """The formation and its circle (module docstring); SI units, world frame z-up."""

    n_vehicles: int = 3
    formation_radius_m: float = 0.8
    altitude_m: float = 3.0
    circle_radius_m: float = 2.0
    speed_m_s: float = 1.5
    start_s: float = 4.0
    ramp_s: float = 4.0
    start_w_m: tuple[float, float] = (0.0, 0.0)
    heading_offset_deg: float = 90.0

    def __post_init__(self) -> None:
        if self.n_vehicles < 1:
            raise ValueError(f"n_vehicles must be >= 1, got {self.n_vehicles}")
        require_positive(self, "formation_radius_m", "altitude_m", "circle_radius_m", "ramp_s")
        require_nonnegative(self, "speed_m_s", "start_s")


@dataclass(frozen=True)
class FormationState:
    """The formation at one time: the centre (3,), its angle on the circle ``phi_rad``, every
    vehicle's position (n, 3) and yaw (n,)."""

    center_w_m: np.ndarray
    phi_rad: float
    pos_w_m: np.ndarray
    yaw_rad: np.ndarray


def arc_length(tau_s, ramp_s: float, speed_m_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance along the circle and its rate at ``tau_s`` (array) after the start: the speed
    ramps as ``V (3x^2 - 2x^3)``, ``x = tau / ramp_s`` (0 -> V, zero acceleration at both ends),
    then stays ``V``; nothing before the start."""
    tau = np.asarray(tau_s, dtype=float)
    T, V = ramp_s, speed_m_s
    x = np.clip(tau / T, 0.0, 1.0)
    s = np.where(tau < T, V * T * (x**3 - 0.5 * x**4), V * T * 0.5 + V * (tau - T))
    s_dot = V * np.where(tau < T, 3 * x**2 - 2 * x**3, 1.0)
    return s, s_dot


def _arc_length(t: float, cfg: CircleFormationConfig) -> float:
    return float(arc_length(t - cfg.start_s, cfg.ramp_s, cfg.speed_m_s)[0])


def formation_state(t: float, cfg: CircleFormationConfig) -> FormationState:
    """Where the centre and every vehicle are at ``t`` (module docstring)."""
    phi = _arc_length(t, cfg) / cfg.circle_radius_m
    Rc = cfg.circle_radius_m
    x0, y0 = cfg.start_w_m
    center = np.array([x0 - Rc + Rc * math.cos(phi), y0 + Rc * math.sin(phi), cfg.altitude_m])
    ang = phi + 2.0 * math.pi * np.arange(cfg.n_vehicles) / cfg.n_vehicles
    pos = center + cfg.formation_radius_m * np.stack((np.cos(ang), np.sin(ang), np.zeros_like(ang)), axis=1)
    return FormationState(center, phi, pos, ang + math.radians(cfg.heading_offset_deg))


def cable_feedforward(u_w: np.ndarray, load_mass_kg: float, load_acc_w_m_s2: np.ndarray,
                      gravity_m_s2: float = GRAVITY_M_S2) -> np.ndarray:
    """Per vehicle, the force (n, 3) its rotors add for its cable: ``T_i u_i`` with the tensions
    solving ``sum_i T_i u_i = m (a + g e3)`` (least squares; ``u_i`` (n, 3): unit vectors from
    the load's attachment to vehicle ``i``). Tensions below zero (a slack cable) are set to 0."""
    u = np.asarray(u_w, dtype=float)
    rhs = load_mass_kg * (np.asarray(load_acc_w_m_s2, dtype=float) + np.array([0.0, 0.0, gravity_m_s2]))
    T, *_ = np.linalg.lstsq(u.T, rhs, rcond=None)
    return np.maximum(T, 0.0)[:, None] * u


def formation_targets(t: float, cfg: CircleFormationConfig, *, load_mass_kg: float = 0.0,
                      cable_dirs_f: np.ndarray | None = None, h_s: float = 1e-3) -> list[PoseTarget]:
    """Every vehicle's :class:`PoseTarget` at ``t``: pose, velocity and acceleration (central
    differences over ``h_s``), yaw rate and its derivative; with ``load_mass_kg`` > 0 and
    ``cable_dirs_f`` (n, 3: the unit cable directions, load to vehicle, in the formation frame
    that yaws with ``phi``: x towards vehicle 0), the cables' feed-forward force."""
    states = [formation_state(t + k * h_s, cfg) for k in (-1, 0, 1)]
    p = [s.pos_w_m for s in states]
    yaw = [s.yaw_rad for s in states]
    v = (p[2] - p[0]) / (2 * h_s)
    a = (p[2] - 2 * p[1] + p[0]) / (h_s * h_s)
    yaw_rate = (yaw[2] - yaw[0]) / (2 * h_s)
    yaw_acc = (yaw[2] - 2 * yaw[1] + yaw[0]) / (h_s * h_s)
    n = cfg.n_vehicles
    ff = np.zeros((n, 3))
    if load_mass_kg > 0.0:
        if cable_dirs_f is None or np.shape(cable_dirs_f) != (n, 3):
            raise ValueError(f"cable_dirs_f must be ({n}, 3) with a load mass")
        c = [s.center_w_m for s in states]
        a_c = (c[2] - 2 * c[1] + c[0]) / (h_s * h_s)
        phi = states[1].phi_rad
        Rz = np.array([[math.cos(phi), -math.sin(phi), 0.0], [math.sin(phi), math.cos(phi), 0.0], [0.0, 0.0, 1.0]])
        ff = cable_feedforward(np.asarray(cable_dirs_f, dtype=float) @ Rz.T, load_mass_kg, a_c)
    q = quat_from_euler_zyx(yaw[1], np.zeros(n), np.zeros(n))
    return [PoseTarget(p[1][i], q[i], v[i], a[i], np.array([0.0, 0.0, yaw_rate[i]]),
                       np.array([0.0, 0.0, yaw_acc[i]]), force_ff_w_n=ff[i]) for i in range(n)]


class FormationTrajectory:
    """The formation of ``load`` (a :class:`~.config.LoadConfig`) carrying it: every vehicle's
    target at ``t`` is :func:`formation_targets` of ``load.formation`` with the load's mass and
    its cables' nominal directions (:meth:`~.config.LoadConfig.cable_dirs_f`), the interface of
    :meth:`companion.trajectory.ChainTrajectory.targets`."""

    def __init__(self, load):
        self.load = load
        self.n = load.formation.n_vehicles
        self._cable_dirs_f = load.cable_dirs_f()

    def targets(self, t: float, passive=frozenset()) -> list[PoseTarget]:
        """Every vehicle's target at ``t``; ``passive`` is ignored (a formation's vehicles are not
        joined: none carries another)."""
        ld = self.load
        return formation_targets(t, ld.formation, load_mass_kg=ld.mass_kg, cable_dirs_f=self._cable_dirs_f)

"""The sequential grid search of the ODAR design problem (2.4)-(2.6) (thesis sec. 2.2.2).

``max_{R,S} M_min^V(argmax_U F_min^W(U), R, S)`` subject to unit directions and
``r_i in R_max`` (2.5), ``F_min^W(U) >= m g`` and ``d_aero(U, R) >= D`` (2.6): first the thrust
directions ``U``, then the positions ``R`` and rotor types ``S`` given ``U``, each by grid search
(the thesis: "the solution is obtained with the grid search method").

Search space (assumptions, stated; both hold for the thesis's optimum of Table 2.1):

* **Directions** (step 1): the mirror-symmetric family of Table 2.1,
  ``u_1 = (cos e cos a, cos e sin a, sin e)``, ``u_2 = M_z u_1``, ``u_3 = M_y u_1``,
  ``u_4 = M_y M_z u_1`` (``M_y``, ``M_z``: the reflections ``y -> -y``, ``z -> -z``), on an
  ``(a, e)`` grid over ``[0, 90] deg`` squared. It keeps the bar's left/right and up/down
  symmetry and makes ``u_1 - u_2 - u_3 + u_4 = 0`` (the force half of (2.11)). Objective
  ``F_min^W``; ties broken by ``F_min``.
* **Positions** (step 2): ``r_1 = (x_1, rho_1 cos psi_1, rho_1 sin psi_1)`` and ``r_2`` likewise on
  a grid (``x`` in ``[0, L_max/2]``, ``rho`` in ``(0, R_max]``, ``psi`` all round; ``x >= 0``
  loses nothing: swapping a pair's rotors flips ``t_j`` only), with ``r_4 = R_x(pi) r_1``,
  ``r_3 = R_x(pi) r_2`` (the half-turn about the bar that maps ``u_1 -> u_4``, ``u_2 -> u_3``).
  Rotor types: all 16 ``(sigma_1..sigma_4)``. Rotors 5-8 by the pair symmetry.

Two optima are returned: the optimum of (2.4)-(2.6) as posed (the thesis's, which had
``sigma_1 = +1``), and the best design that the firmware can fly: with the null structure
(2.11) that the allocation of Prop. 1 needs (sec. 2.4.1's modification, made a constraint of the
search) and principal body axes (``sum r r^T`` diagonal, the link model's diagonal inertia).

Pure numpy; ``progress`` is an optional callback ``progress(n_done)`` for a progress bar.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.configfile import require_positive
from companion.skeleton.rotors import RotorGeometry

from .metrics import (
    DesignMetrics,
    DesignProblem,
    aero_clearance_m,
    evaluate,
    force_min,
    force_min_weighted,
    torque_min_weighted,
)

__all__ = ["DirectionResult", "SearchGrid", "SearchResult", "mirror_directions", "n_position_steps",
           "position_candidates", "search", "search_directions", "search_positions"]

#: Tolerance of the structural constraints (null structure, principal axes) on grid values.
_STRUCTURE_TOL = 1e-9
_RX_PI = np.diag([1.0, -1.0, -1.0])
_SIGMAS = np.array([[1.0 if (k >> b) & 1 else -1.0 for b in range(4)] for k in range(16)])


@dataclass(frozen=True)
class SearchGrid:
    """Grid resolution of the two steps.

    Attributes:
        direction_step_deg: step of the azimuth/elevation grid of ``u_1`` (step 1).
        x_count: number of ``r_x`` values in ``[0, L_max/2]`` (step 2).
        radius_count: number of ``rho`` values, ``R_max k / radius_count``, ``k = 1..radius_count``.
        angle_step_deg: step of the angle ``psi`` about the bar; must divide 360.
    """

    direction_step_deg: float = 0.5
    x_count: int = 5
    radius_count: int = 3
    angle_step_deg: float = 7.5

    def __post_init__(self) -> None:
        require_positive(self, "direction_step_deg", "angle_step_deg")
        if self.direction_step_deg > 45:
            raise ValueError(f"direction_step_deg must be <= 45, got {self.direction_step_deg}")
        n_angle = 360.0 / self.angle_step_deg
        if abs(n_angle - round(n_angle)) > 1e-9 or round(n_angle) < 4:
            raise ValueError(f"angle_step_deg must divide 360 into at least 4 steps, got {self.angle_step_deg}")
        if self.x_count < 1 or self.radius_count < 1:
            raise ValueError(f"x_count and radius_count must be >= 1, got {self.x_count}, {self.radius_count}")

    @classmethod
    def fine(cls) -> SearchGrid:
        """A finer grid (minutes instead of seconds)."""
        return cls(direction_step_deg=0.1, x_count=9, radius_count=4, angle_step_deg=5.0)


def mirror_directions(azimuth_rad, elevation_rad) -> np.ndarray:
    """``(u_1, M_z u_1, M_y u_1, M_y M_z u_1)`` for ``u_1`` at azimuth/elevation; shape (..., 4, 3)."""
    a = np.asarray(azimuth_rad, dtype=float)
    e = np.asarray(elevation_rad, dtype=float)
    x, y, z = np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)
    return np.stack([np.stack(v, axis=-1) for v in ((x, y, z), (x, y, -z), (x, -y, z), (x, -y, -z))], axis=-2)


@dataclass(frozen=True)
class DirectionResult:
    """Step 1's optimum: ``u_1..u_4`` (4, 3), its angles [deg], ``F_min^W`` and ``F_min`` (x lambda_max)."""

    directions: np.ndarray
    azimuth_deg: float
    elevation_deg: float
    f_min_weighted: float
    f_min: float
    n_evaluated: int
    n_feasible: int


def search_directions(problem: DesignProblem, grid: SearchGrid) -> DirectionResult:
    """Step 1: ``argmax_U F_min^W(U)`` s.t. ``F_min^W >= m g`` over the mirror family (ties: larger ``F_min``)."""
    angles = np.deg2rad(np.arange(0.0, 90.0 + 1e-9, grid.direction_step_deg))
    A, E = np.meshgrid(angles, angles, indexing="ij")
    U = mirror_directions(A, E)
    fw = force_min_weighted(U, problem.force_weight)
    feasible = fw >= problem.weight_lambda
    if not feasible.any():
        raise ValueError(f"no direction set reaches F_min^W >= m g = {problem.weight_lambda:.3f} lambda_max "
                         f"(best {fw.max():.3f}); raise thrust_max_n or lower mass_kg")
    f = force_min(U)
    # lexicographic: F_min^W first (to 1e-12), then F_min
    score = np.where(feasible, fw, -np.inf)
    best = score.max()
    tie = feasible & (fw >= best - 1e-12)
    k = np.unravel_index(np.argmax(np.where(tie, f, -np.inf)), f.shape)
    return DirectionResult(
        directions=U[k],
        azimuth_deg=float(np.rad2deg(A[k])),
        elevation_deg=float(np.rad2deg(E[k])),
        f_min_weighted=float(fw[k]),
        f_min=float(f[k]),
        n_evaluated=int(fw.size),
        n_feasible=int(feasible.sum()),
    )


def position_candidates(problem: DesignProblem, grid: SearchGrid) -> np.ndarray:
    """The position grid of one rotor, (N, 3) [m], all within ``R_max`` (2.5)."""
    xs = np.linspace(0.0, 0.5 * problem.length_max_m, grid.x_count) if grid.x_count > 1 else np.array(
        [0.5 * problem.length_max_m])
    rhos = problem.radius_max_m * np.arange(1, grid.radius_count + 1) / grid.radius_count
    psis = np.deg2rad(np.arange(0.0, 360.0 - 1e-9, grid.angle_step_deg))
    X, P, S = np.meshgrid(xs, rhos, psis, indexing="ij")
    return np.stack([X.ravel(), (P * np.cos(S)).ravel(), (P * np.sin(S)).ravel()], axis=-1)


@dataclass(frozen=True)
class _Best:
    score: float = -math.inf
    i1: int = -1
    i2: int = -1
    sigma: int = -1


def _full(directions: np.ndarray, r1: np.ndarray, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotors 1-8 of a batch: directions (8, 3) and positions (..., 8, 3)."""
    r = np.stack(np.broadcast_arrays(r1, r2, r2 @ _RX_PI, r1 @ _RX_PI), axis=-2)
    u = np.broadcast_to(np.vstack((directions, directions)), r.shape[:-2] + (8, 3))
    return u, np.concatenate((r, -r), axis=-2)


def search_positions(
    directions: np.ndarray,
    problem: DesignProblem,
    grid: SearchGrid,
    progress: Callable[[int], None] | None = None,
) -> tuple[RotorGeometry | None, RotorGeometry | None, int]:
    """Step 2: ``max_{R,S} M_min^V`` given ``U`` s.t. (2.5), ``d_aero >= D``.

    Returns the optimum as posed, the best flyable one (null structure (2.11), principal
    axes), either ``None`` if nothing is feasible, and the number of designs evaluated.
    """
    u = np.asarray(directions, dtype=float)
    if u.shape != (4, 3):
        raise ValueError(f"directions must be (4, 3), got {u.shape}")
    G = position_candidates(problem, grid)
    n = G.shape[0]
    gamma = problem.drag_ratio_m
    c1 = np.cross(G, u[0])  # r_1 x u_1 for every candidate r_1, (n, 3)
    c2 = np.cross(G, u[1])
    drag = gamma * _SIGMAS[:, :, None] * u[None]  # (16, 4, 3)
    # principal axes: sum r r^T off-diagonal; with the half-turn symmetry only y z survives
    yz = G[:, 1] * G[:, 2]
    best, best_fly = _Best(), _Best()
    sigma_equal = np.all(_SIGMAS == _SIGMAS[:, :1], axis=1)  # (16,): gamma part of (2.11) vanishes
    for i1 in range(n):
        # (n, 16, 4, 3) torques t_1..t_4 with r_1 = G[i1], r_2 = G[i2]
        t_geo = np.stack(np.broadcast_arrays(c1[i1], c2, c2 @ _RX_PI, c1[i1] @ _RX_PI), axis=-2)  # (n, 4, 3)
        t = t_geo[:, None] + drag[None]
        score = torque_min_weighted(t, problem.torque_weight)  # (n, 16)
        # d_aero (the costly part) only where the score could still improve an optimum
        need = score.max(axis=1) > min(best.score, best_fly.score)
        ok = np.zeros(n, dtype=bool)
        if need.any():
            ok[need] = aero_clearance_m(*_full(u, G[i1], G[need])) >= problem.clearance_min_m
        if ok.any():
            masked = np.where(ok[:, None], score, -np.inf)
            k = np.unravel_index(np.argmax(masked), masked.shape)
            if masked[k] > best.score:
                best = _Best(float(masked[k]), i1, int(k[0]), int(k[1]))
            fly = (ok & (np.abs(c1[i1, 0] - c2[:, 0]) <= _STRUCTURE_TOL)
                   & (np.abs(yz[i1] + yz) <= _STRUCTURE_TOL))[:, None] & sigma_equal[None]
            if fly.any():
                masked = np.where(fly, score, -np.inf)
                k = np.unravel_index(np.argmax(masked), masked.shape)
                if masked[k] > best_fly.score:
                    best_fly = _Best(float(masked[k]), i1, int(k[0]), int(k[1]))
        if progress is not None:
            progress(1)

    def geometry(b: _Best) -> RotorGeometry | None:
        if b.i1 < 0:
            return None
        r1, r2 = G[b.i1], G[b.i2]
        return RotorGeometry.from_pairs(u, np.stack((r1, r2, r2 @ _RX_PI, r1 @ _RX_PI)), _SIGMAS[b.sigma], gamma)

    return geometry(best), geometry(best_fly), n * n * len(_SIGMAS)


@dataclass(frozen=True)
class SearchResult:
    """Both steps' outcome: the directions, the optimum as posed and the best flyable design with their metrics."""

    directions: DirectionResult
    optimum: RotorGeometry | None
    optimum_metrics: DesignMetrics | None
    flyable: RotorGeometry | None
    flyable_metrics: DesignMetrics | None
    n_position_designs: int


def search(
    problem: DesignProblem | None = None,
    grid: SearchGrid | None = None,
    progress: Callable[[int], None] | None = None,
) -> SearchResult:
    """The sequential grid search (2.4)-(2.6): step 1 (:func:`search_directions`), then step 2 (:func:`search_positions`).

    Defaults: Table 2.1's problem (:class:`DesignProblem`) and the default :class:`SearchGrid`.
    """
    problem = DesignProblem() if problem is None else problem
    grid = SearchGrid() if grid is None else grid
    d = search_directions(problem, grid)
    optimum, flyable, count = search_positions(d.directions, problem, grid, progress)
    return SearchResult(
        directions=d,
        optimum=optimum,
        optimum_metrics=None if optimum is None else evaluate(optimum, problem),
        flyable=flyable,
        flyable_metrics=None if flyable is None else evaluate(flyable, problem),
        n_position_designs=count,
    )


def n_position_steps(problem: DesignProblem, grid: SearchGrid) -> int:
    """How many ``progress(1)`` calls :func:`search` makes (for a progress bar's total)."""
    return position_candidates(problem, grid).shape[0]

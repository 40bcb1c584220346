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
  ``F_min^W``. The grid's best few points are then refined continuously over the same ``(a, e)``
  (:func:`refine_directions`): SLSQP on the epigraph form ``max t s.t. d_ij(a, e) >= t`` of the
  max-min (``d_ij`` the facet distances of ``V_F`` stretched by ``1/W``), then Nelder-Mead on the
  max-min itself (for kinks), each kept only where it beats its start. Secondary criterion: among
  directions within a relative ``direction_tie_tolerance`` (default 0.1 %) of the best ``F_min^W``
  found, the largest ``F_min`` (again refined: ``max t s.t. d_ij >= t``,
  ``F_min^W >= (1 - tol) F_min^W*``); the thesis reports both for its design, and ``F_min^W`` is nearly flat where ``F_min`` still grows (Table 2.1's problem: the
  window costs 0.1 % of ``F_min^W`` = ``F_min^xz``, 3.849 -> 3.845, and gains 1.1 % of ``F_min``,
  2.022 -> 2.043). Deterministic (fixed starts, no randomness). Over all 4-direction sets the best
  ``F_min^W`` is the same 3.849 (checked by multistart SLSQP): the family loses nothing.
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

import logging
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from companion.configfile import require_positive
from companion.skeleton.rotors import RotorGeometry

from .metrics import (
    DesignMetrics,
    DesignProblem,
    aero_clearance_m,
    evaluate,
    force_min,
    force_min_weighted,
    force_min_xz,
    torque_min_weighted,
    zonotope_facet_distances,
    zonotope_inradius,
)

__all__ = ["DirectionResult", "SearchGrid", "SearchResult", "mirror_directions", "n_position_steps",
           "position_candidates", "refine_directions", "search", "search_directions", "search_positions"]

log = logging.getLogger(__name__)

#: Tolerance of the structural constraints (null structure, principal axes) on grid values.
_STRUCTURE_TOL = 1e-9
_RX_PI = np.diag([1.0, -1.0, -1.0])
_SIGMAS = np.array([[1.0 if (k >> b) & 1 else -1.0 for b in range(4)] for k in range(16)])


@dataclass(frozen=True)
class SearchGrid:
    """Grid resolution of the two steps and step 1's continuous refinement.

    Attributes:
        direction_step_deg: step of the azimuth/elevation grid of ``u_1`` (step 1).
        x_count: number of ``r_x`` values in ``[0, L_max/2]`` (step 2).
        radius_count: number of ``rho`` values, ``R_max k / radius_count``, ``k = 1..radius_count``.
        angle_step_deg: step of the angle ``psi`` about the bar; must divide 360.
        refine_directions: refine step 1's grid optimum continuously (:func:`refine_directions`).
        direction_tie_tolerance: relative window of ``F_min^W`` below its best within which the
            larger ``F_min`` wins (step 1's secondary criterion), in ``[0, 0.1]``; 0: ``F_min^W`` only.
    """

    direction_step_deg: float = 0.5
    x_count: int = 5
    radius_count: int = 3
    angle_step_deg: float = 7.5
    refine_directions: bool = True
    direction_tie_tolerance: float = 1e-3

    def __post_init__(self) -> None:
        require_positive(self, "direction_step_deg", "angle_step_deg")
        tol = self.direction_tie_tolerance
        if not (isinstance(tol, int | float) and math.isfinite(tol) and 0.0 <= tol <= 0.1):
            raise ValueError(f"direction_tie_tolerance must be in [0, 0.1], got {tol}")
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
    """Step 1's optimum: ``u_1..u_4`` (4, 3), its angles [deg] and metrics (x lambda_max).

    ``f_min_weighted``, ``f_min``, ``f_min_xz``: of the chosen directions; ``f_min_weighted_best``:
    the best ``F_min^W`` found (the reference of the tie window; ``>= grid_f_min_weighted``, the
    grid's best); ``refined``: the chosen directions come from the continuous refinement.
    """

    directions: np.ndarray
    azimuth_deg: float
    elevation_deg: float
    f_min_weighted: float
    f_min: float
    n_evaluated: int
    n_feasible: int
    f_min_xz: float
    f_min_weighted_best: float
    grid_f_min_weighted: float
    tie_tolerance: float
    refined: bool


#: Bound of a facet distance in the optimiser's constraints (a degenerate pair spans no facet: no constraint).
_DISTANCE_CAP = 1e3
_ANGLE_BOUNDS = ((0.0, 90.0), (0.0, 90.0))


def _facet_distances(angles_deg: np.ndarray, weight: np.ndarray | None) -> np.ndarray:
    """The facet distances of ``V_F`` (stretched by ``1/weight``) at ``(a, e)`` [deg], capped finite."""
    u = mirror_directions(*np.deg2rad(np.asarray(angles_deg, dtype=float)))
    return np.minimum(zonotope_facet_distances(u if weight is None else u / weight), _DISTANCE_CAP)


def _epigraph_max(x0: np.ndarray, weight: np.ndarray | None, floor: tuple[np.ndarray, float] | None) -> np.ndarray:
    """SLSQP on ``max_{a,e,t} t s.t. d_ij(a, e) >= t`` (and ``min d^floor_ij >= level`` if ``floor``); the new ``(a, e)``.

    ``weight``: the stretch of the maximised distances (``1/W``; None: ``F_min``); ``floor``:
    ``(weight, level)`` of a lower bound on a second min (the tie window on ``F_min^W``). The
    caller checks the result (nonsmooth points, a failed run): it may be no better than ``x0``.
    """
    t0 = float(_facet_distances(x0, weight).min())
    cons = [{"type": "ineq", "fun": lambda z: _facet_distances(z[:2], weight) - z[2]}]
    if floor is not None:
        w_floor, level = floor
        cons.append({"type": "ineq", "fun": lambda z: _facet_distances(z[:2], w_floor) - level})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = minimize(lambda z: -z[2], np.r_[x0, t0], method="SLSQP", constraints=cons,
                       bounds=(*_ANGLE_BOUNDS, (None, None)), options={"ftol": 1e-14, "maxiter": 200})
    x = np.clip(np.asarray(res.x[:2], dtype=float), 0.0, 90.0)
    return x if np.all(np.isfinite(x)) else np.asarray(x0, dtype=float)


def _metrics_at(angles_deg: np.ndarray, weight: np.ndarray) -> tuple[float, float]:
    """``(F_min^W, F_min)`` at ``(a, e)`` [deg] (the public metric functions); ``-inf`` off ``[0, 90]^2``."""
    x = np.asarray(angles_deg, dtype=float)
    if not (np.all(np.isfinite(x)) and np.all((x >= 0.0) & (x <= 90.0))):
        return -math.inf, -math.inf
    u = mirror_directions(*np.deg2rad(x))
    fw, f = zonotope_inradius(np.stack((u / weight, u)))  # force_min_weighted, force_min in one batch
    return float(fw), float(f)


#: Edge of Nelder-Mead's first simplex [deg] and its stopping tolerances.
_SIMPLEX_DEG = 0.25
_NM_OPTIONS = {"xatol": 1e-8, "fatol": 1e-13, "maxiter": 600}


def _improve(x0: np.ndarray, key: Callable[[np.ndarray], tuple[float, float]],
             slsqp: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The best by ``key`` (lexicographic; ``-inf`` first: infeasible) of ``x0``, SLSQP from it, Nelder-Mead after.

    SLSQP (the epigraph form) is exact where the active facets are smooth; at a kink (a symmetry
    line such as ``a = 45 deg`` with ``W_x = W_y``) it can stop short, and Nelder-Mead on the
    max-min itself (infeasible points worth ``+inf``: an extreme barrier) finishes the job.
    """
    best, best_key = np.asarray(x0, dtype=float), key(x0)
    y = slsqp(best)
    y_key = key(y)
    if y_key > best_key:
        best, best_key = y, y_key
    simplex = np.stack([best, best + (_SIMPLEX_DEG, 0.0), best + (0.0, _SIMPLEX_DEG)])

    def cost(x: np.ndarray) -> float:
        v = key(x)[0]
        return -v if math.isfinite(v) else math.inf

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        z = np.asarray(minimize(cost, best, method="Nelder-Mead",
                                options={**_NM_OPTIONS, "initial_simplex": simplex}).x, dtype=float)
    return z if key(z) > best_key else best


def refine_directions(
    starts_deg: np.ndarray,
    problem: DesignProblem,
    tie_tolerance: float = 1e-3,
    tie_starts_deg: np.ndarray | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Continuous refinement of step 1 over the mirror family's ``(a, e)`` [deg].

    1. From each of ``starts_deg`` (k, 2), ``max F_min^W`` (SLSQP on the epigraph form, then
       Nelder-Mead); a result replaces its start only if better, so ``F_min^W*`` is never below
       the starts' best.
    2. The secondary criterion: from the best point of 1 and each of ``tie_starts_deg`` (e.g. the
       grid's own choice), ``max F_min s.t. F_min^W >= max((1 - tie_tolerance) F_min^W*, m g)``
       (never below ``m g``); the winner by ``F_min``, then ``F_min^W``.

    Returns ``(angles of the chosen directions, F_min^W*, angles of F_min^W*)``.
    """
    weight = np.asarray(problem.force_weight, dtype=float)
    starts = np.atleast_2d(np.asarray(starts_deg, dtype=float))
    if starts.ndim != 2 or starts.shape[1] != 2 or not len(starts):
        raise ValueError(f"starts_deg must be (k, 2) angles [deg], got shape {starts.shape}")
    if not (math.isfinite(tie_tolerance) and 0.0 <= tie_tolerance <= 0.1):
        raise ValueError(f"tie_tolerance must be in [0, 0.1], got {tie_tolerance}")

    def weighted(x: np.ndarray) -> tuple[float, float]:
        fw, f = _metrics_at(x, weight)
        return (fw, f) if fw >= problem.weight_lambda else (-math.inf, -math.inf)

    best_x, best_key = starts[0], weighted(starts[0])
    for x0 in starts:
        x = _improve(x0, weighted, lambda z: _epigraph_max(z, weight, None))
        x_key = weighted(x)
        if x_key > best_key:
            best_x, best_key = x, x_key
    best_fw = best_key[0]
    if not math.isfinite(best_fw):
        raise ValueError(f"no start reaches F_min^W >= m g = {problem.weight_lambda:.3f} lambda_max")
    level = max((1.0 - tie_tolerance) * best_fw, problem.weight_lambda)
    # SLSQP ends on its constraint, either side by round-off: it aims 1e-9 inside the window
    inner = level + 1e-9 * abs(best_fw)

    def secondary(x: np.ndarray) -> tuple[float, float]:
        fw, f = _metrics_at(x, weight)
        return (f, fw) if fw >= level else (-math.inf, -math.inf)

    chosen, chosen_key = best_x, secondary(best_x)
    if tie_tolerance > 0:
        seeds = [best_x] + ([] if tie_starts_deg is None else list(np.atleast_2d(tie_starts_deg)))
        for x0 in seeds:
            x = _improve(x0, secondary, lambda z: _epigraph_max(z, None, (weight, inner)))
            x_key = secondary(x)
            if x_key > chosen_key:
                chosen, chosen_key = x, x_key
    return np.asarray(chosen, dtype=float), best_fw, np.asarray(best_x, dtype=float)


def _grid_local_maxima(values: np.ndarray) -> np.ndarray:
    """Mask of the points no lower than any of their (up to 8) grid neighbours."""
    padded = np.pad(values, 1, constant_values=-np.inf)
    peak = np.ones(values.shape, dtype=bool)
    n0, n1 = values.shape
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                peak &= values >= padded[1 + di:1 + di + n0, 1 + dj:1 + dj + n1]
    return peak


#: How many grid optima (local maxima of ``F_min^W``, best first) seed the refinement.
_N_STARTS = 3


def search_directions(problem: DesignProblem, grid: SearchGrid) -> DirectionResult:
    """Step 1: ``argmax_U F_min^W(U)`` s.t. ``F_min^W >= m g`` over the mirror family.

    On the ``(a, e)`` grid, then (``grid.refine_directions``) refined from the grid's
    ``_N_STARTS`` best local maxima; within ``grid.direction_tie_tolerance`` of the best
    ``F_min^W`` the larger ``F_min`` wins (module docstring).
    """
    deg = np.arange(0.0, 90.0 + 1e-9, grid.direction_step_deg)
    A, E = np.meshgrid(deg, deg, indexing="ij")
    U = mirror_directions(np.deg2rad(A), np.deg2rad(E))
    weight = np.asarray(problem.force_weight, dtype=float)
    fw = force_min_weighted(U, weight)
    feasible = fw >= problem.weight_lambda
    if not feasible.any():
        raise ValueError(f"no direction set reaches F_min^W >= m g = {problem.weight_lambda:.3f} lambda_max "
                         f"(best {fw.max():.3f}); raise thrust_max_n or lower mass_kg")
    f = force_min(U)
    score = np.where(feasible, fw, -np.inf)
    grid_best = float(score.max())
    tol = grid.direction_tie_tolerance
    # the grid's own choice: the largest F_min within the window (to 1e-12 when tol = 0)
    window = feasible & (fw >= (1.0 - tol) * grid_best - 1e-12 * grid_best)
    k = np.unravel_index(np.argmax(np.where(window, f, -np.inf)), f.shape)
    angles = np.array([A[k], E[k]])
    best_fw = grid_best
    refined = False
    if grid.refine_directions:
        peaks = np.flatnonzero((_grid_local_maxima(score) & feasible).ravel())
        order = peaks[np.argsort(-score.ravel()[peaks], kind="stable")][:_N_STARTS]
        starts = np.stack([A.ravel()[order], E.ravel()[order]], axis=-1)
        x, best_fw, _ = refine_directions(starts, problem, tol, tie_starts_deg=angles[None])
        refined = not np.array_equal(x, angles)
        angles = x
        log.debug("step 1: grid F_min^W %.6f -> refined %.6f; chosen (a, e) = (%.4f, %.4f) deg",
                  grid_best, best_fw, *angles)
    u = mirror_directions(*np.deg2rad(angles))
    return DirectionResult(
        directions=u,
        azimuth_deg=float(angles[0]),
        elevation_deg=float(angles[1]),
        f_min_weighted=float(force_min_weighted(u, weight)),
        f_min=float(force_min(u)),
        n_evaluated=int(fw.size),
        n_feasible=int(feasible.sum()),
        f_min_xz=float(force_min_xz(u)),
        f_min_weighted_best=float(best_fw),
        grid_f_min_weighted=grid_best,
        tie_tolerance=float(tol),
        refined=refined,
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

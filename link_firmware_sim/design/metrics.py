"""Design metrics of an ODAR link (thesis sec. 2.2.2): guaranteed force and torque, aerodynamic clearance.

Pure numpy, batched: every function takes arrays with any leading batch shape ``(..., m, 3)``.

Feasible wrench volumes
-----------------------
With the rotor pairs ``(j, j + n/2)`` as actuator units, the feasible control force volume
``V_F`` (and torque volume ``V_M``) is the zonotope ``{sum_k mu_k g_k, |mu_k| <= 2 lambda_max}``
of the pair generators ``g_k = u_k`` (``t_k``), ``k in N_h = {1..n/2}``. Its facets are spanned
by pairs ``(g_i, g_j)``; the facet's distance from the origin along ``n_ij = g_i x g_j`` is
``d_ij = sum_k 2 lambda_max |n_ij^T g_k| / ||n_ij||`` (sec. 2.2.2, from [29]). Then

* ``F_min(U) = min_ij d_ij`` (eq. 2.2): the radius of the largest origin-centred ball in ``V_F``;
* ``F_min^W(U)``: (2.2) with ``W^-1 u_k`` in place of ``u_k`` (``W = diag(W_x, W_y, W_z)``,
  ``0 < W <= 1``): the ball in ``V_F`` stretched by ``1/W``;
* ``F_min^xz(U)`` (Table 2.1; the guaranteed force "within the sagittal XZ-plane", sec. 2.2.2):
  the radius of the largest origin-centred disc in the section ``V_F`` and the body XZ plane,
  ``min_ij d_ij / ||P_xz n_ij / ||n_ij||| ``, ``P_xz`` the projection on that plane
  (the limit ``W_y -> 0`` of ``F_min^W``);
* ``M_min(U, R, S)`` (eq. 2.3) and ``M_min^V``: the same with ``t_k`` (eq. 2.1) and ``V``.

Degenerate pairs (``g_i || g_j``) span no facet and are skipped; generators of rank < 3 give 0.

Aerodynamic clearance ``d_aero`` (constraint 2.6)
-------------------------------------------------
``d_aero(U, R) = min_{i != j} min_{c in C_a,i} ||c - r_j||`` with the flow volume of rotor ``i``
``C_a,i = {R_BU_i v + r_i : sqrt(v_x^2 + v_y^2) <= r_a(v_z)}``. The thesis obtains ``r_a`` from
an anemometer survey (Fig. 2-3, not reproduced in the text) as a *tapered cylinder* bounded by
the 4 m/s interference threshold. The flow-volume function derived here (:class:`FlowVolume`),
with ``z`` the distance downstream of the rotor disc along the rotor axis::

    r_a(z) = r_0 - (r_0 - r_e) z / L     for 0 <= z <= L   (empty elsewhere)

Assumptions (every one a default of :class:`FlowVolume`, all configurable):

* ``r_0 = 0.127 m``: the slipstream leaves the disc with the propeller radius (10-inch props,
  sec. 2.5.1);
* ``r_e = r_0 / sqrt(2) = 0.0898 m``: the fully contracted slipstream of momentum theory (the
  far-wake area is half the disc area), reached at ``z = L``; the linear taper in between is the
  "tapered cylinder" of Fig. 2-3;
* ``L = 1.0 m``: the hover slipstream (about 10 m/s in the far wake at the 3.2 N hover thrust)
  stays above 4 m/s further than the module's own span (0.93 m between the farthest rotors), so
  the flow never ends within the module;
* both directions (``z -> |z|``): the rotors are reversible, so the flow leaves whichever face
  the thrust sign picks; the design must hold for both.

The distance from ``r_j`` to the solid of revolution ``C_a,i`` is the planar distance, in the
meridian half-plane ``(rho, z)``, from ``r_j``'s axial/radial coordinates to the trapezoid
``{0 <= z <= L, 0 <= rho <= r_a(z)}`` (exact: the solid is convex and rotationally symmetric).
On Table 2.1 this gives ``d_aero = 0.131 m`` (thesis: 0.125 m; the bound ``D = 0.12 m``).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_positive
from companion.skeleton.body import GRAVITY_M_S2
from companion.skeleton.rotors import RotorGeometry

__all__ = [
    "DesignMetrics",
    "DesignProblem",
    "FlowVolume",
    "OdarDesign",
    "aero_clearance_m",
    "evaluate",
    "flow_radius_m",
    "force_min",
    "force_min_weighted",
    "force_min_xz",
    "torque_generators",
    "torque_min",
    "torque_min_weighted",
    "zonotope_facet_distances",
    "zonotope_inradius",
    "zonotope_plane_inradius",
]

#: Relative size below which ``||g_i x g_j||`` counts as parallel generators (no facet).
_PARALLEL_TOL = 1e-12
_XZ_ROWS = (0, 2)


def _pairs(m: int) -> tuple[list[int], list[int]]:
    idx = list(itertools.combinations(range(m), 2))
    return [i for i, _ in idx], [j for _, j in idx]


def _facets(generators: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Facet normals ``n_ij = g_i x g_j`` (..., P, 3) and ``sum_k |n_ij^T g_k|`` (..., P)."""
    g = np.asarray(generators, dtype=float)
    if g.ndim < 2 or g.shape[-1] != 3 or g.shape[-2] < 2:
        raise ValueError(f"generators must have shape (..., m, 3) with m >= 2, got {g.shape}")
    i, j = _pairs(g.shape[-2])
    n = np.cross(g[..., i, :], g[..., j, :])
    support = np.abs(np.einsum("...pc,...kc->...pk", n, g)).sum(axis=-1)
    return n, support


def _min_ratio(num: np.ndarray, den: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``min_p num/den`` over pairs with ``den > tol * scale``; 0 where no pair qualifies."""
    ok = den > _PARALLEL_TOL * scale[..., None]
    ratio = np.where(ok, num / np.where(ok, den, 1.0), np.inf).min(axis=-1)
    return np.where(np.isinf(ratio), 0.0, ratio)


def _scale(generators: np.ndarray) -> np.ndarray:
    return np.max(np.sum(np.asarray(generators, dtype=float) ** 2, axis=-1), axis=-1)


def zonotope_inradius(generators: np.ndarray, lambda_max: float = 1.0) -> np.ndarray:
    """Radius of the largest origin-centred ball in ``{sum_k mu_k g_k : |mu_k| <= 2 lambda_max}`` (eq. 2.2 form).

    ``generators`` (..., m, 3): the pair generators (``u_k`` or ``t_k``, ``k in N_h``).
    """
    n, support = _facets(generators)
    return 2.0 * lambda_max * _min_ratio(support, np.linalg.norm(n, axis=-1), _scale(generators))


def zonotope_facet_distances(generators: np.ndarray, plane_rows=None, lambda_max: float = 1.0) -> np.ndarray:
    """Per facet pair ``(g_i, g_j)``: its distance from the origin, (..., P); ``inf`` where ``g_i || g_j``.

    The smooth pieces whose minimum is :func:`zonotope_inradius` (``plane_rows=None``) or, with
    ``plane_rows``, :func:`zonotope_plane_inradius` (the in-plane distance ``d / ||P n||``);
    for smooth optimisers (the epigraph form ``max t s.t. every distance >= t``).
    """
    n, support = _facets(generators)
    den = np.linalg.norm(n if plane_rows is None else n[..., list(plane_rows)], axis=-1)
    ok = den > _PARALLEL_TOL * _scale(generators)[..., None]
    return np.where(ok, 2.0 * lambda_max * support / np.where(ok, den, 1.0), np.inf)


def zonotope_plane_inradius(generators: np.ndarray, plane_rows=_XZ_ROWS, lambda_max: float = 1.0) -> np.ndarray:
    """Radius of the largest origin-centred disc in the zonotope's section by a coordinate plane.

    ``plane_rows``: the two body axes spanning the plane (default X and Z: the sagittal plane).
    A facet ``n^T f <= d`` bounds the section at in-plane distance ``d / ||P n||``.
    """
    n, support = _facets(generators)
    n_plane = np.linalg.norm(n[..., list(plane_rows)], axis=-1)
    return 2.0 * lambda_max * _min_ratio(support, n_plane, _scale(generators))


def _weights(weight, name: str) -> np.ndarray:
    w = np.asarray(weight, dtype=float)
    if w.shape != (3,) or not np.all((w > 0) & (w <= 1)):
        raise ValueError(f"{name} must be 3 numbers in (0, 1], got {weight}")
    return w


def force_min(directions: np.ndarray, lambda_max: float = 1.0) -> np.ndarray:
    """``F_min(U)`` of eq. (2.2); ``directions`` (..., n/2, 3) are ``u_1..u_{n/2}`` [units of ``lambda_max``]."""
    return zonotope_inradius(directions, lambda_max)


def force_min_weighted(directions: np.ndarray, weight=(1.0, 0.4, 1.0), lambda_max: float = 1.0) -> np.ndarray:
    """``F_min^W(U)`` of sec. 2.2.2: (2.2) with ``W^-1 u_k``, ``W = diag(weight)``, ``0 < W <= 1``."""
    return zonotope_inradius(np.asarray(directions, dtype=float) / _weights(weight, "weight"), lambda_max)


def force_min_xz(directions: np.ndarray, lambda_max: float = 1.0) -> np.ndarray:
    """``F_min^xz(U)``: the guaranteed force within the body XZ (sagittal) plane (Table 2.1)."""
    return zonotope_plane_inradius(directions, _XZ_ROWS, lambda_max)


def torque_generators(directions: np.ndarray, positions_m: np.ndarray, spin: np.ndarray, drag_ratio_m: float) -> np.ndarray:
    """``t_j = r_j x u_j + gamma sigma_j u_j`` of eq. (2.1), batched: (..., m, 3) [m]."""
    u = np.asarray(directions, dtype=float)
    return np.cross(np.asarray(positions_m, dtype=float), u) + drag_ratio_m * np.asarray(spin, dtype=float)[..., None] * u


def torque_min(torques: np.ndarray, lambda_max: float = 1.0) -> np.ndarray:
    """``M_min(U, R, S)`` of eq. (2.3) from the pair torques ``t_1..t_{n/2}`` (..., n/2, 3)."""
    return zonotope_inradius(torques, lambda_max)


def torque_min_weighted(torques: np.ndarray, weight=(1.0, 1.0, 1.0), lambda_max: float = 1.0) -> np.ndarray:
    """``M_min^V``: (2.3) with ``V^-1 t_k``, ``V = diag(weight)``, ``0 < V <= 1``."""
    return zonotope_inradius(np.asarray(torques, dtype=float) / _weights(weight, "weight"), lambda_max)


@dataclass(frozen=True)
class FlowVolume:
    """The tapered-cylinder flow volume ``r_a`` of Fig. 2-3 (module docstring: the function and its assumptions).

    Attributes:
        radius_at_rotor_m: ``r_0``, the flow radius at the rotor disc [m].
        radius_at_end_m: ``r_e``, the radius at ``z = length_m`` [m] (``<= r_0``: tapered).
        length_m: ``L``, how far downstream the flow stays above the 4 m/s threshold [m].
        both_directions: the flow may leave either face of the (reversible) rotor.
    """

    radius_at_rotor_m: float = 0.127
    radius_at_end_m: float = 0.127 / math.sqrt(2.0)
    length_m: float = 1.0
    both_directions: bool = True

    def __post_init__(self) -> None:
        require_positive(self, "radius_at_rotor_m", "length_m")
        if not 0.0 <= self.radius_at_end_m <= self.radius_at_rotor_m:
            raise ValueError(f"radius_at_end_m must be in [0, radius_at_rotor_m] (a tapered cylinder), "
                             f"got {self.radius_at_end_m}")


def flow_radius_m(z_m: np.ndarray, flow: FlowVolume = FlowVolume()) -> np.ndarray:
    """``r_a(z)`` [m] at downstream distances ``z_m``; NaN outside the flow (``z < 0`` one-way, ``|z| > L``)."""
    z = np.asarray(z_m, dtype=float)
    z = np.abs(z) if flow.both_directions else z
    r = flow.radius_at_rotor_m - (flow.radius_at_rotor_m - flow.radius_at_end_m) * z / flow.length_m
    return np.where((z >= 0.0) & (z <= flow.length_m), r, np.nan)


def _segment_distance(px, pz, a, b) -> np.ndarray:
    """Distance from points ``(px, pz)`` to the segment ``a``-``b`` (2-tuples) in the plane."""
    dx, dz = b[0] - a[0], b[1] - a[1]
    t = np.clip(((px - a[0]) * dx + (pz - a[1]) * dz) / (dx * dx + dz * dz), 0.0, 1.0)
    return np.hypot(px - (a[0] + t * dx), pz - (a[1] + t * dz))


def _trapezoid_distance(rho: np.ndarray, z: np.ndarray, flow: FlowVolume) -> np.ndarray:
    """Distance from meridian points ``(rho >= 0, z)`` to ``{0 <= z <= L, 0 <= rho <= r_a(z)}``."""
    r0, re, L = flow.radius_at_rotor_m, flow.radius_at_end_m, flow.length_m
    inside = (z >= 0.0) & (z <= L) & (rho <= r0 - (r0 - re) * z / L)
    corners = ((0.0, 0.0), (r0, 0.0), (re, L), (0.0, L))
    d = np.min([_segment_distance(rho, z, corners[k], corners[(k + 1) % 4]) for k in range(4)], axis=0)
    return np.where(inside, 0.0, d)


def aero_clearance_m(directions: np.ndarray, positions_m: np.ndarray, flow: FlowVolume = FlowVolume()) -> np.ndarray:
    """``d_aero(U, R)`` of (2.6) [m]: the least distance from a rotor centre ``r_j`` to another rotor's flow.

    ``directions``, ``positions_m``: (..., n, 3), all ``n`` rotors (the flow of rotor ``i``
    goes along ``-u_i``, the positive-thrust wake, and along ``+u_i`` too if
    ``flow.both_directions``).
    """
    u = np.asarray(directions, dtype=float)
    r = np.asarray(positions_m, dtype=float)
    if u.shape != r.shape or u.ndim < 2 or u.shape[-1] != 3:
        raise ValueError(f"directions and positions_m must both have shape (..., n, 3), got {u.shape}, {r.shape}")
    n = u.shape[-2]
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    i, j = np.nonzero(~np.eye(n, dtype=bool))
    d = r[..., j, :] - r[..., i, :]
    axial = np.einsum("...pc,...pc->...p", d, u[..., i, :])
    rho = np.linalg.norm(d - axial[..., None] * u[..., i, :], axis=-1)
    z = np.abs(axial) if flow.both_directions else -axial
    return _trapezoid_distance(rho, z, flow).min(axis=-1)


@dataclass(frozen=True)
class DesignProblem:
    """The design problem (2.4)-(2.6) and its parameters (thesis Table 2.1, sec. 2.2.2); TOML ``[design]``.

    Attributes:
        radius_max_m: ``R_max`` of ``R_max`` (rotor distance from the bar axis) [m].
        length_max_m: ``L_max``, the bar's length: ``|r_x| <= L_max / 2`` [m].
        force_weight: ``W = diag(...)`` of ``F_min^W``, each in (0, 1].
        torque_weight: ``V = diag(...)`` of ``M_min^V``, each in (0, 1].
        clearance_min_m: ``D`` of (2.6) [m].
        thrust_max_n: ``lambda_max = -lambda_min`` [N] (sec. 2.2.2: 9.7 N).
        mass_kg: the module's mass ``m`` of ``F_min^W >= m g`` (sec. 2.5.1: 2.6 kg).
        drag_ratio_m: ``gamma`` of eq. (2.1) [m].
        volume_tolerance_m: slack of the volume check: Table 2.1 prints positions to 0.01 m and
            its ``(r_y, r_z) = (0.17, 0.17)`` lies 0.4 mm outside ``R_max = 0.24``.
        flow: the flow volume of ``d_aero`` (``[design.flow]``).
    """

    radius_max_m: float = 0.24
    length_max_m: float = 0.8
    force_weight: tuple[float, float, float] = (1.0, 0.4, 1.0)
    torque_weight: tuple[float, float, float] = (1.0, 1.0, 1.0)
    clearance_min_m: float = 0.12
    thrust_max_n: float = 9.7
    mass_kg: float = 2.6
    drag_ratio_m: float = 0.02
    volume_tolerance_m: float = 1e-3
    flow: FlowVolume = field(default_factory=FlowVolume)

    def __post_init__(self) -> None:
        require_positive(self, "radius_max_m", "length_max_m", "thrust_max_n", "mass_kg")
        for name in ("force_weight", "torque_weight"):
            _weights(getattr(self, name), name)
        for name in ("clearance_min_m", "drag_ratio_m", "volume_tolerance_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")

    @property
    def weight_lambda(self) -> float:
        """``m g / lambda_max``: the bound ``F_min^W >= m g`` of (2.6) in units of ``lambda_max``."""
        return self.mass_kg * GRAVITY_M_S2 / self.thrust_max_n

    def within_volume(self, positions_m: np.ndarray) -> np.ndarray:
        """Constraint (2.5): every ``r`` in ``R_max`` (``sqrt(r_y^2 + r_z^2) <= R_max``, ``|r_x| <= L_max/2``)."""
        r = np.asarray(positions_m, dtype=float)
        tol = self.volume_tolerance_m
        radial = np.hypot(r[..., 1], r[..., 2]) <= self.radius_max_m + tol
        axial = np.abs(r[..., 0]) <= 0.5 * self.length_max_m + tol
        return np.all(radial & axial, axis=-1)


@dataclass(frozen=True)
class DesignMetrics:
    """The metrics of one geometry (sec. 2.2.2). Wrench figures in units of ``lambda_max``.

    ``f_min`` (2.2), ``f_min_weighted`` (``F_min^W``), ``f_min_xz`` (sagittal plane),
    ``m_min`` (2.3), ``m_min_weighted`` (``M_min^V``); ``d_aero_m`` (2.6); the constraints
    (2.5)-(2.6) (``weight_ok``: ``F_min^W >= m g``; ``clearance_ok``: ``d_aero >= D``);
    ``null_structure``: (2.11) holds, so the firmware's allocation can fly it.
    """

    f_min: float
    f_min_weighted: float
    f_min_xz: float
    m_min: float
    m_min_weighted: float
    d_aero_m: float
    within_volume: bool
    weight_ok: bool
    clearance_ok: bool
    null_structure: bool

    @property
    def feasible(self) -> bool:
        """All of (2.5)-(2.6)."""
        return self.within_volume and self.weight_ok and self.clearance_ok

    def as_dict(self, thrust_max_n: float | None = None) -> dict:
        """JSON form: ``F_min``, ``F_min_xz``, ``M_min`` (x lambda_max), ``d_aero_m`` and the rest."""
        out = {
            "F_min": self.f_min,
            "F_min_xz": self.f_min_xz,
            "M_min": self.m_min,
            "d_aero_m": self.d_aero_m,
            "F_min_W": self.f_min_weighted,
            "M_min_V": self.m_min_weighted,
            "within_volume": self.within_volume,
            "weight_ok": self.weight_ok,
            "clearance_ok": self.clearance_ok,
            "feasible": self.feasible,
            "null_structure_2_11": self.null_structure,
        }
        if thrust_max_n is not None:
            out["in_newtons"] = {"F_min_n": self.f_min * thrust_max_n, "F_min_xz_n": self.f_min_xz * thrust_max_n,
                                 "F_min_W_n": self.f_min_weighted * thrust_max_n, "M_min_nm": self.m_min * thrust_max_n}
        return out


def evaluate(geometry: RotorGeometry, problem: DesignProblem = DesignProblem()) -> DesignMetrics:
    """All metrics of ``geometry`` (8 rotors with the pair symmetry; rotors 1-4 are the pair generators).

    The torques use ``geometry.drag_ratio`` (``gamma``); ``problem`` gives the weights, bounds
    and the flow volume. Wrench figures in units of ``lambda_max``.
    """
    n_half = geometry.directions.shape[0] // 2
    u = geometry.directions[:n_half]
    t = geometry.torque_per_thrust()[:n_half]
    fw = float(force_min_weighted(u, problem.force_weight))
    d_aero = float(aero_clearance_m(geometry.directions, geometry.positions_m, problem.flow))
    return DesignMetrics(
        f_min=float(force_min(u)),
        f_min_weighted=fw,
        f_min_xz=float(force_min_xz(u)),
        m_min=float(torque_min(t)),
        m_min_weighted=float(torque_min_weighted(t, problem.torque_weight)),
        d_aero_m=d_aero,
        within_volume=bool(problem.within_volume(geometry.positions_m)),
        weight_ok=fw >= problem.weight_lambda,
        clearance_ok=d_aero >= problem.clearance_min_m,
        null_structure=geometry.has_null_structure(tol=1e-9),
    )


class OdarDesign:
    """Thin object over :func:`evaluate`: one geometry under one design problem."""

    def __init__(self, geometry: RotorGeometry, problem: DesignProblem = DesignProblem()) -> None:
        self.geometry = geometry
        self.problem = problem

    def metrics(self) -> DesignMetrics:
        return evaluate(self.geometry, self.problem)

    def force_volume_vertices_n(self) -> np.ndarray:
        """Vertices of ``V_F`` [N] (body frame), for plots: the zonotope's sums of ``+-2 lambda_max u_k``."""
        return _zonotope_points(self.geometry.directions[: self.geometry.directions.shape[0] // 2],
                                self.problem.thrust_max_n)

    def torque_volume_vertices_nm(self) -> np.ndarray:
        """Vertices of ``V_M`` [Nm] (body frame)."""
        t = self.geometry.torque_per_thrust()
        return _zonotope_points(t[: t.shape[0] // 2], self.problem.thrust_max_n)


def _zonotope_points(generators: np.ndarray, lambda_max: float) -> np.ndarray:
    """All ``2^m`` corner sums ``sum_k +-2 lambda_max g_k`` (the zonotope is their convex hull)."""
    g = np.asarray(generators, dtype=float)
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=g.shape[0])))
    return 2.0 * lambda_max * signs @ g

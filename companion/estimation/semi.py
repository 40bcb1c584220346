"""Semi-distributed constraint application (paper sec. III-B): Alg. 2 and eq. 6.

The chain is split into contiguous groups ``G_1 .. G_s`` (left to right). Each group runs
the constraint application of Alg. 1 on its own links only (Alg. 2: the *local* step).
The joints between groups are then closed by the *global* step (eq. 6): attitudes are
held fixed and each group ``g`` is shifted rigidly by one ``Dx_g = [Dp_g; Dv_g]``::

    min  sum_i Dx_{G(i)}^T Pbar_i^-1 Dx_{G(i)}   s.t.  c^G(x + Dx) = 0

with ``Pbar_i`` the [p; v] covariance of link ``i`` after the local step. The objective
collapses to ``sum_g Dx_g^T Lambda_g Dx_g`` with ``Lambda_g = sum_{i in G_g} Pbar_i^-1``
and the constraints are linear, ``Dx_{g+1} = Dx_g + c^G_g`` where ``c^G_g`` is the [position;
velocity] difference between the right tip of group ``g`` and the left tip of group
``g+1``. With ``s_1 = 0`` and ``s_{g+1} = s_g + c^G_g`` the closed form is::

    Dx_1 = -(sum_g Lambda_g)^-1 sum_g Lambda_g s_g,     Dx_g = Dx_1 + s_g.

So each group contributes only its two end tips and ``Lambda_g``
(:class:`GroupBoundary`, what a group companion publishes to the leader) and the leader's
work is ``O(s)``.

Covariance. The paper defines the global step on the mean only; reporting the local step's
covariance after it would overstate the error (a group's common offset is averaged with the
other groups'). The shifts are linear in the tips, ``Dx = G tau`` with ``tau_g = [left tip;
right tip]`` of group ``g``, so with every group's tip covariance ``T_g`` (12 x 12, from the
local step's joint covariance; groups are independent) the leader also returns, per group,
``Gamma_g = G_gg`` (the shift's dependence on the group's own tips) and ``V_g = Cov(Dx_g) =
sum_k G_gk T_k G_gk^T``. Link ``i`` of group ``g``, shifted by ``Dx_g``, then has the first-order
covariance (:func:`shifted_covariance`)::

    P_i' = P_i + E^T Gamma_g Y_i + Y_i^T Gamma_g^T E + E^T V_g E,   Y_i = Cov(tau_g, x~_i)

with ``E`` the [p; v] rows of the 9-dim error state. A group that reports no tip covariance
(an older peer) makes the leader solve the mean only, and the local covariance stays.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..kernels.jit import ENABLED as _COMPILED, as_kernel_array
from ..kernels.semi import group_terms_kernel
from .chain import CON_DIM, CON_POS, CON_VEL, ERR_DIM, ERR_PV
from .constraints import left_tip, right_tip, tip_jacobians
from .neighbour import NEIGHBOUR_GATE_CHI2, NeighbourMeasurement, neighbour_updates
from .sckf import CAParams, CAResult, constraint_apply, constraint_apply_dense_batched
from .so3 import quat_to_rotmat, skew

__all__ = [
    "Groups",
    "make_groups",
    "parse_groups",
    "validate_groups",
    "format_groups",
    "GroupBoundary",
    "group_boundary",
    "group_boundaries",
    "local_constraint_apply",
    "BATCH_DENSE_MAX_LINKS",
    "boundary_residuals",
    "global_step",
    "GlobalSolution",
    "global_solution",
    "group_tip_terms",
    "local_boundary",
    "shifted_covariance",
    "SemiResult",
    "semi_distributed_apply",
]

#: Groups as tuples of 0-based link indices, contiguous and in chain order.
Groups = tuple[tuple[int, ...], ...]

#: Groups up to this size run through the batched dense CA in ``method="auto"``: for small groups
#: one batched call beats one call per group; the two break even near 6 links.
BATCH_DENSE_MAX_LINKS = 5


def validate_groups(groups: Sequence[Sequence[int]], n: int) -> Groups:
    """Check that ``groups`` (0-based) partition ``0..n-1`` into contiguous ordered runs."""
    out = tuple(tuple(int(i) for i in g) for g in groups)
    if not out:
        raise ValueError("groups: at least one group is required")
    expected = 0
    for k, g in enumerate(out):
        if not g:
            raise ValueError(f"groups: group {k + 1} is empty")
        if list(g) != list(range(expected, expected + len(g))):
            raise ValueError(
                f"groups: group {k + 1} is {[i + 1 for i in g]}, expected consecutive links starting at link "
                f"{expected + 1} (groups must be contiguous and in chain order)"
            )
        expected += len(g)
    if expected != n:
        raise ValueError(f"groups: cover links 1..{expected}, but the chain has {n} links")
    return out


def make_groups(n: int, size: int) -> Groups:
    """Consecutive groups of ``size`` links (the last one may be shorter)."""
    if size < 1:
        raise ValueError(f"group size must be >= 1, got {size}")
    return tuple(tuple(range(s, min(s + size, n))) for s in range(0, n, size))


def parse_groups(spec: str, n: int) -> Groups:
    """Parse the CLI layout ``"1,2/3,4,5/6,7"`` (1-based links) into 0-based groups."""
    groups = []
    for k, part in enumerate(spec.split("/")):
        try:
            links = [int(tok) for tok in part.split(",") if tok.strip()]
        except ValueError:
            raise ValueError(f"groups: cannot read group {k + 1} ({part!r}): use comma-separated link numbers") from None
        if any(i < 1 for i in links):
            raise ValueError(f"groups: link numbers are 1-based, got {part!r}")
        groups.append([i - 1 for i in links])
    return validate_groups(groups, n)


def format_groups(groups: Groups) -> str:
    """Inverse of :func:`parse_groups`."""
    return "/".join(",".join(str(i + 1) for i in g) for g in groups)


@dataclass(frozen=True)
class GroupBoundary:
    """A group's contribution to the global step (eq. 6).

    Attributes:
        left_tip: (6,) [position m; velocity m/s] of the left tip of the group's first link.
        right_tip: (6,) the same for the right tip of its last link.
        info_pv: (6, 6) ``Lambda_g = sum_i Pbar_i^-1`` over the group's links.
        tip_cov: (12, 12) covariance of the ``[left tip; right tip]`` errors after the local
            step, ``None`` if unknown (then the global step shifts the mean only).
    """

    left_tip: np.ndarray
    right_tip: np.ndarray
    info_pv: np.ndarray
    tip_cov: np.ndarray | None = None


def group_boundaries(p, v, q, w, d, P, groups: Groups, tip_covs: Sequence[np.ndarray | None] | None = None,
                     ) -> tuple[GroupBoundary, ...]:
    """Boundaries of all ``groups`` of one chain (arrays indexed by link, groups 0-based);
    ``tip_covs``: each group's tip covariance (:func:`group_tip_terms`), or none."""
    first = [g[0] for g in groups]
    last = [g[-1] for g in groups]
    lt = left_tip(p[first], v[first], q[first], w[first], d[first])
    rt = right_tip(p[last], v[last], q[last], w[last], d[last])
    info = np.add.reduceat(np.linalg.inv(P[:, ERR_PV, ERR_PV]), first, axis=0)
    info = 0.5 * (info + np.swapaxes(info, 1, 2))
    covs = [None] * len(groups) if tip_covs is None else list(tip_covs)
    return tuple(GroupBoundary(left_tip=lt[k], right_tip=rt[k], info_pv=info[k], tip_cov=covs[k])
                 for k in range(len(groups)))


def group_boundary(p, v, q, w, d, P, tip_cov: np.ndarray | None = None) -> GroupBoundary:
    """Boundary of one group from its own links' (locally corrected) states and covariances."""
    return group_boundaries(p, v, q, w, d, P, (tuple(range(p.shape[0])),), (tip_cov,))[0]


def _end_jacobians(q, w, d) -> tuple[np.ndarray, np.ndarray]:
    """A group's ``tau = [left tip; right tip]`` (12) against the error state of its first link
    (``J[0]``, (12, 9)) and of its last (``J[1]``), and against their body rates (``B[0]``,
    ``B[1]``, (12, 3): the tip velocities carry ``+-R S(w) d = -+R S(d) w``)."""
    ends = [0, q.shape[0] - 1]
    J_left, J_right = tip_jacobians(q[ends], w[ends], d[ends])
    rate = -quat_to_rotmat(q[ends]) @ skew(d[ends])
    J = np.zeros((2, 2 * CON_DIM, ERR_DIM))
    B = np.zeros((2, 2 * CON_DIM, 3))
    J[0, :CON_DIM] = J_left[0]
    J[1, CON_DIM:] = J_right[1]
    B[0, CON_VEL] = -rate[0]
    B[1, CON_DIM + CON_VEL.start:CON_DIM + CON_VEL.stop] = rate[1]
    return J, B


def group_tip_terms(q, w, d, local: CAResult) -> tuple[np.ndarray, np.ndarray]:
    """``(T, Y)`` of one group after its local step (``q``: its final attitudes; ``local``: the
    step's result, with ``P_ends`` and ``W_ends``): ``T = Cov(tau, tau)`` (12, 12), the tips'
    covariance it publishes, and ``Y_i = Cov(tau, x~_i)`` (n, 12, 9) per link, what
    :func:`shifted_covariance` needs; body-rate noise included."""
    J, B = _end_jacobians(q, w, d)
    # Cov(tau, x_i) = J_e P^C[e, i] + B_e Cov(dw_e, x_i) over the ends e, with P^C[e, i] = P_ends[e, i]^T
    Y = J[0] @ np.swapaxes(local.P_ends[0], 1, 2) + J[1] @ np.swapaxes(local.P_ends[1], 1, 2)
    if local.W_ends is not None:
        Y = Y + B[0] @ np.swapaxes(local.W_ends[0], 1, 2) + B[1] @ np.swapaxes(local.W_ends[1], 1, 2)
    T = Y[0] @ J[0].T + Y[-1] @ J[1].T  # Cov(tau, J_first x_first + J_last x_last)
    var = local.omega_std_rad_s**2
    if var > 0.0:
        # Cov(tau, dw_e) = J_first Cov(x_first, dw_e) + J_last Cov(x_last, dw_e) + B_e' Cov(dw_e', dw_e)
        same = q.shape[0] == 1  # one link: both ends carry the same rate
        for e in (0, 1):
            Z = var * (B[0] + B[1] if same else B[e])
            if local.W_ends is not None:
                Z = Z + J[0] @ local.W_ends[e][0] + J[1] @ local.W_ends[e][-1]
            T = T + Z @ B[e].T
    return 0.5 * (T + T.T), Y


_NO_RATE_COLUMNS = np.zeros((2, 0, ERR_DIM, 3))


def local_boundary(p, v, q, w, d, local: CAResult, compiled: bool | None = None) -> tuple[GroupBoundary, np.ndarray]:
    """One group after its local step (``p, v, q``: its corrected states, ``local``: the step's
    result): its boundary with the tips' covariance (:func:`group_boundary`, ``T`` of
    :func:`group_tip_terms`) and ``Y = Cov(tau, x~_i)`` (n, 12, 9), what a group companion
    publishes and keeps for its shift.

    The two functions named are the specification; ``compiled`` (default: when numba is
    installed) computes the same numbers by :func:`companion.kernels.semi.group_terms_kernel` in one
    call (``tests/unit/test_fast_paths.py``: agreement to 1e-12)."""
    if not (_COMPILED if compiled is None else compiled):
        T, Y = group_tip_terms(q, w, np.asarray(d, float), local)
        return group_boundary(p, v, q, w, d, local.P, T), Y
    n = np.shape(p)[0]
    arr, v3 = as_kernel_array, (n, 3)
    has_w = local.W_ends is not None
    tips, info = np.empty((2, CON_DIM)), np.empty((CON_DIM, CON_DIM))
    T, Y = np.empty((2 * CON_DIM, 2 * CON_DIM)), np.empty((n, 2 * CON_DIM, ERR_DIM))
    group_terms_kernel((arr(p, v3), arr(v, v3), arr(q, (n, 4)), arr(w, v3), arr(d, v3)),
                       arr(local.P, (n, ERR_DIM, ERR_DIM)),
                       (arr(local.P_ends, (2, n, ERR_DIM, ERR_DIM)),
                        arr(local.W_ends, (2, n, ERR_DIM, 3)) if has_w else _NO_RATE_COLUMNS),
                       has_w, float(local.omega_std_rad_s) ** 2, (tips, info, T, Y))
    return GroupBoundary(left_tip=tips[0], right_tip=tips[1], info_pv=info, tip_cov=T), Y


def boundary_residuals(boundaries: Sequence[GroupBoundary]) -> np.ndarray:
    """(s-1, 6) inter-group constraint errors ``c^G_g`` (right tip g minus left tip g+1)."""
    return np.array([boundaries[g].right_tip - boundaries[g + 1].left_tip for g in range(len(boundaries) - 1)])


def global_step(boundaries: Sequence[GroupBoundary]) -> np.ndarray:
    """Closed-form solution of eq. 6: one [Dp; Dv] shift per group, shape (s, 6)."""
    s = len(boundaries)
    if s == 0:
        raise ValueError("global step needs at least one group")
    offsets = np.zeros((s, 6))
    if s > 1:
        offsets[1:] = np.cumsum(boundary_residuals(boundaries), axis=0)
    infos = np.array([b.info_pv for b in boundaries])
    total = infos.sum(axis=0)
    weighted = np.einsum("gij,gj->i", infos, offsets)
    first = -np.linalg.solve(total, weighted)
    return first[None, :] + offsets


@dataclass(frozen=True)
class GlobalSolution:
    """Eq. 6 solved with its covariance terms (see the module docstring).

    Attributes:
        shifts: (s, 6) ``[Dp; Dv]`` per group (:func:`global_step`).
        gains: (s, 6, 12) ``Gamma_g``, the derivative of group ``g``'s shift with respect to its
            own ``[left tip; right tip]``; ``None`` when a group reported no tip covariance.
        shift_cov: (s, 6, 6) ``V_g = Cov(Dx_g)``; ``None`` likewise.
    """

    shifts: np.ndarray
    gains: np.ndarray | None = None
    shift_cov: np.ndarray | None = None


def global_solution(boundaries: Sequence[GroupBoundary]) -> GlobalSolution:
    """:func:`global_step` plus, when every group reported its tip covariance, the terms of
    :func:`shifted_covariance`: ``Dx = G tau`` (the shifts are linear in the tips), ``Gamma_g =
    G_gg`` and ``V_g = sum_k G_gk T_k G_gk^T``."""
    shifts = global_step(boundaries)
    if any(b.tip_cov is None for b in boundaries):
        return GlobalSolution(shifts)
    s = len(boundaries)
    # Dx_g = s_g - sum_j W_j s_j with W_j = Lambda^-1 Lambda_j (sum_j W_j = I), s_g = sum_{h<g} c_h and
    # c_h = right tip of h - left tip of h+1. So, with Wsuf_k = sum_{j>=k} W_j:
    #   dDx_g / d(left tip of k)  = Wsuf_k - [g >= k] I      (0 for k = 0: Wsuf_0 = I)
    #   dDx_g / d(right tip of k) = [g > k] I - Wsuf_{k+1}   (0 for the last group)
    infos = np.array([b.info_pv for b in boundaries])
    W = np.linalg.solve(infos.sum(axis=0)[None], infos)  # (s, 6, 6)
    Wsuf = np.zeros((s + 1, CON_DIM, CON_DIM))
    Wsuf[:s] = np.cumsum(W[::-1], axis=0)[::-1]
    order = np.arange(s)
    eye = np.eye(CON_DIM)
    G = np.empty((s, s, CON_DIM, 2 * CON_DIM))  # [g, k]: dDx_g / d tau_k
    G[:, :, :, :CON_DIM] = Wsuf[None, :s] - (order[:, None] >= order[None, :])[:, :, None, None] * eye
    G[:, :, :, CON_DIM:] = (order[:, None] > order[None, :])[:, :, None, None] * eye - Wsuf[None, 1:]
    T = np.array([b.tip_cov for b in boundaries])
    gains = G[order, order]  # (s, 6, 12)
    cov = np.sum(G @ T[None] @ np.swapaxes(G, 2, 3), axis=1)
    return GlobalSolution(shifts, gains, 0.5 * (cov + np.swapaxes(cov, 1, 2)))


def shifted_covariance(P: np.ndarray, Y: np.ndarray, gain: np.ndarray, shift_cov: np.ndarray) -> np.ndarray:
    """Covariance blocks (n, 9, 9) of a group's links after its global-step shift (module
    docstring): ``P_i + E^T Gamma Y_i + Y_i^T Gamma^T E + E^T V E`` from the local step's blocks
    ``P``, ``Y = Cov(tau, x~_i)`` (:func:`group_tip_terms`), the group's ``Gamma`` (6, 12)
    and ``V`` (6, 6) (:class:`GlobalSolution`)."""
    out = np.array(P, dtype=float, copy=True)
    cross = gain @ Y  # (n, 6, 9) = Cov(Dx, x~_i)
    out[:, ERR_PV, :] += cross
    out[:, :, ERR_PV] += np.swapaxes(cross, 1, 2)
    out[:, ERR_PV, ERR_PV] += shift_cov
    return 0.5 * (out + np.swapaxes(out, 1, 2))


@dataclass(frozen=True)
class SemiResult:
    """Output of the semi-distributed estimator (Alg. 2 then eq. 6).

    Attributes:
        p, v, q: final estimates; P: (n, 9, 9) their covariance blocks (the local step's,
            carried through the global step: :func:`shifted_covariance`).
        shifts: (s, 6) global-step shifts per group.
        local: the per-group :class:`CAResult` of Alg. 2.
        boundaries: the per-group :class:`GroupBoundary` fed to eq. 6; none with a single group
            (no joint between groups for eq. 6 to close: its shift is zero).
        neighbour_nis, neighbour_accepted: per neighbour camera measurement given, its
            normalised innovation squared and whether it was applied (NaN and ``False`` for one
            between two groups, which the local steps cannot take; gated: a finite NIS,
            ``False``).
    """

    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    P: np.ndarray
    shifts: np.ndarray
    local: tuple[CAResult, ...]
    boundaries: tuple[GroupBoundary, ...]
    neighbour_nis: np.ndarray = field(default_factory=lambda: np.zeros(0))
    neighbour_accepted: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    @property
    def iterations(self) -> np.ndarray:
        """CA iterations per group."""
        return np.array([r.iterations for r in self.local], dtype=int)


def local_constraint_apply(
    p, v, q, w, d, P, groups: Groups, params: CAParams = CAParams(), method: str = "auto",
    whole: dict[int, np.ndarray] | None = None,
) -> tuple[CAResult, ...]:
    """Alg. 2: Alg. 1 inside every group, independently.

    Groups of the same size up to :data:`BATCH_DENSE_MAX_LINKS` links go through one batched
    dense CA (same iterates as one call per group, without the per-call overhead); larger
    groups use :func:`constraint_apply` (``method`` as there). ``whole``: by group index, a
    group's whole covariance (its links correlated by neighbour measurements) instead of its
    links' blocks in ``P``; such a group takes the dense CA on it.
    """
    whole = whole or {}
    results: list[CAResult | None] = [None] * len(groups)
    by_size: dict[int, list[int]] = {}
    for k, g in enumerate(groups):
        sl = slice(g[0], g[-1] + 1)
        if k in whole:
            results[k] = constraint_apply(p[sl], v[sl], q[sl], w[sl], d[sl], whole[k], params, "dense")
            continue
        by_size.setdefault(len(g), []).append(k)
    for size, members in by_size.items():
        if method == "dense" or (method == "auto" and size <= BATCH_DENSE_MAX_LINKS):
            idx = np.array([groups[k] for k in members])  # (groups of this size, size)
            batch = constraint_apply_dense_batched(p[idx], v[idx], q[idx], w[idx], d[idx], P[idx], params)
            for k, res in zip(members, batch):
                results[k] = res
        else:
            for k in members:
                sl = slice(groups[k][0], groups[k][-1] + 1)
                results[k] = constraint_apply(p[sl], v[sl], q[sl], w[sl], d[sl], P[sl], params, method)
    return tuple(results)


def neighbour_step(p, v, q, w, P, groups: Groups, neighbours: Sequence[NeighbourMeasurement],
                   gate_chi2: float | None = NEIGHBOUR_GATE_CHI2, d=None):
    """The neighbour camera measurements (:mod:`.neighbour`; ``w`` the body rates and ``d`` the
    tip vectors that take the states back to a measurement's capture) applied inside each group
    before its constraint application: ``(p, v, q, whole, nis, accepted)``, the states after
    them, each updated group's whole covariance by group index, and per measurement its NIS and
    whether it was applied (one between two groups is not: NaN, ``False``)."""
    p, v, q = p.copy(), v.copy(), q.copy()
    nis, accepted = np.full(len(neighbours), np.nan), np.zeros(len(neighbours), dtype=bool)
    whole: dict[int, np.ndarray] = {}
    for k, g in enumerate(groups):
        mine = [(m_idx, m) for m_idx, m in enumerate(neighbours) if m.observer in g and m.observed in g]
        if not mine:
            continue
        sl = slice(g[0], g[-1] + 1)
        local = [m.numbered_from(g[0]) for _, m in mine]
        up = neighbour_updates(p[sl], v[sl], q[sl], P[sl], local, gate_chi2, w[sl],
                               d=None if d is None else np.asarray(d, dtype=float)[sl])
        p[sl], v[sl], q[sl], whole[k] = up.p, up.v, up.q, up.P
        for (m_idx, _), x, ok in zip(mine, up.nis, up.accepted):
            nis[m_idx], accepted[m_idx] = x, ok
    return p, v, q, whole, nis, accepted


def semi_distributed_apply(
    p, v, q, w, d, P, groups: Groups, params: CAParams = CAParams(), method: str = "auto",
    neighbours: Sequence[NeighbourMeasurement] = (),
) -> SemiResult:
    """Local CA in every group (Alg. 2), then the global shift of eq. 6; ``neighbours``: camera
    measurements between links, applied inside each group first (:func:`neighbour_step`).

    With a single group this is exactly Alg. 1 on the whole chain (no boundaries, a zero shift).
    """
    groups = validate_groups(groups, p.shape[0])
    p, v, q, whole, nis, accepted = neighbour_step(p, v, q, w, P, groups, neighbours, d=d)
    local = local_constraint_apply(p, v, q, w, d, P, groups, params, method, whole)
    p_out = np.concatenate([r.p for r in local])
    v_out = np.concatenate([r.v for r in local])
    q_out = np.concatenate([r.q for r in local])
    P_out = np.concatenate([r.P for r in local])
    if len(groups) == 1:
        return SemiResult(p_out, v_out, q_out, P_out, np.zeros((1, CON_DIM)), local, (), nis, accepted)
    terms = [group_tip_terms(q_out[g[0]:g[-1] + 1], w[g[0]:g[-1] + 1], d[g[0]:g[-1] + 1], r)
             for g, r in zip(groups, local)]
    boundaries = group_boundaries(p_out, v_out, q_out, w, d, P_out, groups, [T for T, _ in terms])
    solution = global_solution(boundaries)
    shifts = solution.shifts
    sizes = [len(g) for g in groups]
    for k, g in enumerate(groups):
        sl = slice(g[0], g[-1] + 1)
        P_out[sl] = shifted_covariance(P_out[sl], terms[k][1], solution.gains[k], solution.shift_cov[k])
    p_out += np.repeat(shifts[:, CON_POS], sizes, axis=0)
    v_out += np.repeat(shifts[:, CON_VEL], sizes, axis=0)
    return SemiResult(p_out, v_out, q_out, P_out, shifts, local, boundaries, nis, accepted)

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
work is ``O(s)``. The local covariances are reported unchanged by the shift (the paper
defines the global step on the mean only).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .chain import CON_POS, CON_VEL, ERR_PV
from .constraints import left_tip, right_tip
from .sckf import CAParams, CAResult, constraint_apply, constraint_apply_dense_batched

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
    "SemiResult",
    "semi_distributed_apply",
]

#: Groups as tuples of 0-based link indices, contiguous and in chain order.
Groups = tuple[tuple[int, ...], ...]

#: Groups up to this size run through the batched dense CA in ``method="auto"`` (measured:
#: 48 groups of 2 take 2.2 ms batched vs 12.3 ms one call each; break-even near 6 links).
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
    """

    left_tip: np.ndarray
    right_tip: np.ndarray
    info_pv: np.ndarray


def group_boundaries(p, v, q, w, d, P, groups: Groups) -> tuple[GroupBoundary, ...]:
    """Boundaries of all ``groups`` of one chain (arrays indexed by link, groups 0-based)."""
    first = [g[0] for g in groups]
    last = [g[-1] for g in groups]
    lt = left_tip(p[first], v[first], q[first], w[first], d[first])
    rt = right_tip(p[last], v[last], q[last], w[last], d[last])
    info = np.add.reduceat(np.linalg.inv(P[:, ERR_PV, ERR_PV]), first, axis=0)
    info = 0.5 * (info + np.swapaxes(info, 1, 2))
    return tuple(GroupBoundary(left_tip=lt[k], right_tip=rt[k], info_pv=info[k]) for k in range(len(groups)))


def group_boundary(p, v, q, w, d, P) -> GroupBoundary:
    """Boundary of one group from its own links' (locally corrected) states and covariances."""
    return group_boundaries(p, v, q, w, d, P, (tuple(range(p.shape[0])),))[0]


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
    infos = np.stack([b.info_pv for b in boundaries])
    total = infos.sum(axis=0)
    weighted = np.einsum("gij,gj->i", infos, offsets)
    first = -np.linalg.solve(total, weighted)
    return first[None, :] + offsets


@dataclass(frozen=True)
class SemiResult:
    """Output of the semi-distributed estimator (Alg. 2 then eq. 6).

    Attributes:
        p, v, q: final estimates; P: (n, 9, 9) local-step covariance blocks.
        shifts: (s, 6) global-step shifts per group.
        local: the per-group :class:`CAResult` of Alg. 2.
        boundaries: the per-group :class:`GroupBoundary` fed to eq. 6.
    """

    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    P: np.ndarray
    shifts: np.ndarray
    local: tuple[CAResult, ...]
    boundaries: tuple[GroupBoundary, ...]

    @property
    def iterations(self) -> np.ndarray:
        """CA iterations per group."""
        return np.array([r.iterations for r in self.local], dtype=int)


def local_constraint_apply(
    p, v, q, w, d, P, groups: Groups, params: CAParams = CAParams(), method: str = "auto"
) -> tuple[CAResult, ...]:
    """Alg. 2: Alg. 1 inside every group, independently.

    Groups of the same size up to :data:`BATCH_DENSE_MAX_LINKS` links go through one batched
    dense CA (same iterates as one call per group, without the per-call overhead); larger
    groups use :func:`constraint_apply` (``method`` as there).
    """
    results: list[CAResult | None] = [None] * len(groups)
    by_size: dict[int, list[int]] = {}
    for k, g in enumerate(groups):
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


def semi_distributed_apply(
    p, v, q, w, d, P, groups: Groups, params: CAParams = CAParams(), method: str = "auto"
) -> SemiResult:
    """Local CA in every group (Alg. 2), then the global shift of eq. 6.

    With a single group this is exactly Alg. 1 on the whole chain.
    """
    groups = validate_groups(groups, p.shape[0])
    local = local_constraint_apply(p, v, q, w, d, P, groups, params, method)
    p_out = np.concatenate([r.p for r in local])
    v_out = np.concatenate([r.v for r in local])
    q_out = np.concatenate([r.q for r in local])
    P_out = np.concatenate([r.P for r in local])
    boundaries = group_boundaries(p_out, v_out, q_out, w, d, P_out, groups)
    shifts = global_step(boundaries)
    sizes = [len(g) for g in groups]
    p_out += np.repeat(shifts[:, CON_POS], sizes, axis=0)
    v_out += np.repeat(shifts[:, CON_VEL], sizes, axis=0)
    return SemiResult(p_out, v_out, q_out, P_out, shifts, local, boundaries)

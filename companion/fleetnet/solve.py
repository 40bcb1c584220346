"""Eq. 6 over the boundaries the groups reported for one cycle: the leader's shifts, and the
covariance terms each group derives from the same boundaries (pure).

:func:`solve_cycle` solves each run of joined parts on its own: the entries are the groups' parts
(:class:`~companion.messages.GroupBoundaryReport`, a whole group being one part), and two entries
are joined when they are neighbouring groups' parts that meet at the joint between the groups
(``joins_right`` of the first, ``joins_left`` of the second). A missing group, a link down or a
joint cut inside a group splits the chain there. :func:`shift_covariance_terms` gives one part its
``(Gamma_g, V_g)``. One cycle's
boundaries are solved by the leader, checked by each follower against its shift and used by each
group for its covariance terms, so the solutions are kept by the content of their boundaries and
computed once per content.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence

import numpy as np

from companion.estimation.semi import GlobalSolution, GroupBoundary, global_solution
from companion.messages import GroupBoundaryReport

__all__ = ["joined", "runs", "solve_cycle", "shift_covariance_terms"]


def joined(a: GroupBoundaryReport, b: GroupBoundaryReport) -> bool:
    """Whether entry ``b`` follows ``a`` across the joint between two neighbouring groups."""
    return b.group == a.group + 1 and a.joins_right and b.joins_left


def runs(reports: Sequence[GroupBoundaryReport]) -> list[list[GroupBoundaryReport]]:
    """The reports in chain order (by ``(group, part)``), cut into runs of joined entries."""
    ordered = [r for _, r in sorted({r.key: r for r in reports}.items())]
    out: list[list[GroupBoundaryReport]] = []
    for r in ordered:
        if out and joined(out[-1][-1], r):
            out[-1].append(r)
        else:
            out.append([r])
    return out


def solve_cycle(reports: Sequence[GroupBoundaryReport]) -> tuple[tuple[tuple[int, int], ...], np.ndarray]:
    """Eq. 6 over the parts that reported: ``(keys, shifts (len(keys), 6))``, ``keys`` the
    ``(group, part)`` of each entry in chain order. Each run of joined entries is one chain segment
    solved by :func:`~companion.estimation.semi.global_step` (a run of one entry gets a zero shift).
    """
    keys: list[tuple[int, int]] = []
    blocks = []
    for run in runs(reports):
        keys += [r.key for r in run]
        blocks.append(_solution(run).shifts)
    return tuple(keys), (np.concatenate(blocks) if blocks else np.zeros((0, 6)))


#: The latest eq. 6 solutions, by the content of their boundaries. One cycle's boundaries are
#: solved by the leader, checked by each follower against its shift and used by each group for its
#: covariance terms: twice per process and cycle, six times for three groups in one process (batch
#: mode, ``sitl.runner``). The arrays are read-only: every caller of the same content shares them.
_SOLUTIONS: OrderedDict[tuple, GlobalSolution] = OrderedDict()
_SOLUTIONS_KEPT = 8


def _content(a: np.ndarray | None) -> tuple | None:
    if a is None:
        return None
    a = np.asarray(a, dtype=float)
    return a.shape, a.tobytes()


def _solution(run: Sequence[GroupBoundaryReport]) -> GlobalSolution:
    """:func:`~companion.estimation.semi.global_solution` of a run of consecutive groups' reports,
    computed once per content (the same numbers: the same function of the same bytes)."""
    key = tuple((_content(r.left_tip_pv_w), _content(r.right_tip_pv_w), _content(r.info_pv), _content(r.tip_cov_pv))
                for r in run)
    solution = _SOLUTIONS.get(key)
    if solution is not None:
        _SOLUTIONS.move_to_end(key)
        return solution
    solution = global_solution([_boundary(r) for r in run])
    for a in (solution.shifts, solution.gains, solution.shift_cov):
        if a is not None:
            a.setflags(write=False)
    _SOLUTIONS[key] = solution
    while len(_SOLUTIONS) > _SOLUTIONS_KEPT:
        _SOLUTIONS.popitem(last=False)
    return solution


def _boundary(report: GroupBoundaryReport) -> GroupBoundary:
    return GroupBoundary(report.left_tip_pv_w, report.right_tip_pv_w, report.info_pv, report.tip_cov_pv)


def shift_covariance_terms(reports: Sequence[GroupBoundaryReport], key: tuple[int, int] | int,
                           ) -> tuple[np.ndarray, np.ndarray] | None:
    """``(Gamma_g, V_g)`` of the entry ``key`` (``(group, part)``, or a whole group's index;
    :class:`~companion.estimation.semi.GlobalSolution`) from the boundaries of its run of joined
    entries in ``reports`` (the entries solved together); ``None`` if an entry of that run sent no
    tip covariance, or ``key`` is not among them."""
    key = (key, 0) if isinstance(key, int) else tuple(key)
    for run in runs(reports):
        keys = [r.key for r in run]
        if key in keys:
            solution = _solution(run)
            if solution.gains is None:
                return None
            k = keys.index(key)
            return solution.gains[k], solution.shift_cov[k]
    return None

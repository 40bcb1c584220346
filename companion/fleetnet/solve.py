"""Eq. 6 over the boundaries the groups reported for one cycle: the leader's shifts, and the
covariance terms each group derives from the same boundaries (pure).

:func:`solve_cycle` solves each run of consecutive groups on its own (a missing group splits the
chain); :func:`shift_covariance_terms` gives one group its ``(Gamma_g, V_g)``. One cycle's
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

__all__ = ["solve_cycle", "shift_covariance_terms"]


def solve_cycle(reports: Sequence[GroupBoundaryReport]) -> tuple[tuple[int, ...], np.ndarray]:
    """Eq. 6 over the groups that reported: ``(groups, shifts (len(groups), 6))``.

    Groups are sorted; each run of consecutive group indices is one chain segment solved by
    :func:`~companion.estimation.semi.global_step` (a segment of one group gets a zero shift).
    """
    by_group = {r.group: r for r in reports}
    groups = tuple(sorted(by_group))
    shifts = np.zeros((len(groups), 6))
    start = 0
    for k in range(1, len(groups) + 1):
        if k == len(groups) or groups[k] != groups[k - 1] + 1:
            shifts[start:k] = _solution([by_group[g] for g in groups[start:k]]).shifts
            start = k
    return groups, shifts


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


def shift_covariance_terms(reports: Sequence[GroupBoundaryReport], group: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``(Gamma_g, V_g)`` of ``group`` (:class:`~companion.estimation.semi.GlobalSolution`) from
    the boundaries of its run of consecutive groups in ``reports`` (the groups solved together);
    ``None`` if a group of that run sent no tip covariance."""
    by_group = {r.group: r for r in reports}
    lo = hi = group
    while lo - 1 in by_group:
        lo -= 1
    while hi + 1 in by_group:
        hi += 1
    solution = _solution([by_group[g] for g in range(lo, hi + 1)])
    if solution.gains is None:
        return None
    return solution.gains[group - lo], solution.shift_cov[group - lo]

"""The companion's 20 Hz step as a pure function: link states in, per-link corrections out.

Takes the newest :class:`~companion.messages.LinkState` of every link of the chain, runs the
semi-distributed constraint application (Alg. 2 + eq. 6; Alg. 1 for one group) and returns
each link's :class:`~companion.messages.Correction` = corrected minus EKF estimate.

Time alignment: the constraint holds between states of the same instant. Links stamped at
different EKF times are first propagated to the newest stamp with their own velocity and body
rate (``p + v dt``, ``q (x) Exp(w dt)``; the covariance is left as reported, the offsets being
a few milliseconds at most in lockstep). In batch mode all stamps are equal and nothing moves.
A group companion of the semi-distributed fleet aligns to the cycle time instead (the step
time on the flight-controller clock, the same for every group), so that the boundaries the
leader joins describe one instant.

:func:`compute_corrections` is the whole step in one process (Alg. 2 + eq. 6).
:func:`local_step` and :func:`finish_step` are the two halves a group companion runs around
the network: its own links' Alg. 1 and boundary, then the leader's shift (or none).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .estimation.chain import CON_POS, CON_VEL
from .estimation.neighbour import NeighbourMeasurement
from .estimation.sckf import CAParams, CAResult, constraint_apply
from .estimation.semi import (
    GroupBoundary,
    Groups,
    SemiResult,
    local_boundary,
    neighbour_step,
    semi_distributed_apply,
    shifted_covariance,
)
from .estimation.so3 import attitude_error, quat_from_rotvec, quat_mul
from .kernels.align import align_kernel, attitude_errors_kernel
from .kernels.jit import ENABLED as _COMPILED
from .messages import Correction, LinkState

__all__ = ["align_states", "compute_corrections", "LocalStep", "local_step", "finish_step"]


def align_states(states: Sequence[LinkState], t: float | None = None,
                 compiled: bool | None = None) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Propagate every state to time ``t`` (default: the newest stamp): ``(t, p (n,3), v (n,3), q (n,4))``.

    The numpy code below is the specification; ``compiled`` (default: when numba is installed)
    propagates by :func:`companion.kernels.align.align_kernel` (the same numbers to 1e-15:
    ``tests/unit/test_companion_kernels.py``)."""
    if t is None:
        t = max(s.time_s for s in states)
    p = np.array([s.p_w_m for s in states], dtype=float)
    v = np.array([s.v_w_m_s for s in states], dtype=float)
    w = np.array([s.omega_b_rad_s for s in states], dtype=float)
    q = np.array([s.q_wxyz for s in states], dtype=float)
    if _COMPILED if compiled is None else compiled:
        p_out, q_out = np.empty_like(p), np.empty_like(q)
        align_kernel(float(t), np.array([s.time_s for s in states], dtype=float), p, v, q, w, p_out, q_out)
        return t, p_out, v, q_out
    dt = np.array([t - s.time_s for s in states])[:, None]
    return t, p + v * dt, v, quat_mul(q, quat_from_rotvec(w * dt))


def compute_corrections(
    states: Sequence[LinkState],
    d_b_m: np.ndarray,
    groups: Groups,
    params: CAParams = CAParams(),
    seq: int = 0,
    t: float | None = None,
    neighbours: Sequence[NeighbourMeasurement] = (),
) -> tuple[SemiResult, list[Correction]]:
    """Constraint application on one snapshot of the chain, or of a segment of it: ``states`` of
    consecutive links in chain order, ``d_b_m`` and ``groups`` (numbered from the first) theirs,
    aligned to time ``t`` (default: their newest stamp); ``neighbours``: camera measurements
    between its links (numbered from the first), applied before the constraint (the
    corrections carry them)."""
    links = [s.link for s in states]
    if not links or links != list(range(links[0], links[0] + len(links))):
        raise ValueError(f"states must be consecutive links in chain order, got {links}")
    _, p, v, q = align_states(states, t)
    w = np.array([s.omega_b_rad_s for s in states])
    P = np.array([s.P for s in states])
    result = semi_distributed_apply(p, v, q, w, d_b_m, P, groups, params, neighbours=neighbours)
    return result, _deltas(states, p, v, q, result.p, result.v, result.q, seq)


def _deltas(states, p, v, q, p_out, v_out, q_out, seq: int, compiled: bool | None = None) -> list[Correction]:
    """Corrections against the aligned states: the link adds them to its EKF output. ``compiled``
    (default: when numba is installed): the attitude part by
    :func:`companion.kernels.align.attitude_errors_kernel` instead of ``so3.attitude_error``."""
    if _COMPILED if compiled is None else compiled:
        dtheta = np.empty((len(states), 3))
        attitude_errors_kernel(np.ascontiguousarray(q_out, dtype=float), np.ascontiguousarray(q, dtype=float), dtheta)
    else:
        dtheta = attitude_error(q_out, q)
    dp, dv = p_out - p, v_out - v
    return [
        Correction(link=s.link, ekf_time_s=s.time_s, dp_w_m=dp[i], dv_w_m_s=dv[i], dtheta_w_rad=dtheta[i], seq=seq)
        for i, s in enumerate(states)
    ]


@dataclass(frozen=True)
class LocalStep:
    """A group's half of the semi-distributed step: its links aligned to ``time_s``, the local
    constraint application (Alg. 2 for this group, i.e. Alg. 1 on its links), its boundary and
    ``tip_cross``, the (n, 12, 9) ``Cov(tau, x~_i)`` that carries the covariance through its shift."""

    time_s: float
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    w: np.ndarray
    result: CAResult
    boundary: GroupBoundary
    tip_cross: np.ndarray
    neighbour_accepted: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))


def local_step(states: Sequence[LinkState], d_b_m: np.ndarray, params: CAParams = CAParams(),
               t: float | None = None, neighbours: Sequence[NeighbourMeasurement] = ()) -> LocalStep:
    """Align a group's link states (consecutive links of the chain, in order) to ``t`` and apply
    the constraints among them; ``d_b_m`` is (len(states), 3); ``neighbours``: camera
    measurements between them (numbered from the first), applied first (:func:`neighbour_step`;
    ``neighbour_accepted`` says which were)."""
    links = [s.link for s in states]
    if links != list(range(links[0], links[0] + len(links))):
        raise ValueError(f"a group's states must be consecutive links in chain order, got {links}")
    t, p, v, q = align_states(states, t)
    w = np.array([s.omega_b_rad_s for s in states])
    P = np.array([s.P for s in states])
    pn, vn, qn, whole, _, accepted = neighbour_step(p, v, q, w, P, (tuple(range(len(states))),), neighbours,
                                                    d=d_b_m)
    result = constraint_apply(pn, vn, qn, w, d_b_m, whole.get(0, P), params)
    boundary, tip_cross = local_boundary(result.p, result.v, result.q, w, d_b_m, result)
    return LocalStep(t, p, v, q, w, result, boundary, tip_cross, accepted)


def finish_step(states: Sequence[LinkState], step: LocalStep, shift_pv: np.ndarray | None, seq: int,
                shift_gain: np.ndarray | None = None, shift_cov: np.ndarray | None = None,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[Correction]]:
    """The group's final estimate (local result shifted by the global step's ``[dp; dv]``, eq. 6;
    ``None``: local only), its covariance blocks and its links' corrections: ``(p, v, q, P,
    corrections)``. With the shift's covariance terms (``shift_gain`` (6, 12), ``shift_cov``
    (6, 6): :class:`~companion.estimation.semi.GlobalSolution`) the covariance is carried through
    the shift (:func:`~companion.estimation.semi.shifted_covariance`); else it is the local step's."""
    p_out, v_out = step.result.p.copy(), step.result.v.copy()
    P_out = step.result.P
    if shift_pv is not None:
        p_out += shift_pv[CON_POS]
        v_out += shift_pv[CON_VEL]
        if shift_gain is not None and shift_cov is not None:
            P_out = shifted_covariance(P_out, step.tip_cross, shift_gain, shift_cov)
    return (p_out, v_out, step.result.q, P_out,
            _deltas(states, step.p, step.v, step.q, p_out, v_out, step.result.q, seq))

"""The companion's 20 Hz step as a pure function: link states in, per-link corrections out.

Takes the newest :class:`~companion.messages.LinkState` of every link of the chain, runs the
semi-distributed constraint application (Alg. 2 + eq. 6; Alg. 1 for one group) and returns
each link's :class:`~companion.messages.Correction` = corrected minus EKF estimate.

Time alignment: the constraint holds between states of the same instant. Links stamped at
different EKF times are first propagated to the newest stamp with their own velocity and body
rate (``p + v dt``, ``q (x) Exp(w dt)``; the covariance is left as reported, the offsets being
a few milliseconds at most in lockstep). In batch mode all stamps are equal and nothing moves.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .estimation.sckf import CAParams
from .estimation.semi import Groups, SemiResult, semi_distributed_apply
from .estimation.so3 import attitude_error, quat_from_rotvec, quat_mul
from .messages import Correction, LinkState

__all__ = ["align_states", "compute_corrections"]


def align_states(states: Sequence[LinkState]) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Propagate every state to the newest stamp: ``(t, p (n,3), v (n,3), q (n,4))``."""
    t = max(s.time_s for s in states)
    dt = np.array([t - s.time_s for s in states])[:, None]
    p = np.stack([s.p_w_m for s in states]) + np.stack([s.v_w_m_s for s in states]) * dt
    v = np.stack([s.v_w_m_s for s in states])
    w = np.stack([s.omega_b_rad_s for s in states])
    q = quat_mul(np.stack([s.q_wxyz for s in states]), quat_from_rotvec(w * dt))
    return t, p, v, q


def compute_corrections(
    states: Sequence[LinkState],
    d_b_m: np.ndarray,
    groups: Groups,
    params: CAParams = CAParams(),
    seq: int = 0,
) -> tuple[SemiResult, list[Correction]]:
    """Constraint application on one snapshot of the chain; ``states`` ordered by link."""
    if [s.link for s in states] != list(range(len(states))):
        raise ValueError(f"states must cover links 0..{len(states) - 1} in order, got {[s.link for s in states]}")
    _, p, v, q = align_states(states)
    w = np.stack([s.omega_b_rad_s for s in states])
    P = np.stack([s.P for s in states])
    result = semi_distributed_apply(p, v, q, w, d_b_m, P, groups, params)
    # Deltas against the aligned states: the link adds them to its EKF output.
    dtheta = attitude_error(result.q, q)
    corrections = [
        Correction(
            link=s.link,
            ekf_time_s=s.time_s,
            dp_w_m=result.p[i] - p[i],
            dv_w_m_s=result.v[i] - v[i],
            dtheta_w_rad=dtheta[i],
            seq=seq,
        )
        for i, s in enumerate(states)
    ]
    return result, corrections

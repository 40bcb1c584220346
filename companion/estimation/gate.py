"""Which links a constraint step may use: the chi-square joint gate and the chain's segments.

A link whose state disagrees with its neighbours beyond what the covariances allow must not
take part in the constraint application: the SCKF would spread its error over the healthy
links (a +3 m state with a tiny covariance pulls its neighbours by metres). Before every step:

1. per joint ``i`` (links ``i`` and ``i+1``) the normalised innovation squared of the eq. 3
   residual ``c_i`` (position and velocity of the two tips)::

       NIS_i = c_i^T S_i^-1 c_i,   S_i = L_i P_i L_i^T + R_i P_{i+1} R_i^T + G        (eq. 4 blocks)

   with ``G = diag(gate_pos^2 I3, gate_vel^2 I3)``, the joint's slack (cable stretch, link
   bending, the flight controllers' covariances being tighter than their errors). Without
   fault ``NIS_i`` follows a chi-square law with 6 degrees of freedom; a joint above
   ``threshold`` (default the 1e-6 tail, 38.26) is *cut*;
2. a link whose every joint is cut (an inner link with both joints cut, an end link whose
   one joint is cut while its neighbour's other joint holds) is the outlier: it is
   *excluded*. Where a cut cannot be pinned on one link (a chain of two, two adjacent faulty
   links) both sides of the cut simply stop constraining each other;
3. the chain splits at cut joints and around links that may not be used at all (silent,
   EKF not usable, just rebooted): :func:`segments` returns the runs of at least two
   consecutive usable links; each is corrected on its own, every other link gets no
   correction and flies on its own EKF.

Pure numpy, no state: :func:`joint_nis`, :func:`gate_chain`, :func:`segments`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..kernels.gate import joint_nis_kernel
from ..kernels.jit import ENABLED as _COMPILED, as_kernel_array
from .chain import CON_POS, CON_VEL
from .constraints import jacobian_blocks_from_tips, residual_from_tips, tip_offsets

__all__ = ["CHI2_6_1E6", "GateParams", "GateResult", "joint_nis", "gate_chain", "segments"]

#: Chi-square quantile with 6 degrees of freedom, tail probability 1e-6 (``scipy.stats.chi2.isf(1e-6, 6)``).
CHI2_6_1E6 = 38.26


@dataclass(frozen=True)
class GateParams:
    """The joint gate: ``threshold`` on NIS (6 dof), the joint's slack ``gate_pos_m`` [m] and
    ``gate_vel_m_s`` [m/s] (1 sigma) added to the residual covariance."""

    threshold: float = CHI2_6_1E6
    gate_pos_m: float = 0.05
    gate_vel_m_s: float = 0.25

    def __post_init__(self) -> None:
        if not (self.threshold > 0 and self.gate_pos_m > 0 and self.gate_vel_m_s > 0):
            raise ValueError(f"gate parameters must be positive, got {self}")


@dataclass(frozen=True)
class GateResult:
    """``nis`` (n-1,) per joint; ``cut`` (n-1,) bool; ``excluded`` the outlier links (0-based)."""

    nis: np.ndarray
    cut: np.ndarray
    excluded: tuple[int, ...]


def joint_nis(p, v, q, w, d, P, params: GateParams = GateParams(), compiled: bool | None = None) -> np.ndarray:
    """NIS of every joint's eq. 3 residual (see the module docstring), shape (n-1,).

    The numpy code below is the specification; ``compiled`` (default: when numba is installed)
    computes the same numbers by :func:`companion.kernels.gate.joint_nis_kernel` (one call instead of
    about thirty numpy calls before every step; ``tests/unit/test_fast_paths.py``: agreement to 1e-12)."""
    n = np.shape(p)[0]
    if n < 2:
        return np.zeros(0)
    if _COMPILED if compiled is None else compiled:
        nis = np.empty(n - 1)
        arr, v3 = as_kernel_array, (n, 3)
        joint_nis_kernel((arr(p, v3), arr(v, v3), arr(q, (n, 4)), arr(w, v3), arr(d, v3)), arr(P, (n, 9, 9)),
                         params.gate_pos_m ** 2, params.gate_vel_m_s ** 2, nis)
        return nis
    a, b = tip_offsets(q, w, d)  # once for the residual and the Jacobian blocks
    c = residual_from_tips(p, v, a, b).reshape(n - 1, 6)
    L, R = jacobian_blocks_from_tips(a, b)
    S = L @ P[:-1] @ np.swapaxes(L, 1, 2) + R @ P[1:] @ np.swapaxes(R, 1, 2)
    slack = np.zeros(6)
    slack[CON_POS] = params.gate_pos_m ** 2
    slack[CON_VEL] = params.gate_vel_m_s ** 2
    S = S + np.diag(slack)
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
    return np.einsum("ji,ji->j", c, np.linalg.solve(S, c[..., None])[..., 0])


def gate_chain(p, v, q, w, d, P, params: GateParams = GateParams()) -> GateResult:
    """Cut joints and outlier links of one chain snapshot (arrays indexed by link)."""
    nis = joint_nis(p, v, q, w, d, P, params)
    cut = ~(nis <= params.threshold)  # NaN cuts too
    n = np.shape(p)[0]
    excluded = []
    for k in range(n):
        left = cut[k - 1] if k > 0 else None
        right = cut[k] if k < n - 1 else None
        if left is not None and right is not None:
            if left and right:
                excluded.append(k)
        elif left is not None:  # last link: its joint cut while its neighbour's other joint holds
            if left and n > 2 and not cut[k - 2]:
                excluded.append(k)
        elif right is not None:  # first link
            if right and n > 2 and not cut[k + 1]:
                excluded.append(k)
    return GateResult(nis, cut, tuple(excluded))


def segments(usable: Sequence[bool], cut: Sequence[bool] | None = None, min_links: int = 2) -> list[tuple[int, ...]]:
    """Runs of at least ``min_links`` consecutive usable links not separated by a cut joint.

    ``usable`` (n,) per link; ``cut`` (n-1,) per joint (default none cut).
    """
    n = len(usable)
    cut = [False] * max(n - 1, 0) if cut is None else list(cut)
    out: list[tuple[int, ...]] = []
    run: list[int] = []
    for k in range(n):
        if usable[k] and run and not cut[k - 1]:
            run.append(k)
            continue
        if len(run) >= min_links:
            out.append(tuple(run))
        run = [k] if usable[k] else []
    if run and len(run) >= min_links:
        out.append(tuple(run))
    return out

"""Control allocation of one 8-rotor ODAR link with selective mapping (thesis ch. 2, sec. 2.4).

The link produces the body-frame wrench ``U = [R_OB^T f; tau] = B lambda`` (eq. 2.8) from
the eight bidirectional rotor thrusts ``lambda`` [N]; the geometry (:class:`RotorGeometry`,
Table 2.1) is the shared vehicle model of :mod:`companion.skeleton.rotors`. Column ``i`` of the mapping matrix
``B = [B_f; B_tau]`` (6x8) is ``[u_i; t_i]`` with the torque per unit thrust
``t_i = r_i x u_i + gamma sigma_i u_i`` (eq. 2.1).

Rotors 1-4 (0-based indices 0..3, :data:`R_SIDE`) form the r-side and rotors 5-8 (4..7,
:data:`L_SIDE`) the l-side, with ``u_{j+4} = u_j``, ``r_{j+4} = -r_j``,
``sigma_{j+4} = -sigma_j`` (sec. 2.2.2). With the modified design of sec. 2.4.1
(``sigma_1 = -1``) the null-vector structure (2.11) holds with ``nu = [1, -1, -1, 1]`` and
the kernel of ``B`` is ``N_B = blkdiag(nu, nu)`` (2.13).

The allocation pipeline, per call (all ``(8,)`` vectors are ordered ``[r-side; l-side]``):

1. ``lambda_o = B^+ U`` with ``B^+ = B^T (B B^T)^-1`` (sec. 2.4.1);
2. ``lambda_alpha = lambda_o + N_B xi'``, the closed-form infinity-norm minimiser of
   Prop. 1 (eq. 2.10, 2.12, 2.14);
3. ``lambda_beta = lambda_o + N_B (xi' + xi'')``, the null-space modulation (2.15) that keeps
   at least three rotors per side at ``|lambda| >= eps1``, staying as close as possible to the
   previous ``xi''`` (state of :class:`Allocator`);
4. ``lambda_gamma`` of the gradually switching selective mapping (2.17), which fades the
   (at most one per side) near-zero rotor out of the mapping between ``eps1`` and ``eps0``,
   using the decoupled reduced pseudo-inverses (2.18)-(2.19); exact by Prop. 2.

The command sent to the ESCs is ``lambda_gamma`` (or ``lambda_alpha`` with selective mapping
off) clipped to ``+-thrust_max``.

Units: thrusts in N, forces in N, torques in Nm, lengths in m; everything in the body frame.
Rotor indices in code are 0-based (thesis rotor ``i`` is index ``i - 1``).

This module is the functional core (:func:`pseudo_inverse`, :func:`reduced_pseudo_inverse`,
:func:`infinity_norm_allocation`, :func:`scaled_to_limit`, :func:`selective_modulation`,
:func:`selective_mapping_weights`, :func:`gradual_selective_mapping`; pure, numpy only), with the
parameters and the result; the stateful :class:`~.allocator.Allocator` on top precomputes every
matrix once and runs the whole pipeline.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.skeleton.rotors import N_ROTORS, N_SIDE, NU, SIDES, WRENCH_DIM

__all__ = [
    "MARGIN_TOL_N",
    "AllocationParams",
    "AllocationResult",
    "pseudo_inverse",
    "reduced_pseudo_inverse",
    "reduced_pseudo_inverses",
    "infinity_norm_allocation",
    "scaled_to_limit",
    "selective_modulation",
    "selective_mapping_weights",
    "gradual_selective_mapping",
]


MARGIN_TOL_N = 1e-9
"""Slack [N] in the thrust-margin test of (2.15): a rotor with ``|lambda| >= eps1 - MARGIN_TOL_N``
counts as clear of ``eps1`` (absorbs rounding at the endpoints of the forbidden intervals)."""


# --------------------------------------------------------------------------------------------
# Parameters and result
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AllocationParams:
    """Thrust limit and selective-mapping thresholds (sec. 2.4.2, Fig. 2-5).

    Attributes
    ----------
    thrust_max_n : float
        Bidirectional thrust limit: commands are clipped to ``[-thrust_max_n, thrust_max_n]`` [N].
    eps0_n : float
        Below this ``|lambda_beta|`` the near-zero rotor is fully removed from the mapping
        (``e = 0`` in (2.17)) [N].
    eps1_n : float
        Thrust margin of (2.15) and the threshold above which a rotor is fully used (``e = 1``) [N].
    selective_mapping : bool
        ``False``: command ``lambda_alpha`` (Prop. 1 only), skipping (2.15) and (2.17).
    scale_to_limit : bool
        A wrench beyond the rotors' limit: allocate what they can produce of it, a wrench kept
        whole (the firmware: the link's weight) and the rest scaled (:func:`scaled_to_limit`),
        and keep (2.15)'s modulation and (2.17)'s fade within the limit (the fade's weight ``e``
        raised as far as that needs). ``False``: the thesis as written, commands clipped rotor
        by rotor.
    remove_failed_rotor : bool
        A rotor the firmware finds failed (its ESC reports it stopped while commanded) is left
        out of the allocation, the link flying on the other seven (PX4's ``CA_FAILURE_MODE = 1``;
        :meth:`~.allocator.Allocator.remove_rotor`). ``False``: reported only.

    Requires ``0 < eps0_n < eps1_n < thrust_max_n`` (all finite).
    """

    thrust_max_n: float = 8.0
    eps0_n: float = 0.3
    eps1_n: float = 0.8
    selective_mapping: bool = True
    scale_to_limit: bool = True
    remove_failed_rotor: bool = True

    def __post_init__(self) -> None:
        vals = (self.thrust_max_n, self.eps0_n, self.eps1_n)
        if not all(np.isfinite(v) for v in vals):
            raise ValueError(f"AllocationParams thresholds must be finite; got thrust_max_n, eps0_n, eps1_n = {vals}")
        if not self.eps0_n > 0.0:
            raise ValueError(f"eps0_n must be > 0 (thesis: 0 < eps0 < eps1); got {self.eps0_n}")
        if not self.eps0_n < self.eps1_n:
            raise ValueError(f"eps0_n must be < eps1_n (thesis: 0 < eps0 < eps1); got eps0_n={self.eps0_n}, eps1_n={self.eps1_n}")
        if not self.thrust_max_n > self.eps1_n:
            raise ValueError(
                f"thrust_max_n must be > eps1_n (the margin must be reachable); got thrust_max_n={self.thrust_max_n}, "
                f"eps1_n={self.eps1_n}"
            )


@dataclass(frozen=True, eq=False)
class AllocationResult:
    """Outcome of one :meth:`Allocator.allocate` call (all thrusts in N, rotor order 1..8).

    Attributes
    ----------
    command_n : ndarray, shape (8,)
        Thrust commands sent to the ESCs: ``lambda_gamma`` (or ``lambda_alpha`` with selective
        mapping off) clipped to ``+-thrust_max_n``.
    lambda_o : ndarray, shape (8,)
        Minimum two-norm allocation ``B^+ U`` (sec. 2.4.1).
    lambda_alpha : ndarray, shape (8,)
        Minimum infinity-norm allocation of Prop. 1 (2.12).
    lambda_beta : ndarray, shape (8,)
        After the null-space modulation (2.15); ``lambda_alpha`` if selective mapping is off.
    lambda_gamma : ndarray, shape (8,)
        Gradually switching selective mapping (2.17), unclipped; ``lambda_alpha`` if off.
    e : tuple of float
        ``(e_r, e_l)`` of (2.17), as used: with ``scale_to_limit`` raised above (2.17)'s where
        its fade would take a rotor past the limit; ``(1.0, 1.0)`` if off.
    near_zero : tuple of int
        0-based index of the near-zero rotor of each side (``0..3``, ``4..7``), ``-1`` if no
        rotor of that side is below ``eps1`` (or selective mapping is off).
    saturated : bool
        Whether the wrench asked for was beyond the rotors (scaled, ``scale``), the fade (2.17)
        was held back by the limit (``e`` raised) or any unclipped thrust exceeded
        ``thrust_max_n`` in magnitude (the command was clipped).
    wrench : ndarray, shape (6,)
        The wrench allocated: ``U``, or with ``scale_to_limit`` ``K + s (U - K)``, what the rotors
        can produce of it (:func:`scaled_to_limit`).
    scale : float
        ``s`` of :func:`scaled_to_limit` (1: all of ``U``).
    """

    command_n: np.ndarray
    lambda_o: np.ndarray
    lambda_alpha: np.ndarray
    lambda_beta: np.ndarray
    lambda_gamma: np.ndarray
    e: tuple[float, float]
    near_zero: tuple[int, int]
    saturated: bool
    wrench: np.ndarray
    scale: float = 1.0


# --------------------------------------------------------------------------------------------
# Functional core
# --------------------------------------------------------------------------------------------


def pseudo_inverse(B: np.ndarray) -> np.ndarray:
    """Right pseudo-inverse ``B^+ = B^T (B B^T)^-1`` (sec. 2.4.1), shape (n, 6).

    Raises
    ------
    ValueError
        If ``B`` is not full row rank.
    """
    B = np.asarray(B, dtype=float)
    if np.linalg.matrix_rank(B) < B.shape[0]:
        raise ValueError(f"mapping matrix must be full row rank ({B.shape[0]}); got rank {np.linalg.matrix_rank(B)}")
    # B^T (B B^T)^-1 = ((B B^T)^-1 B)^T since B B^T is symmetric.
    return np.linalg.solve(B @ B.T, B).T


def reduced_pseudo_inverse(B: np.ndarray, excluded: Sequence[int]) -> np.ndarray:
    """Reduced pseudo-inverse ``B^+_{\\S} = I_{\\S} B^T (B I_{\\S} B^T)^-1`` (sec. 2.4.2), shape (n, 6).

    ``I_{\\S}`` is the identity with the diagonal entries of the 0-based rotor indices in
    ``excluded`` set to zero, so the rows of the excluded rotors are zero and
    ``B B^+_{\\S} = I``.

    Raises
    ------
    ValueError
        If the mapping without the excluded rotors is not full row rank.
    """
    B = np.asarray(B, dtype=float)
    keep = np.ones(B.shape[1])
    keep[list(excluded)] = 0.0
    Bk = B * keep  # B I_{\S}
    if np.linalg.matrix_rank(Bk) < B.shape[0]:
        raise ValueError(f"mapping without rotors {list(excluded)} is not full row rank; cannot exclude them")
    return np.linalg.solve(Bk @ B.T, Bk).T


def reduced_pseudo_inverses(B: np.ndarray) -> np.ndarray:
    """All single-rotor reduced pseudo-inverses ``B^+_{\\i}``, ``i = 0..7``: shape (8, 8, 6), ``[i]`` is ``B^+_{\\i}``."""
    B = np.asarray(B, dtype=float)
    return np.stack([reduced_pseudo_inverse(B, (i,)) for i in range(B.shape[1])])


def infinity_norm_allocation(
    B_pinv: np.ndarray, U: np.ndarray, nu: np.ndarray = NU
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form minimum infinity-norm allocation of Prop. 1 (eq. 2.10, 2.12-2.14).

    Valid when ``B`` satisfies (2.11), so that ``N_B = blkdiag(nu, nu)`` (2.13).

    Parameters
    ----------
    B_pinv : ndarray, shape (8, 6)
        ``B^+`` from :func:`pseudo_inverse`.
    U : ndarray, shape (6,)
        Body-frame wrench ``[R^T f; tau]`` (eq. 2.8).
    nu : ndarray, shape (4,)
        Null vector of each side (2.11).

    Returns
    -------
    lambda_o : ndarray, shape (8,)
        ``B^+ U``.
    xi_prime : ndarray, shape (2,)
        ``[xi'_r; xi'_l]`` with ``xi'_s = -(max(lambda^nu_s) + min(lambda^nu_s)) / 2`` and
        ``lambda^nu_s = diag(nu) lambda_{o,s}`` (2.12).
    lambda_alpha : ndarray, shape (8,)
        ``lambda_o + N_B xi'`` (2.12), the minimiser of ``||lambda||_inf`` over ``B lambda = U``.
    """
    nu = np.asarray(nu, dtype=float)
    lambda_o = np.asarray(B_pinv, dtype=float) @ np.asarray(U, dtype=float)
    lam_nu = lambda_o.reshape(2, N_SIDE) * nu  # rows: r-side, l-side
    xi_prime = -0.5 * (lam_nu.max(axis=1) + lam_nu.min(axis=1))
    lambda_alpha = lambda_o + (nu * xi_prime[:, None]).ravel()
    return lambda_o, xi_prime, lambda_alpha


def scaled_to_limit(B_pinv: np.ndarray, U: np.ndarray, tmax: float, nu: np.ndarray = NU,
                    keep: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """The wrench ``K + s (U - K)`` (``0 <= s <= 1``, largest) that the rotors can produce, ``K``
    the wrench ``keep`` kept whole (an addition to the thesis, whose commands are clipped rotor by
    rotor): ``(K + s (U - K), s)``. ``keep``: the firmware passes the link's weight at its attitude
    (:func:`~link_firmware_sim.controllers.common.weight_wrench`), so that a demand beyond the rotors gives way
    in what it adds to hovering (a far target's force, an attitude torque, a neighbour's weight)
    and the link does not drop; ``None`` (or a ``keep`` the rotors cannot produce): ``K = 0``, the
    whole wrench scaled.

    ``U`` is feasible (some ``lambda`` with ``B lambda = U`` and every ``|lambda_i| <= tmax``) iff
    Prop. 1's minimum infinity norm is within ``tmax``, i.e. iff on each side the spread
    ``max - min`` of ``diag(nu) B^+ U`` is at most ``2 tmax`` (2.12); a feasible ``U`` is returned as
    it is (``s = 1``). Along ``K + s D`` the side values are ``a_i + s d_i`` (``a``, ``d``: of ``K``
    and ``D = U - K``), and every difference ``(a_i - a_j) + s (d_i - d_j) <= 2 tmax``: the
    largest ``s`` is the smallest of ``(2 tmax - (a_i - a_j)) / (d_i - d_j)`` over ``d_i > d_j``
    (with ``K = 0``, ``2 tmax`` over the wider side's spread of ``d``).

    Why: clipping rotor by rotor distorts the wrench (part of the torque lost, a side force
    gained; 5-15 % of the pitch torque of a tilted link at 110 % of its limit; a 300 N lateral
    demand, a target 30 m off, came out with no lift at all). In ``three_link`` with link 2
    unpowered and carried, each neighbour holds half of its weight at its joint, 0.5 m from its
    centre: 96 % of the 8 N rotors' limit when level. Clipped, the neighbours tipped 10-75 deg
    and the lowest link fell to 0.71-2.32 m (12 fleet runs); the whole wrench scaled, 6-20 deg
    and 1.96-2.31 m (30 runs); the weight kept, 2.11-2.27 m (8 runs). The torque first, then the
    force (PX4's multicopter order) held the attitude but spent lift on it: 1.71-1.91 m.
    """
    U = np.asarray(U, dtype=float)
    B_pinv = np.asarray(B_pinv, dtype=float)
    nu = np.asarray(nu, dtype=float)
    side_values = lambda V: (B_pinv @ V).reshape(2, N_SIDE) * nu  # noqa: E731
    if float(np.max(np.ptp(side_values(U), axis=1))) <= 2.0 * tmax:
        return U, 1.0
    K = np.zeros(WRENCH_DIM) if keep is None else np.asarray(keep, dtype=float)
    a = side_values(K)
    if not float(np.max(np.ptp(a, axis=1))) <= 2.0 * tmax:  # the kept wrench beyond the rotors too
        K, a = np.zeros(WRENCH_DIM), np.zeros((2, N_SIDE))
    D = U - K
    d = side_values(D)
    scale = 1.0
    for s in range(2):
        for i in range(N_SIDE):
            for j in range(N_SIDE):
                dd = d[s, i] - d[s, j]
                if dd > 0.0:
                    scale = min(scale, (2.0 * tmax - (a[s, i] - a[s, j])) / dd)
    scale = max(scale, 0.0)
    return K + scale * D, scale


def _modulate_side(b: Sequence[float], xi_pre: float, eps1: float, tmax: float = math.inf) -> float:
    """Exact solution of (2.15) for one side, within the thrust limit; see :func:`selective_modulation`.

    ``b[i] = nu_i lambda_{o,i} + xi'`` (the nu-scaled ``lambda_alpha`` of the side, 2.14), so
    rotor ``i`` is clear of the margin iff ``|b_i + xi''| >= eps1``: it forbids the open
    interval of ``xi''`` of half-width ``eps1`` centred at ``-b_i``. Every rotor stays within
    ``tmax`` iff ``lo = -tmax - min(b) <= xi'' <= tmax - max(b) = hi``.
    """
    thr = eps1 - MARGIN_TOL_N
    lo, hi = -tmax - min(b), tmax - max(b)
    if lo > hi:
        return 0.0  # beyond the limit even at Prop. 1's optimum (xi'' = 0): the least saturated
    if lo <= xi_pre <= hi and sum(abs(bi + xi_pre) < thr for bi in b) <= 1:
        return xi_pre  # feasible: no needless motion
    # Otherwise the closest feasible point is an endpoint of a forbidden interval or of the
    # limit's interval (the feasible set is a union of closed intervals with such endpoints).
    # Exact ties go to the smaller xi''.
    best = best_d = math.inf
    ends = [x for bi in b for x in (-bi - eps1, -bi + eps1)] + [x for x in (lo, hi) if math.isfinite(x)]
    for x in ends:
        d = abs(x - xi_pre)
        if lo <= x <= hi and (d < best_d or (d == best_d and x < best)) and sum(abs(bk + x) < thr for bk in b) <= 1:
            best, best_d = x, d
    if best_d == math.inf:
        return _least_within_margin(b, xi_pre, lo, hi)
    return best


def _second_smallest_magnitude(b: Sequence[float], x: float) -> float:
    """The second-smallest ``|b_i + x|`` of a side: (2.17) fades only the smallest."""
    return sorted(abs(bi + x) for bi in b)[1]


def _least_within_margin(b: Sequence[float], xi_pre: float, lo: float, hi: float) -> float:
    """``xi''`` in ``[lo, hi]`` where no point has three rotors clear of the margin: the point
    that takes the second-nearest-zero rotor furthest from zero (the nearest one (2.17) fades
    out), ties to the point nearest ``xi_pre``, then the smaller.

    The objective is piecewise linear in ``xi''`` with kinks at ``-b_i`` and at the midpoints
    ``-(b_i + b_j) / 2``, so its maximum over ``[lo, hi]`` is at one of these or at an end."""
    ends = [lo, hi] + [-bi for bi in b] + [-(b[i] + b[j]) * 0.5 for i in range(N_SIDE) for j in range(i + 1, N_SIDE)]
    best, best_f, best_d = lo, -math.inf, math.inf
    for x in ends:
        if not lo <= x <= hi:
            continue
        f, d = _second_smallest_magnitude(b, x), abs(x - xi_pre)
        if f > best_f or (f == best_f and (d < best_d or (d == best_d and x < best))):
            best, best_f, best_d = x, f, d
    return best


def _fade_within_limit(red: Sequence[float], beta: Sequence[float], e: float, tmax: float) -> float:
    """The smallest ``e' >= e`` for which (2.17)'s side ``red + e' (beta - red)`` is within
    ``+-tmax`` (``red``: the side rows of ``B^+_{\\j} U``; ``beta``: ``lambda_beta`` of the side,
    within the limit, so ``e' = 1`` always is). Each rotor allows an interval of ``e'`` that
    contains 1 (the side is affine in ``e'``), so ``e'`` is the largest of their lower ends."""
    for p, x in zip(red, beta):
        d = x - p
        if d > 0.0:
            e = max(e, (-tmax - p) / d)
        elif d < 0.0:
            e = max(e, (tmax - p) / d)
    return min(e, 1.0)


def _side_weight(mags: Sequence[float], eps0: float, eps1: float) -> tuple[float, int]:
    """``(e_s, j)`` of (2.17) for one side from ``|lambda_{beta,s,i}|``; ``j`` local, ``-1`` if clear.

    A side whose minimum is within :data:`MARGIN_TOL_N` of ``eps1`` counts as clear
    (``e_s = 1`` exactly), consistently with the margin test of (2.15).
    """
    m = min(mags)
    if m >= eps1 - MARGIN_TOL_N:
        return 1.0, -1
    e = (m - eps0) / (eps1 - eps0)
    return (e if e > 0.0 else 0.0), mags.index(m)  # type: ignore[attr-defined]


def selective_modulation(
    lambda_o: np.ndarray, xi_prime: np.ndarray, xi_pre: np.ndarray, nu: np.ndarray, eps1: float,
    tmax: float = math.inf,
) -> np.ndarray:
    """Null-space modulation ``xi''`` of (2.15), solved exactly (pure function).

    Per side ``s``: ``xi''_s = argmin |xi''_s - xi''_{s,pre}|`` subject to at least three of
    the four rotors having ``|lambda_{o,s,i} + nu_i (xi'_s + xi''_s)| >= eps1`` and, an addition
    to the thesis, every rotor ``|lambda_{o,s,i} + nu_i (xi'_s + xi''_s)| <= tmax``.

    By (2.14) each rotor forbids the open interval ``|xi'' - c_i| < eps1``,
    ``c_i = -(nu_i lambda_{o,s,i} + xi'_s)``; the feasible set is where at most one interval
    covers ``xi''``. The minimiser is ``xi''_pre`` if feasible, otherwise the feasible interval
    endpoint closest to it (exact ties: the smaller value). The feasible set is never empty
    (``max_i c_i + eps1`` is feasible), matching the thesis's always-feasible remark.

    Parameters
    ----------
    lambda_o : ndarray, shape (8,)
        ``B^+ U``.
    xi_prime : ndarray, shape (2,)
        ``[xi'_r; xi'_l]`` of Prop. 1 (2.12).
    xi_pre : ndarray, shape (2,)
        Previous solution ``[xi''_{r,pre}; xi''_{l,pre}]``.
    nu : ndarray, shape (4,)
        Null vector (2.11); entries must be ``+-1``.
    eps1 : float
        Thrust margin [N] (> 0).

    Returns
    -------
    ndarray, shape (2,)
        ``[xi''_r; xi''_l]``. The margin is enforced up to :data:`MARGIN_TOL_N`.

    Notes
    -----
    * The thesis writes the constraint as ``sum_i sgn(|.| - eps1) >= 3``; read literally (three
      ``+1`` and one ``-1`` sum to 2) it would demand all four rotors clear, contradicting the
      text ("at least three", "at most one rotor with its thrust magnitude less than eps1").
      It is implemented as "at least three of four clear".
    * Continuity: while ``xi''_pre`` stays feasible it is kept; otherwise it is pushed to the
      nearest endpoint, which moves with ``lambda_o`` (``|d xi''| <= 2 ||d lambda_o||_inf``). But
      when a rotor inside the margin is squeezed between two neighbours whose margins meet,
      the feasible component holding ``xi''_pre`` vanishes and every solution of (2.15) must
      jump (by up to about ``2 eps1``); the near-zero rotor then changes.
    * Nothing pulls ``xi''`` back to 0: after a modulation, ``lambda_beta`` stays off the
      infinity-norm optimum ``lambda_alpha`` until the constraint pushes it again (this follows
      (2.15) literally). Up to about ``2 eps1`` off it: near full load that would push a rotor
      past ``tmax`` where ``lambda_alpha`` fits (the ESC command is clipped, and the wrench with
      it). So the limit bounds ``xi''`` too (``tmax``; ``inf``: the thesis's (2.15) alone):
      where no point within the limit has three rotors clear of ``eps1``, the limit wins: the
      point within it that takes the second-nearest-zero rotor furthest from zero ((2.17)
      fades the nearest out; the other is left below the margin); beyond the
      limit even at ``xi'' = 0`` (an infeasible wrench, see :func:`scaled_to_limit`),
      ``xi'' = 0``, the optimum.
    """
    b = np.asarray(lambda_o, dtype=float).reshape(2, N_SIDE) * np.asarray(nu, dtype=float)
    b = b + np.asarray(xi_prime, dtype=float).reshape(2, 1)
    xi_pre = np.asarray(xi_pre, dtype=float).reshape(2)
    return np.array([_modulate_side(b[s].tolist(), float(xi_pre[s]), float(eps1), float(tmax)) for s in range(2)])


def selective_mapping_weights(
    lambda_beta: np.ndarray, eps0: float, eps1: float
) -> tuple[tuple[float, float], tuple[int, int]]:
    """Gradual switching weights ``(e_r, e_l)`` of (2.17) and the near-zero rotors.

    Per side, with ``m_s = min_i |lambda_{beta,s,i}|``: ``e_s = 1`` if ``m_s > eps1``,
    ``(m_s - eps0) / (eps1 - eps0)`` if ``eps0 < m_s <= eps1``, ``0`` if ``m_s <= eps0``
    (continuous in ``m_s``).

    Returns
    -------
    e : tuple of float
        ``(e_r, e_l)``.
    near_zero : tuple of int
        0-based index (``0..3`` r-side, ``4..7`` l-side) of ``argmin_i |lambda_{beta,s,i}|``
        if that minimum is below ``eps1``, else ``-1``.

    Notes
    -----
    A minimum within :data:`MARGIN_TOL_N` below ``eps1`` counts as clear (``e_s = 1``,
    index ``-1``), consistently with the margin test of (2.15) (a rotor pushed exactly onto
    the margin by (2.15) may land a rounding error below it).
    """
    mag = np.abs(np.asarray(lambda_beta, dtype=float)).reshape(2, N_SIDE)
    (e_r, j), (e_l, k) = (_side_weight(mag[s].tolist(), float(eps0), float(eps1)) for s in range(2))
    return (e_r, e_l), (j, k + N_SIDE if k >= 0 else -1)


def gradual_selective_mapping(
    B_pinv: np.ndarray,
    B_pinv_reduced: np.ndarray,
    U: np.ndarray,
    nu: np.ndarray,
    xi: np.ndarray,
    e: tuple[float, float],
    near_zero: tuple[int, int],
) -> np.ndarray:
    """``lambda_gamma = Bbar^+ U + Nbar_B xi`` of the gradually switching selective mapping (2.17).

    Side ``s`` rows of ``Bbar^+`` are ``e_s B^+_s + (1 - e_s) B^+_{s\\j}`` and
    ``Nbar_B = blkdiag(e_r nu, e_l nu)``, where by the decoupling property (2.18)-(2.19) the
    side rows of the reduced pseudo-inverse excluding ``j`` (r-side) and ``k`` (l-side) are the
    side rows of ``B^+_{\\j}`` and ``B^+_{\\k}``. Exact (``B lambda_gamma = U``) for every
    ``e_r, e_l`` by Prop. 2 when (2.11) holds.

    Parameters
    ----------
    B_pinv : ndarray, shape (8, 6)
        ``B^+``.
    B_pinv_reduced : ndarray, shape (8, 8, 6)
        ``[i] = B^+_{\\i}``, from :func:`reduced_pseudo_inverses`.
    U : ndarray, shape (6,)
        Body-frame wrench.
    nu : ndarray, shape (4,)
        Null vector (2.11).
    xi : ndarray, shape (2,)
        Total null-space coordinate ``xi' + xi''``.
    e : tuple of float
        ``(e_r, e_l)`` in ``[0, 1]``.
    near_zero : tuple of int
        ``(j, k)``, ``j`` in ``0..3`` and ``k`` in ``4..7``, or ``-1`` for none (then that
        side uses ``B^+_s``, i.e. ``e_s`` is immaterial for the ``B^+`` rows).

    Returns
    -------
    ndarray, shape (8,)
    """
    U = np.asarray(U, dtype=float)
    nu = np.asarray(nu, dtype=float)
    B_pinv = np.asarray(B_pinv, dtype=float)
    B_pinv_reduced = np.asarray(B_pinv_reduced, dtype=float)
    out = np.empty(N_ROTORS)
    for s, side in enumerate(SIDES):
        idx = near_zero[s]
        if idx == -1:
            reduced = B_pinv[side]
        else:
            if not side.start <= idx < side.stop:
                raise ValueError(f"near_zero[{s}] = {idx} is not a rotor of side {side.start}..{side.stop - 1}")
            reduced = B_pinv_reduced[idx][side]
        rows = e[s] * B_pinv[side] + (1.0 - e[s]) * reduced
        out[side] = rows @ U + e[s] * nu * xi[s]
    return out

"""Constraint application CA of the smoothly constrained Kalman filter (paper Alg. 1).

Starting from the EKF estimates ``x^E`` and their block-diagonal covariance ``P^E``, every
iteration ``j`` linearises the chain constraint (eq. 3, Jacobian ``C_j`` of eq. 4) at the
current estimate and applies it as a pseudo-measurement ``0 = c(x) `` with the weakening
covariance (Alg. 1)::

    P^w_j   = alpha e^{-j} C_j P^E C_j^T
    K_j     = P^C_j C_j^T (C_j P^C_j C_j^T + P^w_j)^{-1}
    x~_j+1  = -K_j c(x^C_j)
    P^C_j+1 = (I - K_j C_j) P^C_j (I - K_j C_j)^T + K_j P^w_j K_j^T      (Joseph form)

then injects ``x~`` (positions and velocities added, attitude by the normalised error
quaternion on the left: see :mod:`.so3`), until ``||c||_2 <= eps`` or ``max_iter``.

Two exact implementations are provided:

* :func:`constraint_apply_dense` is Alg. 1 written out on the full ``9n x 9n`` covariance.
  It is the reference, and the fastest for short chains.
* :func:`constraint_apply_structured` evaluates the same iterates without ever forming the
  dense covariance. The ``j`` pseudo-measurements are independent, so after ``J`` of them
  ``P^C_J = P^E - P^E Cs^T A^-1 Cs P^E`` with ``Cs = [C_0; ...; C_{J-1}]`` and
  ``A = blkdiag(P^w_a) + Cs P^E Cs^T`` (the Joseph recursion with the optimal gain equals
  this batch form), and by block elimination ``K_j c_j = P^E Cs^T A^-1 [0; ...; 0; c_j]``.
  Because ``C`` only couples neighbouring links and ``P^E`` is block diagonal, ``A``
  ordered constraint-major/iteration-minor is block tridiagonal with ``6J x 6J`` blocks:
  each iteration is one banded Cholesky solve, ``O(n J^3)``, and the per-link blocks of
  ``P^C`` come from a selected inversion of ``A``. It returns only the per-link diagonal
  blocks of ``P^C``, which is all the companion, the global step (eq. 6) and the replay
  tool use.

:func:`constraint_apply` picks one by chain length (``method="auto"``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..kernels.jit import ENABLED as _COMPILED, as_kernel_array
from ..kernels.sckf import constraint_apply_batched_kernel
from .chain import CON_DIM, CON_VEL, ERR_DIM, ERR_P, ERR_TH, ERR_V
from .constraints import (
    body_tip_vectors,
    dense_jacobian_from_blocks,
    jacobian_blocks_from_tips,
    residual_from_tips,
    tips_from_body,
)
from .so3 import quat_to_rotmat, retract, skew

__all__ = [
    "CAParams",
    "CAResult",
    "constraint_apply",
    "constraint_apply_dense",
    "constraint_apply_dense_batched",
    "constraint_apply_structured",
    "block_diag_covariance",
    "rate_noise_covariance",
    "diagonal_blocks",
    "inject_errors",
    "DENSE_MAX_LINKS",
]

#: Chains up to this many links use the dense reference in ``method="auto"`` (measured with
#: ``python -m sitl.bench scaling``: the dense form wins for short chains, where its
#: few large BLAS calls beat the structured solver's per-block overhead).
DENSE_MAX_LINKS = 3


@dataclass(frozen=True)
class CAParams:
    """Parameters of Alg. 1.

    Attributes:
        alpha: weakening factor of ``P^w`` (paper: 0.01, after De Geeter et al.).
        eps: stop when ``||c||_2 <= eps`` (stacked position [m] and velocity [m/s] error;
            paper: 0.01 in simulation, 0.05 in the outdoor experiment).
        max_iter: iteration cap; the result reports ``converged=False`` if it is hit.
        omega_std_rad_s: standard deviation per axis of the body rates the links report, the
            velocity input of eq. 3. Alg. 1 takes them as exact (0, the default); with a value
            the error they put into the corrected estimate is added to its covariance
            (:func:`rate_noise_covariance`; the estimate itself is unchanged).
    """

    alpha: float = 0.01
    eps: float = 0.01
    max_iter: int = 20
    omega_std_rad_s: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.alpha) and self.alpha > 0.0):
            raise ValueError(f"alpha must be a positive number, got {self.alpha!r}")
        if not (math.isfinite(self.eps) and self.eps >= 0.0):
            raise ValueError(f"eps must be a non-negative number, got {self.eps!r}")
        if int(self.max_iter) != self.max_iter or self.max_iter < 1:
            raise ValueError(f"max_iter must be a positive integer, got {self.max_iter!r}")
        if not (math.isfinite(self.omega_std_rad_s) and self.omega_std_rad_s >= 0.0):
            raise ValueError(f"omega_std_rad_s must be a non-negative number, got {self.omega_std_rad_s!r}")


@dataclass(frozen=True)
class CAResult:
    """Output of the constraint application.

    Attributes:
        p, v, q: corrected positions (n, 3), velocities (n, 3), attitudes (n, 4).
        P: (n, 9, 9) per-link diagonal blocks of the corrected covariance ``P^C``.
        iterations: number of CA iterations run (0 if the chain was already consistent).
        residual_history: ``||c||_2`` before the first iteration and after each one.
        converged: whether ``||c||_2 <= eps`` at the end.
        P_full: the full ``9n x 9n`` ``P^C`` (dense method only, else ``None``).
        P_ends: (2, n, 9, 9) cross-covariances ``P^C[i, 1]`` and ``P^C[i, n]`` of every link ``i``
            with the first and the last link (both methods): what the covariance of the
            semi-distributed global step needs (:func:`companion.estimation.semi.shifted_covariance`).
        W_ends: (2, n, 9, 3) cross-covariances of every link's corrected error with the body-rate
            error of the first and of the last link (``None`` when the rates count as exact,
            :attr:`CAParams.omega_std_rad_s` = 0).
        omega_std_rad_s: the body-rate noise the covariance accounts for.
    """

    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    P: np.ndarray
    iterations: int
    residual_history: np.ndarray
    converged: bool
    P_full: np.ndarray | None = None
    P_ends: np.ndarray | None = None
    W_ends: np.ndarray | None = None
    omega_std_rad_s: float = 0.0


def block_diag_covariance(P_blocks: np.ndarray) -> np.ndarray:
    """Stacked block-diagonal ``(..., 9n, 9n)`` covariance from ``(..., n, 9, 9)`` blocks."""
    n = P_blocks.shape[-3]
    full = np.zeros(P_blocks.shape[:-3] + (ERR_DIM * n, ERR_DIM * n))
    for i in range(n):
        full[..., ERR_DIM * i:ERR_DIM * (i + 1), ERR_DIM * i:ERR_DIM * (i + 1)] = P_blocks[..., i, :, :]
    return full


def diagonal_blocks(P_full: np.ndarray) -> np.ndarray:
    """``(..., n, 9, 9)`` per-link diagonal blocks of a stacked ``(..., 9n, 9n)`` covariance."""
    n = P_full.shape[-1] // ERR_DIM
    P4 = P_full.reshape(P_full.shape[:-2] + (n, ERR_DIM, n, ERR_DIM))
    return np.einsum("...ikil->...ikl", P4).copy()


def inject_errors(p, v, q, dx_links):
    """Apply per-link error states ``(..., n, 9)`` to the nominal state (Alg. 1 state update;
    attitudes by :func:`~.so3.retract`)."""
    return p + dx_links[..., ERR_P], v + dx_links[..., ERR_V], retract(q, dx_links[..., ERR_TH])


def constraint_apply_dense(p, v, q, w, d, P, params: CAParams = CAParams(), compiled: bool | None = None) -> CAResult:
    """Alg. 1 verbatim on the full covariance (reference implementation).

    Args:
        p, v, q, w, d: (n, 3), (n, 3), (n, 4), (n, 3), (n, 3) EKF positions, velocities,
            attitudes, body angular velocities and centre-to-right-tip vectors.
        P: (n, 9, 9) EKF covariance blocks (the block-diagonal ``P^E`` of independent links),
            or the whole (9n, 9n) ``P^E`` (links correlated by a measurement between them before
            the constraint, :mod:`.neighbour`).
        params: :class:`CAParams`.
        compiled: see :func:`constraint_apply_dense_batched`.
    """
    batch = [a[None] for a in (p, v, q, w, d, P)]
    return constraint_apply_dense_batched(*batch, params=params, compiled=compiled)[0]


def constraint_apply_dense_batched(p, v, q, w, d, P, params: CAParams = CAParams(),
                                   compiled: bool | None = None) -> list[CAResult]:
    """Alg. 1 on ``G`` independent chains of equal length at once (leading axis ``G``).

    Each chain keeps its own iteration counter ``j`` (in ``P^w_j``) and stops on its own
    ``||c|| <= eps``; the results equal running :func:`constraint_apply_dense` per chain. Used
    for the many small groups of the semi-distributed step, where per-call overhead dominates.
    ``P``: (G, n, 9, 9) blocks or (G, 9n, 9n) whole covariances (:func:`dense_prior`).

    The numpy code below is the specification. ``compiled`` (default: when numba is installed)
    runs each chain through :func:`companion.kernels.sckf.constraint_apply_kernel` instead, the same
    iterates in plain loops (``tests/unit/test_fast_paths.py``: agreement to 1e-12).
    """
    PE = dense_prior(P, p.shape[1])
    if _COMPILED if compiled is None else compiled:
        return _constraint_apply_compiled(p, v, q, w, d, PE, params)
    G, n = p.shape[:2]
    Pc = PE
    eye = np.eye(ERR_DIM * n)
    body = body_tip_vectors(w, d)
    a, b = tips_from_body(q, body)
    c = residual_from_tips(p, v, a, b)
    norms = np.sqrt(np.einsum("gi,gi->g", c, c))
    history = [[float(x)] for x in norms]
    j = np.zeros(G, dtype=int)
    active = norms > params.eps
    while active.any():
        C = dense_jacobian_from_blocks(*jacobian_blocks_from_tips(a, b))
        Ct = np.swapaxes(C, 1, 2)
        Pw = (params.alpha * np.exp(-j))[:, None, None] * (C @ PE @ Ct)
        PCt = Pc @ Ct
        S = C @ PCt + Pw
        K = np.swapaxes(np.linalg.solve(S, np.swapaxes(PCt, 1, 2)), 1, 2)  # K = P C^T S^-1
        A = eye - K @ C
        Pn = A @ Pc @ np.swapaxes(A, 1, 2) + K @ Pw @ np.swapaxes(K, 1, 2)  # Joseph form
        Pn = 0.5 * (Pn + np.swapaxes(Pn, 1, 2))
        dx = -(K @ c[:, :, None])[:, :, 0]
        sel = active[:, None, None]
        Pc = np.where(sel, Pn, Pc)
        pn, vn, qn = inject_errors(p, v, q, dx.reshape(G, n, ERR_DIM))
        p, v, q = np.where(sel, pn, p), np.where(sel, vn, v), np.where(sel, qn, q)
        a, b = tips_from_body(q, body)
        c = residual_from_tips(p, v, a, b)
        norms = np.sqrt(np.einsum("gi,gi->g", c, c))
        j += active
        for g in np.flatnonzero(active):
            history[g].append(float(norms[g]))
        active = active & (norms > params.eps) & (j < params.max_iter)
    KD = None
    if params.omega_std_rad_s > 0.0 and n > 1:  # (a chain that needed no correction took none)
        KD = (j > 0)[:, None, None] * _rate_noise_gain(q, w, d, PE)
    return _ca_results(p, v, q, Pc, j, history, KD, params)


def dense_prior(P: np.ndarray, n: int) -> np.ndarray:
    """The whole ``(..., 9n, 9n)`` prior ``P^E`` of ``n`` links from their ``(..., n, 9, 9)``
    blocks or as given whole; ``ValueError`` for another shape."""
    P = np.asarray(P, dtype=float)
    if P.shape[-3:] == (n, ERR_DIM, ERR_DIM):
        return block_diag_covariance(P)
    if P.shape[-2:] == (ERR_DIM * n, ERR_DIM * n):
        return P
    raise ValueError(f"P must be ({n}, 9, 9) blocks or a ({9 * n}, {9 * n}) covariance, got shape {P.shape}")


def _constraint_apply_compiled(p, v, q, w, d, PE, params: CAParams) -> list[CAResult]:
    """:func:`constraint_apply_dense_batched` by the compiled kernel (one call for every chain, with
    :func:`_ca_results`' covariance terms)."""
    G, n = p.shape[:2]
    N = ERR_DIM * n
    p, v, q = (np.array(x, dtype=float) for x in (p, v, q))  # the kernel updates them in place
    w, d = (as_kernel_array(x, (G, n, 3)) for x in (w, d))  # (it only reads these and P)
    history = np.empty((G, params.max_iter + 1))
    Pc, j, KD = np.empty((G, N, N)), np.empty(G, dtype=np.int64), np.empty((G, N, 3 * n))
    blocks, ends, W_ends = np.empty((G, n, ERR_DIM, ERR_DIM)), np.empty((G, 2, n, ERR_DIM, ERR_DIM)), np.empty(
        (G, 2, n, ERR_DIM, 3))
    rate = params.omega_std_rad_s > 0.0 and n > 1
    PE = as_kernel_array(PE, (G, N, N))
    settings = (float(params.alpha), float(params.eps), int(params.max_iter), rate, float(params.omega_std_rad_s**2))
    constraint_apply_batched_kernel((p, v, q, w, d), PE, settings, history, (Pc, j, KD, blocks, ends, W_ends))
    eps = params.eps
    return [CAResult(p=p[g], v=v[g], q=q[g], P=blocks[g], iterations=int(j[g]), residual_history=history[g, :j[g] + 1],
                     converged=bool(history[g, j[g]] <= eps), P_full=Pc[g], P_ends=ends[g],
                     W_ends=W_ends[g] if rate else None, omega_std_rad_s=params.omega_std_rad_s) for g in range(G)]


def _ca_results(p, v, q, Pc, iterations, histories, KD, params: CAParams) -> list[CAResult]:
    """The results of ``G`` chains' Alg. 1: the rate noise's covariance term and cross-covariances
    from its gain ``KD`` (``None``: the rates count as exact), the blocks (the compiled path
    computes the same terms in its kernel, :func:`companion.kernels.sckf.covariance_terms`)."""
    n = p.shape[1]
    W_ends = None
    if KD is not None:
        Pc = Pc + params.omega_std_rad_s**2 * _outer(KD)
        W_ends = _rate_end_columns(KD, n, params.omega_std_rad_s)
    blocks = diagonal_blocks(Pc)
    ends = _end_columns(Pc, n)
    return [
        CAResult(
            p=p[g],
            v=v[g],
            q=q[g],
            P=blocks[g],
            iterations=int(iterations[g]),
            residual_history=np.array(histories[g], dtype=float),
            converged=bool(histories[g][-1] <= params.eps),
            P_full=Pc[g],
            P_ends=ends[g],
            W_ends=None if W_ends is None else W_ends[g],
            omega_std_rad_s=params.omega_std_rad_s,
        )
        for g in range(len(iterations))
    ]


def rate_noise_covariance(q, w, d, P, omega_std_rad_s: float) -> np.ndarray:
    """The covariance ``(..., 9n, 9n)`` that white noise of std ``omega_std_rad_s`` per axis on
    the reported body rates ``w`` adds to the constrained estimate (an extension of Alg. 1,
    which takes the rates as exact).

    The rates enter eq. 3's velocity rows through the tip velocities ``R S(w) d = -R S(d) w``, so
    a rate error ``dw`` moves the constraint by ``D dw`` (joint ``i``: ``-R_i S(d_i) dw_i -
    R_{i+1} S(d_{i+1}) dw_{i+1}``), and Alg. 1, converged, removes the residual it sees by the
    projection ``K = P^E C^T (C P^E C^T)^-1`` (the weakening has faded): the estimate takes
    ``-K D dw`` with it. Returns ``sigma^2 K D D^T K^T`` at the attitudes ``q`` (the corrected
    ones), with ``P`` (..., n, 9, 9) the EKF blocks ``P^E`` (or the whole ``P^E``)."""
    return omega_std_rad_s**2 * _outer(_rate_noise_gain(q, w, d, dense_prior(P, q.shape[-2])))


def _outer(A: np.ndarray) -> np.ndarray:
    Q = A @ np.swapaxes(A, -1, -2)
    return 0.5 * (Q + np.swapaxes(Q, -1, -2))


def _rate_noise_gain(q, w, d, PE) -> np.ndarray:
    """``K D`` (..., 9n, 3n) of :func:`rate_noise_covariance` (``PE`` the whole prior)."""
    n = q.shape[-2]
    C = dense_jacobian_from_blocks(*jacobian_blocks_from_tips(*tips_from_body(q, body_tip_vectors(w, d))))
    B = -quat_to_rotmat(q) @ skew(d)  # (..., n, 3, 3): d(tip velocity offset)/d(w)
    D = np.zeros(q.shape[:-2] + (n - 1, CON_DIM, n, 3))
    for i in range(n - 1):
        D[..., i, CON_VEL, i, :] = B[..., i, :, :]
        D[..., i, CON_VEL, i + 1, :] = B[..., i + 1, :, :]
    D = D.reshape(q.shape[:-2] + (CON_DIM * (n - 1), 3 * n))
    PCt = PE @ np.swapaxes(C, -1, -2)
    return PCt @ np.linalg.solve(C @ PCt, D)


def _rate_end_columns(KD: np.ndarray, n: int, omega_std_rad_s: float) -> np.ndarray:
    """``(..., 2, n, 9, 3)``: ``Cov(x~_i, dw_first)`` and ``Cov(x~_i, dw_last)`` = ``-sigma^2 K D``'s
    columns of the first and the last link's rate."""
    cols = -omega_std_rad_s**2 * np.stack([KD[..., :, :3], KD[..., :, 3 * (n - 1):]], axis=-3)
    return cols.reshape(cols.shape[:-2] + (n, ERR_DIM, 3))


def _end_columns(P_full: np.ndarray, n: int) -> np.ndarray:
    """``(..., 2, n, 9, 9)``: the blocks ``P[i, 0]`` and ``P[i, n-1]`` of stacked ``(..., 9n, 9n)`` covariances."""
    cols = np.stack([P_full[..., :, :ERR_DIM], P_full[..., :, ERR_DIM * (n - 1):]], axis=-3)  # (..., 2, 9n, 9)
    return cols.reshape(cols.shape[:-2] + (n, ERR_DIM, ERR_DIM))


def _block_diag_ends(P: np.ndarray) -> np.ndarray:
    """:func:`_end_columns` of the block-diagonal covariance with blocks ``P`` (n, 9, 9)."""
    ends = np.zeros((2,) + P.shape)
    ends[0, 0] = P[0]
    ends[1, -1] = P[-1]
    return ends


@lru_cache(maxsize=128)
def _band_layout(m: int, bs: int):
    """Index maps between block-tridiagonal blocks and LAPACK upper band storage.

    Returns ``(u, M, d_src, d_dst, e_dst, u_diag, u_off)``: ``u`` super-diagonals, size
    ``M``; flat indices scattering the upper triangles of the diagonal blocks and the
    super-diagonal blocks into the band; and gather indices that read the diagonal and
    super-diagonal blocks of the band Cholesky factor ``U`` (``A = U^T U``) back out.
    """
    M = m * bs
    u = (2 * bs - 1) if m > 1 else (bs - 1)
    shape = (u + 1, M)
    i, x, y = np.meshgrid(np.arange(m), np.arange(bs), np.arange(bs), indexing="ij")
    upper = x <= y
    rows = (i * bs + x)[upper]
    cols = (i * bs + y)[upper]
    d_src = np.ravel_multi_index((i[upper], x[upper], y[upper]), (m, bs, bs))
    d_dst = np.ravel_multi_index((u + rows - cols, cols), shape)
    # Diagonal blocks of U: gather the upper triangle (the lower part is masked off by the
    # reader with triu).
    u_diag = np.zeros((m, bs, bs), dtype=np.intp)
    u_diag[i[upper], x[upper], y[upper]] = d_dst
    if m > 1:
        ie, xe, ye = np.meshgrid(np.arange(m - 1), np.arange(bs), np.arange(bs), indexing="ij")
        erows = (ie * bs + xe).ravel()
        ecols = ((ie + 1) * bs + ye).ravel()
        e_dst = np.ravel_multi_index((u + erows - ecols, ecols), shape)
        u_off = e_dst.reshape(m - 1, bs, bs)
    else:
        e_dst = np.zeros(0, dtype=np.intp)
        u_off = np.zeros((0, bs, bs), dtype=np.intp)
    return u, M, d_src, d_dst, e_dst, u_diag, u_off


class _BandedSPD:
    """Cholesky factorisation of an SPD block-tridiagonal matrix in band storage."""

    def __init__(self, D: np.ndarray, E: np.ndarray):
        m, bs, _ = D.shape
        self.m, self.bs = m, bs
        u, M, d_src, d_dst, e_dst, self._u_diag, self._u_off = _band_layout(m, bs)
        ab = np.zeros((u + 1) * M)
        ab[d_dst] = D.reshape(-1)[d_src]
        if m > 1:
            ab[e_dst] = E.reshape(-1)
        # (scipy's LAPACK is imported here, where the banded path runs: a process that never takes
        # it, a vehicle or the companion of short groups, does not load scipy.linalg: 26 MB, 0.16 s)
        from scipy.linalg.lapack import dpbtrf

        cb, info = dpbtrf(ab.reshape(u + 1, M), lower=0, overwrite_ab=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"constraint system is not positive definite (LAPACK pbtrf info={info})")
        self._cb = cb

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        from scipy.linalg.lapack import dpbtrs

        x, info = dpbtrs(self._cb, rhs.reshape(self.m * self.bs, -1), lower=0)
        if info != 0:  # pragma: no cover - only on invalid arguments
            raise np.linalg.LinAlgError(f"LAPACK pbtrs failed (info={info})")
        return x

    def selected_inverse(self) -> tuple[np.ndarray, np.ndarray]:
        """Diagonal blocks ``G_ii`` and super-diagonal blocks ``G_i,i+1`` of ``A^-1``.

        Takahashi recursion on ``A = U^T U`` (``U`` block upper bidiagonal):
        ``G_i,i+1 = -W_i G_i+1,i+1`` and ``G_ii = U_ii^-1 U_ii^-T + W_i G_i+1,i+1 W_i^T``
        with ``W_i = U_ii^-1 U_i,i+1``.
        """
        flat = self._cb.reshape(-1)
        Uinv = np.linalg.inv(np.triu(flat[self._u_diag]))
        UUt = Uinv @ np.swapaxes(Uinv, 1, 2)
        G = np.empty_like(UUt)
        G[-1] = UUt[-1]
        if self.m == 1:
            return G, np.zeros((0, self.bs, self.bs))
        Wm = Uinv[:-1] @ flat[self._u_off]
        WmT = np.swapaxes(Wm, 1, 2).copy()
        Go = np.empty_like(Wm)
        matmul = np.matmul
        for i in range(self.m - 2, -1, -1):
            g_next = matmul(Wm[i], G[i + 1])
            Go[i] = -g_next
            G[i] = UUt[i] + matmul(g_next, WmT[i])
        return G, Go


def constraint_apply_structured(p, v, q, w, d, P, params: CAParams = CAParams()) -> CAResult:
    """Alg. 1 evaluated through the block-tridiagonal structure (same iterates as dense).

    Arguments as :func:`constraint_apply_dense`. Returns per-link covariance blocks only.
    """
    n = p.shape[0]
    m = n - 1
    body = body_tip_vectors(w, d)
    a, b = tips_from_body(q, body)
    c = residual_from_tips(p, v, a, b)
    history = [math.sqrt(float(c @ c))]
    if m == 0 or history[-1] <= params.eps:
        return CAResult(p, v, q, P.copy(), 0, np.asarray(history), history[-1] <= params.eps,
                        P_ends=_block_diag_ends(P), omega_std_rad_s=params.omega_std_rad_s)
    Pl, Pr = P[:-1], P[1:]
    # Rows of C_a and C_a P^E for every iteration a, constraint-major: buffer[i, 6a:6a+6].
    cap = CON_DIM * params.max_iter
    Lb, Rb, LPb, RPb = (np.empty((m, cap, ERR_DIM)) for _ in range(4))
    j = 0
    while history[-1] > params.eps and j < params.max_iter:
        rows = slice(CON_DIM * j, CON_DIM * (j + 1))
        L, R = jacobian_blocks_from_tips(a, b)
        Lb[:, rows] = L
        Rb[:, rows] = R
        LPb[:, rows] = L @ Pl
        RPb[:, rows] = R @ Pr
        J = j + 1
        used = slice(0, CON_DIM * J)
        Lf, Rf, LPf, RPf = Lb[:, used], Rb[:, used], LPb[:, used], RPb[:, used]
        D, E = _assemble(Lf, Rf, LPf, RPf, params.alpha)
        system = _BandedSPD(D, E)
        rhs = np.zeros((m, J, CON_DIM))
        rhs[:, j, :] = c.reshape(m, CON_DIM)
        y = system.solve(rhs).reshape(m, CON_DIM * J, 1)
        # g = Cs^T y per link; the correction is -P^E g.
        g = np.zeros((n, ERR_DIM, 1))
        g[:-1] += np.swapaxes(Lf, 1, 2) @ y
        g[1:] += np.swapaxes(Rf, 1, 2) @ y
        dx = -(P @ g)[:, :, 0]
        p, v, q = inject_errors(p, v, q, dx)
        a, b = tips_from_body(q, body)
        c = residual_from_tips(p, v, a, b)
        history.append(math.sqrt(float(c @ c)))
        j += 1
    PC = _posterior_blocks(P, system, LPf, RPf)
    ends = _posterior_end_columns(P, system, Lf, Rf, LPf, RPf)
    W_ends = None
    if params.omega_std_rad_s > 0.0:
        KD = _rate_noise_gain(q, w, d, block_diag_covariance(P))
        Q = params.omega_std_rad_s**2 * _outer(KD)
        PC = PC + diagonal_blocks(Q)
        ends = ends + _end_columns(Q, n)
        W_ends = _rate_end_columns(KD, n, params.omega_std_rad_s)
    return CAResult(p, v, q, PC, j, np.asarray(history), history[-1] <= params.eps, P_ends=ends, W_ends=W_ends,
                    omega_std_rad_s=params.omega_std_rad_s)


def _assemble(Lf, Rf, LPf, RPf, alpha: float):
    """Blocks of ``A = blkdiag(P^w_a) + Cs P^E Cs^T`` in constraint-major order.

    ``Lf[i]``/``Rf[i]`` stack ``C_a``'s blocks of constraint ``i`` over iterations ``a``
    (``(6J, 9)``), ``LPf``/``RPf`` the same rows of ``C_a P^E``.
    """
    D = LPf @ np.swapaxes(Lf, 1, 2) + RPf @ np.swapaxes(Rf, 1, 2)
    E = RPf[:-1] @ np.swapaxes(Lf[1:], 1, 2)
    factor = _weakening_factor(alpha, Lf.shape[1] // CON_DIM)
    return D * factor, E * factor


@lru_cache(maxsize=256)
def _weakening_factor(alpha: float, J: int) -> np.ndarray:
    """``P^w_a = alpha e^-a C_a P^E C_a^T`` adds to the same-iteration blocks of ``Cs P^E Cs^T``:
    those scale by ``1 + alpha e^-a``, all others by 1."""
    it = np.repeat(np.arange(J), CON_DIM)
    scale = 1.0 + alpha * np.exp(-it.astype(float))
    return np.where(np.equal.outer(it, it), scale[:, None], 1.0)


def _posterior_blocks(P, system: _BandedSPD, LPf, RPf):
    """Per-link blocks of ``P^C = P^E - P^E Cs^T A^-1 Cs P^E`` (selected inversion)."""
    m = LPf.shape[0]
    G, Go = system.selected_inverse()
    corr = np.zeros_like(P)
    corr[:-1] += np.swapaxes(LPf, 1, 2) @ G @ LPf
    corr[1:] += np.swapaxes(RPf, 1, 2) @ G @ RPf
    if m > 1:
        X = np.swapaxes(RPf[:-1], 1, 2) @ Go @ LPf[1:]
        corr[1:-1] += X + np.swapaxes(X, 1, 2)
    PC = P - corr
    return 0.5 * (PC + np.swapaxes(PC, 1, 2))


def _posterior_end_columns(P, system: _BandedSPD, Lf, Rf, LPf, RPf):
    """``P^C[i, 0]`` and ``P^C[i, n-1]`` for every link ``i`` as ``(2, n, 9, 9)``:
    ``P^C[:, k] = P^E[:, k] - P^E Cs^T A^-1 (Cs P^E)[:, k]``, one banded solve with 18 right-hand
    sides. ``(Cs P^E)[:, k]`` is non-zero only in the rows of the constraints touching link ``k``
    (the first constraint's ``L`` rows for ``k = 0``, the last one's ``R`` rows for ``k = n-1``)."""
    n = P.shape[0]
    m, rows, _ = LPf.shape
    Z = np.zeros((m, rows, 2 * ERR_DIM))
    Z[0, :, :ERR_DIM] = LPf[0]
    Z[-1, :, ERR_DIM:] += RPf[-1]
    y = system.solve(Z).reshape(m, rows, 2 * ERR_DIM)
    g = np.zeros((n, ERR_DIM, 2 * ERR_DIM))
    g[:-1] += np.swapaxes(Lf, 1, 2) @ y
    g[1:] += np.swapaxes(Rf, 1, 2) @ y
    cols = -(P @ g)  # (n, 9, 18)
    cols[0, :, :ERR_DIM] += P[0]
    cols[-1, :, ERR_DIM:] += P[-1]
    return np.stack([cols[:, :, :ERR_DIM], cols[:, :, ERR_DIM:]])


def constraint_apply(p, v, q, w, d, P, params: CAParams = CAParams(), method: str = "auto") -> CAResult:
    """Constraint application (Alg. 1) on one chain or group.

    ``method`` is ``"dense"``, ``"structured"`` or ``"auto"`` (dense up to
    :data:`DENSE_MAX_LINKS` links, and for a whole (9n, 9n) covariance ``P``, which only the
    dense path takes). Both give the same iterates; inputs are assumed validated (see
    :func:`companion.estimation.chain.check_chain`).
    """
    if method == "auto":
        method = "dense" if p.shape[0] <= DENSE_MAX_LINKS or np.ndim(P) == 2 else "structured"
    if method == "dense":
        return constraint_apply_dense(p, v, q, w, d, P, params)
    if method == "structured":
        return constraint_apply_structured(p, v, q, w, d, P, params)
    raise ValueError(f"unknown method {method!r}; expected 'auto', 'dense' or 'structured'")

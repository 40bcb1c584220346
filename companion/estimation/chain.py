"""Chain layout of the estimation state: named slices, stacking order, input validation.

Per link the state is ``x_i = [p_i; v_i; q_i]`` (10 numbers; paper sec. III-A) and the error
state is ``x~_i = [dp_i; dv_i; dtheta_i]`` (9 numbers). The chain stacks links in order
(link 1 first, "right" = +x of the link body frame), so link ``i`` (0-based) owns rows
``9 i + ERR_P`` etc. of the stacked error state and constraint ``i`` (joint between links
``i`` and ``i+1``) owns rows ``6 i + CON_POS`` and ``6 i + CON_VEL`` of the stacked residual.

Units: positions m, velocities m/s, angular velocities rad/s (body frame), world frame z-up.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "ERR_P",
    "ERR_V",
    "ERR_TH",
    "ERR_PV",
    "ERR_DIM",
    "CON_POS",
    "CON_VEL",
    "CON_DIM",
    "ChainInputError",
    "check_chain",
    "check_covariance_blocks",
]

#: Error-state slices of one link: position, velocity, world-frame attitude error.
ERR_P = slice(0, 3)
ERR_V = slice(3, 6)
ERR_TH = slice(6, 9)
#: Position and velocity together (the [p; v] block of the global step, eq. 6).
ERR_PV = slice(0, 6)
ERR_DIM = 9

#: Rows of one joint constraint (eq. 3): tip position difference, tip velocity difference.
CON_POS = slice(0, 3)
CON_VEL = slice(3, 6)
CON_DIM = 6


class ChainInputError(ValueError):
    """Estimator input that cannot be used (wrong shape, NaN, non-PD covariance...).

    ``field`` names the offending input and ``index`` the link (0-based) when known.
    """

    def __init__(self, message: str, field: str | None = None, index: int | None = None):
        super().__init__(message)
        self.field = field
        self.index = index


def check_chain(
    p: np.ndarray,
    v: np.ndarray,
    q: np.ndarray,
    w: np.ndarray,
    d: np.ndarray,
    P: np.ndarray | None = None,
    *,
    quat_tol: float = 1e-2,
) -> tuple[np.ndarray, ...]:
    """Validate one chain snapshot and return float arrays with unit quaternions.

    Raises :class:`ChainInputError` naming the field and link on wrong shapes, non-finite
    values, non-unit quaternions (beyond ``quat_tol``) and covariance blocks that are not
    symmetric positive definite.
    """
    arrays = {"p": p, "v": v, "q": q, "w": w, "d": d}
    out = {}
    n = None
    for name, arr in arrays.items():
        a = np.asarray(arr, dtype=float)
        width = 4 if name == "q" else 3
        if a.ndim != 2 or a.shape[1] != width:
            raise ChainInputError(f"{name}: expected shape (n, {width}), got {a.shape}", name)
        if n is None:
            n = a.shape[0]
        elif a.shape[0] != n:
            raise ChainInputError(f"{name}: expected {n} links, got {a.shape[0]}", name)
        bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
        if bad.size:
            raise ChainInputError(f"{name}[{bad[0]}]: non-finite value", name, int(bad[0]))
        out[name] = a
    if n == 0:
        raise ChainInputError("chain has no links", "p")
    qn = np.linalg.norm(out["q"], axis=1)
    bad = np.flatnonzero(np.abs(qn - 1.0) > quat_tol)
    if bad.size:
        raise ChainInputError(
            f"q[{bad[0]}]: quaternion norm {qn[bad[0]]:.6g} is not 1 (tolerance {quat_tol})", "q", int(bad[0])
        )
    out["q"] = out["q"] / qn[:, None]
    result = [out["p"], out["v"], out["q"], out["w"], out["d"]]
    if P is not None:
        result.append(check_covariance_blocks(P, n))
    return tuple(result)


def check_covariance_blocks(P: np.ndarray, n: int, name: str = "P", sym_tol: float = 1e-6) -> np.ndarray:
    """Validate (n, 9, 9) covariance blocks: finite, symmetric, positive definite.

    Returns the blocks symmetrised. Raises :class:`ChainInputError` with the link index.
    """
    Pa = np.asarray(P, dtype=float)
    if Pa.shape != (n, ERR_DIM, ERR_DIM):
        raise ChainInputError(f"{name}: expected shape ({n}, 9, 9), got {Pa.shape}", name)
    finite = np.all(np.isfinite(Pa), axis=(1, 2))
    bad = np.flatnonzero(~finite)
    if bad.size:
        raise ChainInputError(f"{name}[{bad[0]}]: non-finite value", name, int(bad[0]))
    scale = np.maximum(np.max(np.abs(Pa), axis=(1, 2)), 1e-300)
    asym = np.max(np.abs(Pa - np.swapaxes(Pa, 1, 2)), axis=(1, 2)) / scale
    bad = np.flatnonzero(asym > sym_tol)
    if bad.size:
        raise ChainInputError(
            f"{name}[{bad[0]}]: covariance is not symmetric (relative asymmetry {asym[bad[0]]:.3g})",
            name,
            int(bad[0]),
        )
    Ps = 0.5 * (Pa + np.swapaxes(Pa, 1, 2))
    eig_min = np.linalg.eigvalsh(Ps)[:, 0]
    bad = np.flatnonzero(eig_min <= 0.0)
    if bad.size:
        raise ChainInputError(
            f"{name}[{bad[0]}]: covariance is not positive definite (smallest eigenvalue {eig_min[bad[0]]:.3g})",
            name,
            int(bad[0]),
        )
    return Ps

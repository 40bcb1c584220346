"""Offline replay of recorded link state streams through the constraint application.

Input ``.npz`` keys (K steps, n links; world frame z-up, SI units):

=====  ============  ==========================================================
key    shape         meaning
=====  ============  ==========================================================
``t``  (K,)          time of each step [s]
``p``  (K, n, 3)     link centre positions [m]
``v``  (K, n, 3)     link centre velocities [m/s]
``q``  (K, n, 4)     body-to-world attitude quaternions (w, x, y, z)
``w``  (K, n, 3)     body angular velocities [rad/s]
``P``  (K, n, 9, 9)  error-state covariance of [dp; dv; dtheta] per link
``d``  (n, 3)        centre-to-right-tip vector per link, body frame [m]
=====  ============  ==========================================================

Output ``.npz``: the same keys with ``p``, ``v``, ``q``, ``P`` corrected, plus
``residual_before`` and ``residual_after`` (K,) (2-norm of the stacked eq. 3 error over the
whole chain), ``iterations`` (K,) (CA loops of the slowest group), ``iterations_per_group``
(K, s), ``shifts`` (K, s, 6) (global-step [dp; dv] per group) and ``groups`` (the layout,
1-based, as a string).

Validation happens before any work; a bad file raises :class:`ReplayInputError` whose
message names the key and the index.
"""

from __future__ import annotations

import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .estimation.chain import ChainInputError, check_covariance_blocks
from .estimation.constraints import constraint_residual
from .estimation.sckf import CAParams
from .estimation.semi import Groups, format_groups, semi_distributed_apply, validate_groups

__all__ = ["REPLAY_KEYS", "ReplayInputError", "ReplayData", "load_replay_input", "replay", "save_replay_output"]

log = logging.getLogger(__name__)

REPLAY_KEYS = ("t", "p", "v", "q", "w", "P", "d")
QUAT_NORM_TOL = 1e-2


class ReplayInputError(ValueError):
    """A replay input file that cannot be used; the message names the key and index."""


@dataclass(frozen=True)
class ReplayData:
    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    w: np.ndarray
    P: np.ndarray
    d: np.ndarray

    @property
    def n_steps(self) -> int:
        return int(self.t.shape[0])

    @property
    def n_links(self) -> int:
        return int(self.d.shape[0])


def _where(key: str, idx: tuple[int, ...]) -> str:
    """``key[3, 1]`` plus a human reading of step / link (1-based link number)."""
    text = f"{key}[{', '.join(str(i) for i in idx)}]"
    if key == "d":
        return f"{text} (link {idx[0] + 1})"
    if key == "t":
        return f"{text} (step {idx[0]})"
    if len(idx) >= 2:
        return f"{text} (step {idx[0]}, link {idx[1] + 1})"
    return text


def load_replay_input(path: str | Path) -> ReplayData:
    """Read and validate a replay input file (see the module docstring)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            raw = {key: npz[key] for key in npz.files}
    except FileNotFoundError:
        raise ReplayInputError(f"{path}: no such file") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise ReplayInputError(f"{path}: not a readable .npz file ({exc})") from None
    missing = [k for k in REPLAY_KEYS if k not in raw]
    if missing:
        raise ReplayInputError(
            f"{path}: missing key(s) {', '.join(repr(k) for k in missing)} (required: {', '.join(REPLAY_KEYS)})"
        )
    arrays = {}
    for key in REPLAY_KEYS:
        a = raw[key]
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise ReplayInputError(f"{path}: key {key!r} has dtype {a.dtype}, expected numbers")
        arrays[key] = a.astype(float)
    t = arrays["t"]
    if t.ndim != 1 or t.shape[0] == 0:
        raise ReplayInputError(f"{path}: key 't' has shape {t.shape}, expected (K,) with K >= 1")
    K = t.shape[0]
    d = arrays["d"]
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] == 0:
        raise ReplayInputError(f"{path}: key 'd' has shape {d.shape}, expected (n, 3) with n >= 1")
    n = d.shape[0]
    expected = {"t": (K,), "p": (K, n, 3), "v": (K, n, 3), "q": (K, n, 4), "w": (K, n, 3), "P": (K, n, 9, 9), "d": (n, 3)}
    for key, shape in expected.items():
        if arrays[key].shape != shape:
            raise ReplayInputError(
                f"{path}: key {key!r} has shape {arrays[key].shape}, expected {shape} "
                f"(K={K} steps from 't', n={n} links from 'd')"
            )
    for key in REPLAY_KEYS:
        bad = np.argwhere(~np.isfinite(arrays[key]))
        if bad.size:
            idx = tuple(int(i) for i in bad[0])
            raise ReplayInputError(f"{path}: {_where(key, idx)} is not finite ({arrays[key][idx]})")
    if K > 1 and np.any(np.diff(t) < 0):
        k = int(np.flatnonzero(np.diff(t) < 0)[0]) + 1
        raise ReplayInputError(f"{path}: {_where('t', (k,))} goes back in time ({t[k - 1]} -> {t[k]})")
    qn = np.linalg.norm(arrays["q"], axis=-1)
    bad = np.argwhere(np.abs(qn - 1.0) > QUAT_NORM_TOL)
    if bad.size:
        idx = tuple(int(i) for i in bad[0])
        raise ReplayInputError(
            f"{path}: {_where('q', idx)} has norm {qn[idx]:.6g}; quaternions must be unit (tolerance {QUAT_NORM_TOL})"
        )
    arrays["q"] = arrays["q"] / qn[..., None]
    P = arrays["P"]
    for k in range(K):
        try:
            P[k] = check_covariance_blocks(P[k], n)
        except ChainInputError as exc:
            reason = str(exc).split(": ", 1)[-1]
            raise ReplayInputError(f"{path}: {_where('P', (k, exc.index))}: {reason}") from None
    return ReplayData(**arrays)


def replay(data: ReplayData, groups: Groups, params: CAParams = CAParams(), progress=None) -> dict[str, np.ndarray]:
    """Run Alg. 2 + eq. 6 (Alg. 1 for a single group) on every step of ``data``."""
    groups = validate_groups(groups, data.n_links)
    K, n, s = data.n_steps, data.n_links, len(groups)
    out = {
        "t": data.t.copy(),
        "p": np.empty_like(data.p),
        "v": np.empty_like(data.v),
        "q": np.empty_like(data.q),
        "w": data.w.copy(),
        "P": np.empty_like(data.P),
        "d": data.d.copy(),
        "residual_before": np.empty(K),
        "residual_after": np.empty(K),
        "iterations": np.empty(K, dtype=np.int64),
        "iterations_per_group": np.empty((K, s), dtype=np.int64),
        "shifts": np.empty((K, s, 6)),
    }
    for k in range(K):
        args = (data.p[k], data.v[k], data.q[k], data.w[k], data.d)
        out["residual_before"][k] = np.linalg.norm(constraint_residual(*args))
        res = semi_distributed_apply(*args, data.P[k], groups, params)
        out["p"][k], out["v"][k], out["q"][k], out["P"][k] = res.p, res.v, res.q, res.P
        out["residual_after"][k] = np.linalg.norm(constraint_residual(res.p, res.v, res.q, data.w[k], data.d))
        out["iterations_per_group"][k] = res.iterations
        out["iterations"][k] = res.iterations.max()
        out["shifts"][k] = res.shifts
        if progress is not None:
            progress(1)
    out["groups"] = np.array(format_groups(groups))
    log.info(
        "replayed %d steps of %d links in %d group(s): |c| mean %.4g -> %.4g, mean iterations %.2f",
        K,
        n,
        s,
        out["residual_before"].mean(),
        out["residual_after"].mean(),
        out["iterations"].mean(),
    )
    return out


def save_replay_output(path: str | Path, out: dict[str, np.ndarray]) -> None:
    """Write ``out`` to exactly ``path`` (no ``.npz`` suffix appended)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **out)

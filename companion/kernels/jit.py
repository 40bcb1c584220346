"""The one switch and decorator of every compiled kernel in the project.

numba is not an onboard dependency: it comes with the ``sim`` extra. Without it (the Raspberry Pi
install), or with ``SKELETON_JIT=0`` in the environment, :data:`ENABLED` is false, :func:`jit`
returns the function unchanged and every caller runs the numpy specification instead of the
kernel (one log line says so).

Compilation happens at a kernel's first call (or at a warm-up, ``kernels.warm``) and is cached on
disk: ``__pycache__`` beside the kernel's module, or ``NUMBA_CACHE_DIR`` when set (e.g. for a
read-only install), so that later processes load the machine code instead of compiling it.
"""

from __future__ import annotations

import logging
import os

import numpy as np

__all__ = ["ENABLED", "jit", "as_kernel_array"]

log = logging.getLogger(__name__)


def _want_jit() -> bool:
    return os.environ.get("SKELETON_JIT", "1").strip().lower() not in ("0", "false", "no", "off")


try:
    if not _want_jit():
        raise ImportError("SKELETON_JIT=0")
    import numba

    #: the kernels are compiled (numba importable and not turned off with ``SKELETON_JIT=0``)
    ENABLED = True

    def jit(fn):
        """``numba.njit`` as every kernel uses it: cached on disk, numpy's float semantics (a
        division by zero gives inf / nan, as in the numpy specification, instead of raising), no
        fast-math (IEEE arithmetic, so the kernels reorder no sums within one expression)."""
        return numba.njit(cache=True, error_model="numpy", nogil=True)(fn)

except ImportError as exc:  # the onboard install (no numba) or turned off
    ENABLED = False
    log.info("compiled kernels off (%s): the numpy path runs", exc)

    def jit(fn):
        return fn


def as_kernel_array(x, shape: tuple) -> np.ndarray:
    """``x`` as the C-contiguous, writeable float64 array of ``shape`` a kernel reads (broadcast if
    it is not that shape); ``x`` itself, not a copy, when it already is one (a kernel never writes
    to its inputs unless its docstring says so; a read-only array is copied all the same, as numba
    would compile the kernel again for it)."""
    if type(x) is np.ndarray and x.shape == shape and x.dtype == np.float64:
        flags = x.flags
        if flags.c_contiguous and flags.writeable:
            return x
    return np.array(np.broadcast_to(np.asarray(x, dtype=float), shape), order="C")  # (a writeable copy)

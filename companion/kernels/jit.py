"""The one switch and decorator of every compiled kernel in the project.

numba is not an onboard dependency: it comes with the ``sim`` extra. Without it (the Raspberry Pi
install), or with ``SKELETON_JIT=0`` in the environment, :data:`ENABLED` is false, :func:`jit`
returns the function unchanged and every caller runs the numpy specification instead of the
kernel (one log line says so).

Compilation happens at a kernel's first call (or at a warm-up, ``kernels.warm``) and is cached on
disk: ``__pycache__`` beside the kernel's module, or ``NUMBA_CACHE_DIR`` when set (e.g. for a
read-only install), so that later processes load the machine code instead of compiling it.

numba checks a cached kernel against its own module's source only, yet the machine code holds
the kernels it calls from other modules and the layout constants it imports: after an update
that changed only those, it would load the old code. So the first import here fingerprints every
kernel package's sources (:data:`KERNEL_PACKAGES`) and, where the fingerprint left in a package's
``__pycache__`` differs, drops that package's cached kernels (:func:`drop_stale_caches`). A
cache under ``NUMBA_CACHE_DIR`` is not checked: clear it after an update.
"""

from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path

import numpy as np

__all__ = ["ENABLED", "KERNEL_PACKAGES", "jit", "as_kernel_array", "drop_stale_caches"]

log = logging.getLogger(__name__)

#: the folders of compiled kernels (sibling packages of one install; a missing one is skipped)
KERNEL_PACKAGES = ("companion/kernels", "link_firmware_sim/kernels", "sitl/kernels")
_FINGERPRINT = "kernels.fingerprint"


def drop_stale_caches(folders) -> list[Path]:
    """Every ``*.nbi`` / ``*.nbc`` in the ``__pycache__`` of each of ``folders`` whose fingerprint
    file differs from the fingerprint of all their ``*.py`` sources together, removed (the new
    fingerprint written); returns the folders dropped. A folder that cannot be written (a
    read-only install) is left as it is."""
    folders = [Path(f) for f in folders if Path(f).is_dir()]
    digest = hashlib.sha256()
    for f in folders:
        for src in sorted(f.glob("*.py")):
            digest.update(src.name.encode())
            digest.update(src.read_bytes())
    fingerprint = digest.hexdigest()
    dropped = []
    for f in folders:
        cache = f / "__pycache__"
        stamp = cache / _FINGERPRINT
        try:
            if stamp.is_file() and stamp.read_text().strip() == fingerprint:
                continue
            cache.mkdir(exist_ok=True)
            for old in [*cache.glob("*.nbi"), *cache.glob("*.nbc")]:
                old.unlink(missing_ok=True)
            stamp.write_text(fingerprint + "\n")
            dropped.append(f)
        except OSError as exc:
            log.debug("kernel cache in %s left as it is: %s", cache, exc)
    return dropped


def _want_jit() -> bool:
    return os.environ.get("SKELETON_JIT", "1").strip().lower() not in ("0", "false", "no", "off")


try:
    if not _want_jit():
        raise ImportError("SKELETON_JIT=0")
    import numba

    #: the kernels are compiled (numba importable and not turned off with ``SKELETON_JIT=0``)
    ENABLED = True
    drop_stale_caches(Path(__file__).resolve().parents[2] / p for p in KERNEL_PACKAGES)

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

"""Compile (first run) or load from numba's cache (later runs) every kernel of this package, for
the argument types their callers pass, before the first flight step needs them.

It imports the kernels it warms, never their callers: each is compiled for the signature of example
arguments built as the callers build theirs (C-contiguous writeable float64 arrays, tuples of them,
Python floats, ints and bools), without running it. ``tests/unit/test_fast_paths.py`` checks that the
callers then find every signature they use.
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import contextmanager

import numpy as np

from .align import align_kernel, attitude_errors_kernel
from .cpg import body_step_kernel, cpg_output_kernel, cpg_step_kernel, link_targets_kernel
from .dynamics import feedforward_kernel, passive_torques_kernel
from .gate import joint_nis_kernel
from .jit import ENABLED
from .sckf import constraint_apply_batched_kernel
from .semi import group_terms_kernel
from .trajectory import trajectory_kernel

__all__ = ["COMPILING_NOTE_S", "ENABLED", "compile_notice", "warm_up", "load"]

#: a warm-up still running after this long [s] is compiling, and says so (a load takes well under it)
COMPILING_NOTE_S = 3.0


@contextmanager
def compile_notice(what: str, logger: logging.Logger, report_done: bool = True):
    """Around a warm-up of ``what`` (e.g. "the firmware's compiled kernels"): a warning on
    ``logger`` once it has run :data:`COMPILING_NOTE_S` (a machine's first run compiles, for a
    minute or two; later runs load numba's cache) and then, with ``report_done`` (a caller that
    logs the time itself passes false), one with the seconds it took. A quick warm-up says nothing."""
    t0 = time.perf_counter()
    note = threading.Timer(COMPILING_NOTE_S, logger.warning, (f"loading {what}; a first run on this machine compiles "
                                                              "them (a minute or two, once), later runs load them "
                                                              "from numba's cache",))
    note.daemon = True
    note.start()
    try:
        yield
    finally:
        note.cancel()
        seconds = time.perf_counter() - t0
        if report_done and seconds > COMPILING_NOTE_S:
            logger.warning("%s ready in %.0f s", what[0].upper() + what[1:], seconds)


def load(kernel, *args) -> None:
    """Compile ``kernel`` (or load it from the cache) for the types of ``args``, without running it."""
    import numba

    kernel.compile(tuple(numba.typeof(a) for a in args))


def warm_up(*, cpg: bool = True) -> float:
    """The kernels of this package compiled or loaded; returns the seconds it took (0 without the
    compiled kernels). ``cpg``: the CPG motion generator's too (only a ``trajectory.kind = "cpg"``
    flight runs them)."""
    if not ENABLED:
        return 0.0
    t0 = time.perf_counter()
    n, G = 2, 1
    v3, m3 = np.zeros((n, 3)), np.zeros((n, 3, 3))
    chain = (v3, v3, np.zeros((n, 4)), v3, v3)
    P = np.zeros((n, 9, 9))
    load(passive_torques_kernel, m3, v3, 1.0, 1.0, np.zeros((n - 1, 3)))
    load(feedforward_kernel, (v3, v3, v3, v3), m3, np.zeros((n - 1, 3)), (np.zeros(3), np.zeros(3), 1.0, 9.8, 2.0),
         np.ones(n), (v3, v3, np.zeros((n - 1, 3)), np.zeros((n, 6))))
    stacked = tuple(a[None].copy() for a in chain)
    load(constraint_apply_batched_kernel, stacked, np.zeros((G, 9 * n, 9 * n)), (1.0, 1e-9, 20, True, 1e-4),
         np.zeros((G, 21)), (np.zeros((G, 9 * n, 9 * n)), np.zeros(G, dtype=np.int64), np.zeros((G, 9 * n, 3 * n)),
                             np.zeros((G, n, 9, 9)), np.zeros((G, 2, n, 9, 9)), np.zeros((G, 2, n, 9, 3))))
    load(joint_nis_kernel, chain, P, 0.01, 0.01, np.zeros(n - 1))
    load(group_terms_kernel, chain, P, (np.zeros((2, n, 9, 9)), np.zeros((2, n, 9, 3))), True, 1e-4,
         (np.zeros((2, 6)), np.zeros((6, 6)), np.zeros((12, 12)), np.zeros((n, 12, 9))))
    load(align_kernel, 1.0, np.zeros(n), v3, v3, np.zeros((n, 4)), v3, v3, np.zeros((n, 4)))
    load(attitude_errors_kernel, np.zeros((n, 4)), np.zeros((n, 4)), v3)
    load(trajectory_kernel, np.zeros(5), np.zeros((5, 3)), (np.zeros(n), np.zeros(4), np.zeros(3)), 1e-3,
         (v3, np.zeros((n, 4)), m3, v3, v3, v3, v3))
    if cpg:
        _warm_cpg(n, v3, m3)
    return time.perf_counter() - t0


def _warm_cpg(n: int, v3: np.ndarray, m3: np.ndarray) -> None:
    """The CPG motion generator's step (:class:`companion.motion.generator.MotionGenerator`)."""
    cpg_state = (np.zeros((n, 2)), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n))
    shape = (np.zeros(n), np.zeros(n), 1.0, 1.0, 1.0, 1.0)
    coupling = (np.zeros(2, dtype=np.int64), np.zeros(2, dtype=np.int64), np.zeros(2))
    body = (np.zeros(3), np.zeros(3), np.eye(3), np.zeros(3))
    water = (1.0, 1.0, 1.0, np.ones(3))
    load(cpg_step_kernel, cpg_state, shape, coupling, np.zeros(2), np.zeros(2), 0.02)
    load(cpg_output_kernel, cpg_state, shape, coupling, np.zeros(2), np.zeros(2), (m3, v3))
    load(body_step_kernel, body, m3, v3, 0.5, water, 0.02, 4, body)
    load(link_targets_kernel, body, m3, v3, 0.5, (v3, v3, m3, v3))

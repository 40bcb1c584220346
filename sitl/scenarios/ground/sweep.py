"""What the ground robots' sweeps share (eq. 4.1's phase map, eq. 4.2's fits): a grid of jobs flown
in one process or several, the commit the data came from, comma-separated values."""

from __future__ import annotations

import subprocess
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

__all__ = ["run_jobs", "commit", "floats"]


def run_jobs(fn: Callable, jobs: Sequence, workers: int = 1) -> list:
    """``fn(job)`` for every job, in order; ``workers`` > 1: that many processes (``fn`` must be a
    module-level function)."""
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            return list(pool.map(fn, jobs, chunksize=max(1, len(jobs) // (4 * workers))))
    return [fn(j) for j in jobs]


def commit() -> str:
    """The working tree's commit (``unknown`` outside a git checkout)."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10,
                             cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() or "unknown"


def floats(text: str) -> list[float]:
    """``"1,2.5, 3"`` -> ``[1.0, 2.5, 3.0]``."""
    return [float(x) for x in text.split(",") if x.strip()]

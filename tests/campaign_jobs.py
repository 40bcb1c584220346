"""Cheap campaign jobs (sitl.campaign.engine.Job functions) for the engine's tests: importable by
Dask's worker processes, each writing into its run folder as a flight does."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path


def square(out_dir: Path, x: float) -> dict:
    (Path(out_dir) / "out.txt").write_text(repr(x * x))
    return {"x": x, "y": x * x, "per_link": [x, 2 * x]}


def fail_at(out_dir: Path, x: float, bad: float) -> dict:
    if x == bad:
        raise RuntimeError(f"refused {x}")
    return square(out_dir, x)


def interrupt_at(out_dir: Path, x: float, stop: float) -> dict:
    if x == stop:
        raise KeyboardInterrupt
    return square(out_dir, x)


def _die() -> None:
    time.sleep(0.5)  # the worker's "started" event leaves first, as it does from a flight
    os.kill(os.getpid(), signal.SIGKILL)


def die_once(out_dir: Path, x: float) -> dict:
    """Kills its worker process the first time (a marker in its folder), then succeeds."""
    marker = Path(out_dir) / "died"
    if not marker.exists():
        marker.write_text("")
        _die()
    return square(out_dir, x)


def die_always(out_dir: Path, x: float) -> dict:
    _die()
    return {}

"""What the ground robots' sweeps share (eq. 4.1's phase map, eq. 4.2's fits, the inverse models'
data): a grid of jobs flown in one process, several, or on a Dask cluster, the commit the data came from,
comma-separated values, and the inverse models' command-line options, their runs split into
training and held-out ones, and the held-out recovery error."""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

__all__ = ["run_jobs", "commit", "floats", "sweep_parser", "parse_sweep", "inverse_options", "parse_inverse",
           "train_held", "recovery_error_deg"]


def run_jobs(fn: Callable, jobs: Sequence, workers: int = 1, scheduler: str | None = None) -> list:
    """``fn(job)`` for every job, in order; ``scheduler`` (``tcp://HOST:PORT``): as tasks on that Dask
    cluster (the campaign engine's: :mod:`sitl.campaign.cluster`), else ``workers`` > 1: that many
    local processes, else here. ``fn`` must be a module-level function."""
    if scheduler is not None:
        from sitl.campaign.cluster import connect

        with connect(scheduler) as client:
            return client.gather(client.map(fn, list(jobs), pure=False))
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


def sweep_parser(prog: str, doc: str, kind: str, out_help: str, duration_s: float) -> argparse.ArgumentParser:
    """A sweep's command line with the options every sweep has: ``--config`` (a ``kind``
    scenario), ``--duration``, ``--workers``, ``--scheduler``, ``--out``; the sweep adds its own."""
    p = argparse.ArgumentParser(prog=prog, description=doc.split("\n\n")[0])
    p.add_argument("--config", required=True, help=f"a {kind} scenario (its robot, ground, CPG)")
    p.add_argument("--duration", type=float, default=duration_s, help="simulated seconds per run")
    p.add_argument("--workers", type=int, default=1, help="local processes")
    p.add_argument("--scheduler", default=None,
                   help="fly the runs on this Dask scheduler's workers instead (tcp://HOST:PORT; the campaign engine's "
                        "cluster, docs/campaigns.md)")
    p.add_argument("--out", type=Path, required=True, help=out_help)
    return p


def parse_sweep(parser: argparse.ArgumentParser, argv, kind: str):
    """``(args, scenario)``: the command line parsed, and its ``--config`` read with ``--duration``
    if it is a ``kind`` scenario (else ``None``, the error printed)."""
    from sitl.scenarios import load

    args = parser.parse_args(argv)
    found, sc = load(args.config, duration_s=args.duration)
    if found.name != kind:
        print(f"error: {args.config}: a {kind} scenario, not {found.name}", file=sys.stderr)
        return args, None
    return args, sc


def inverse_options(p: argparse.ArgumentParser, samples: int, held_out: int, A: str, B_max: float) -> None:
    """Add an inverse model's data options to ``p``: ``--samples``, ``--held-out`` (runs, each
    also mirrored), ``--A`` (the amplitude range), ``--B-max``, ``--seed``; the defaults given."""
    p.add_argument("--samples", type=int, default=samples, help="training runs (each also mirrored)")
    p.add_argument("--held-out", type=int, default=held_out, help="held-out runs (each also mirrored)")
    p.add_argument("--A", default=A, help="amplitude range [deg]: low,high")
    p.add_argument("--B-max", type=float, default=B_max, help="largest bias [deg] (and its mirror)")
    p.add_argument("--seed", type=int, default=0, help="the data's and the training's seed")


def parse_inverse(parser: argparse.ArgumentParser, argv, kind: str):
    """An inverse model's data command line (:func:`inverse_options`) parsed: ``(args, scenario,
    [A_low, A_high])``, or ``None`` after printing what is wrong (not a ``kind`` scenario, or
    ``--A`` not ``low,high`` with ``0 <= low < high``)."""
    args, sc = parse_sweep(parser, argv, kind)
    if sc is None:
        return None
    A = floats(args.A)
    if len(A) != 2 or not 0 <= A[0] < A[1]:
        print(f"error: --A: low,high with 0 <= low < high, got {args.A}", file=sys.stderr)
        return None
    return args, sc, A


def train_held(samples: int, held_out: int) -> tuple[np.ndarray, np.ndarray]:
    """The training and the held-out rows of a data set of ``samples + held_out`` runs followed by
    their mirror images: each run with its mirror image."""
    n = samples + held_out
    return np.r_[0:samples, n:n + samples], np.r_[samples:n, n + samples:2 * n]


def recovery_error_deg(model, eta: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Per input (A, B), the RMS [deg] of an inverse ``model``'s inputs for the motions ``xi``
    against the inputs ``eta`` [rad] that made them."""
    return np.degrees(np.sqrt(np.mean((model(xi) - eta) ** 2, axis=0)))

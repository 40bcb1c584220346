"""Helpers every command-line tool of the stack uses (never the pure core): BLAS threads, run folders, logging,
argument types.

* BLAS threading: the estimator works on many small matrices (9x9 blocks, banded systems
  of a few hundred rows). On a small machine OpenBLAS's threads make those calls many times
  slower than one thread does, so every CLI runs with one BLAS thread.
* Run folders: every run writes its artefacts into one folder that it names.
* Logging setup for CLIs.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

__all__ = ["LOG_FORMAT", "single_thread_blas", "make_run_dir", "setup_logging", "run_subcommand", "progress_bar",
           "finite_number", "seconds", "nonnegative_seconds", "pace"]


class _NoBar:
    """Stands in for a progress bar where tqdm is not installed (the onboard base install)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def update(self, n=1) -> None:
        return None


def progress_bar(**kwargs):
    """A tqdm progress bar (``kwargs`` as tqdm's) on stderr, or a silent stand-in without tqdm."""
    try:
        from tqdm import tqdm
    except ImportError:
        return _NoBar()
    return tqdm(file=sys.stderr, **kwargs)


def single_thread_blas():
    """Limit BLAS/LAPACK to one thread for this process (returns the limiter object)."""
    return threadpool_limits(limits=1, user_api="blas")


def make_run_dir(kind: str, out: str | Path | None = None, root: str | Path = "runs") -> Path:
    """Create and return the run folder: ``out`` if given, else ``runs/<kind>-<UTC time>``."""
    if out is None:
        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        path = Path(root) / f"{kind}-{stamp}"
        suffix = 1
        while path.exists():
            suffix += 1
            path = Path(root) / f"{kind}-{stamp}-{suffix}"
    else:
        path = Path(out)
    path.mkdir(parents=True, exist_ok=True)
    return path


def finite_number(text: str, check, rule: str) -> float:
    """``text`` as a finite number for which ``check(value)`` holds; else argparse's type error,
    saying ``rule``."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and check(value)):
        raise argparse.ArgumentTypeError(f"{text!r}: {rule}")
    return value


def pace(text: str) -> float:
    """argparse type of a pace (``--speed F``: F times real time, 0 unpaced): a finite number >= 0."""
    return finite_number(text, lambda v: v >= 0.0, "the pace must be >= 0 (0: unpaced)")


def seconds(text: str) -> float:
    """argparse type of a length of time (``--duration S``): a finite number > 0."""
    return finite_number(text, lambda v: v > 0.0, "a duration is a finite number of seconds > 0")


def nonnegative_seconds(text: str) -> float:
    """argparse type of a time or a delay that may be zero (``--at S``, ``--latency S``): a finite
    number >= 0."""
    return finite_number(text, lambda v: v >= 0.0, "a finite number of seconds >= 0")


LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


#: libraries whose INFO lines say nothing to a user of these commands (PyOpenGL's note that its
#: optional accelerator is missing, at every run that renders)
QUIET_LIBRARIES = ("OpenGL",)


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, format=LOG_FORMAT)
    if not verbose:
        for name in QUIET_LIBRARIES:
            logging.getLogger(name).setLevel(logging.WARNING)


def run_subcommand(parser: argparse.ArgumentParser, argv=None, usage_exit: int = 2, args=None) -> int:
    """Parse ``argv`` and run the chosen subcommand's ``func(args)`` the way every CLI here does.

    Without a subcommand: the help on stderr and ``usage_exit``. ``args`` may be given already
    parsed (a CLI that picks a default command). Otherwise logging is set up
    and the command runs with single-threaded BLAS; its return value is the exit code.
    """
    if args is None:
        args = parser.parse_args(argv)
    if getattr(args, "command", None) is None:
        parser.print_help(sys.stderr)
        return usage_exit
    setup_logging()
    with single_thread_blas():
        return args.func(args)

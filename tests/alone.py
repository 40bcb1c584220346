"""Tests that run alone on the host under pytest-xdist: a writer-preferring lock over the workers.

A fleet test (one that takes the ``fleet_ports`` fixture: a dozen processes on the lockstep, unpaced
or paced) measures timing the suite's other tests would skew: on 2 cores beside a second fleet or a
batch flight, a companion takes its inputs late in simulated time. Every other test holds the
lock shared; a fleet test holds it exclusively. A test first passes a gate (a second lock file)
that a fleet test holds while it waits, so the others cannot keep it waiting for ever. The lock
files are in the session's shared temporary folder; without xdist nothing is locked.
"""

from __future__ import annotations

import fcntl
import os
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Iterator


@contextmanager
def _flock(path: Path, mode: int) -> Iterator[None]:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, mode)
        yield
    finally:
        os.close(fd)  # (closing releases the lock)


@contextmanager
def host_turn(folder: Path, alone: bool) -> Iterator[None]:
    """The turn of one test: exclusive with ``alone``, shared otherwise (module docstring)."""
    gate, lock = folder / "alone.gate", folder / "alone.lock"
    with ExitStack() as turn:
        with _flock(gate, fcntl.LOCK_EX):  # the gate is let go once the turn is held
            turn.enter_context(_flock(lock, fcntl.LOCK_EX if alone else fcntl.LOCK_SH))
        yield

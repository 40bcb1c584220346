"""Instance offsets leased on one host, so that fleets started side by side never share a port.

A fleet launched with instance offset K takes PX4 SITL instances K..K+n-1's ports
(:func:`sitl.fleet.launcher.launch`). :func:`lease_instance_offset` holds one lock file per
instance (``aerial-skeleton-instance-<j>.lock`` in the temporary folder, ``flock``: released by
the kernel when the holder exits, even by SIGKILL) for the lowest K whose instances are all free
and whose ports :func:`~sitl.fleet.layout.check_instance_offset` accepts; a campaign's workers on
one host thus each fly on their own ports. Fleets started by hand do not take leases: give them
their own ``--instance-offset``.
"""

from __future__ import annotations

import fcntl
import tempfile
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Iterator

from .layout import check_instance_offset

__all__ = ["lease_instance_offset", "hold_instances", "MAX_INSTANCES"]

#: PX4 SITL's port layout has room for 40 instances (companion ports 14540-14579)
MAX_INSTANCES = 40


def _lock_path(folder: Path, instance: int) -> Path:
    return folder / f"aerial-skeleton-instance-{instance}.lock"


@contextmanager
def hold_instances(first: int, count: int, lock_dir: str | Path | None = None) -> Iterator[bool]:
    """Try to hold instances ``first`` .. ``first + count - 1`` (all or none, without waiting);
    yields whether it holds them, and lets go at the end of the block."""
    folder = Path(lock_dir or tempfile.gettempdir())
    with ExitStack() as stack:
        for j in range(first, first + count):
            f = stack.enter_context(open(_lock_path(folder, j), "w"))
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                stack.close()
                yield False
                return
        yield True


@contextmanager
def lease_instance_offset(scenario, gcs_port: int, *, timeout_s: float = 3600.0, poll_s: float = 0.5,
                          lock_dir: str | Path | None = None, clock=time.monotonic, sleep=time.sleep) -> Iterator[int]:
    """Hold the instances of the lowest free instance offset for ``scenario``'s fleet (with its
    ground-station traffic to ``gcs_port``) while the block runs; yields the offset. Waits for
    one (polling every ``poll_s``) up to ``timeout_s``, then ``TimeoutError``."""
    n = scenario.skeleton.n_links
    candidates = []
    for k in range(MAX_INSTANCES - n + 1):
        try:
            check_instance_offset(scenario, k, gcs_port)
        except ValueError:
            continue
        candidates.append(k)
    if not candidates:
        raise ValueError(f"no instance offset fits a fleet of {n} links")
    deadline = clock() + timeout_s
    while True:
        for k in candidates:
            with hold_instances(k, n, lock_dir) as held:
                if held:
                    yield k
                    return
        if clock() > deadline:
            raise TimeoutError(f"no free instance offset for {n} links within {timeout_s:g} s "
                               f"(lock files in {lock_dir or tempfile.gettempdir()})")
        sleep(poll_s)

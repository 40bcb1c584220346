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

__all__ = ["lease_instance_offset", "MAX_INSTANCES"]

#: PX4 SITL's port layout has room for 40 instances (companion ports 14540-14579)
MAX_INSTANCES = 40


def _try_lock(stack: ExitStack, path: Path) -> bool:
    f = stack.enter_context(open(path, "w"))
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


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
    folder = Path(lock_dir or tempfile.gettempdir())
    deadline = clock() + timeout_s
    while True:
        for k in candidates:
            stack = ExitStack()
            if all(_try_lock(stack, folder / f"aerial-skeleton-instance-{j}.lock") for j in range(k, k + n)):
                with stack:
                    yield k
                return
            stack.close()
        if clock() > deadline:
            raise TimeoutError(f"no free instance offset for {n} links within {timeout_s:g} s (lock files in {folder})")
        sleep(poll_s)

"""Waiting on real sockets and processes: a condition polled until a deadline, never a fixed nap."""

from __future__ import annotations

import time
from typing import Callable


def wait_for(cond: Callable[[], object], timeout_s: float, poll_s: float = 0.01) -> bool:
    """Poll ``cond`` until it is true or ``timeout_s`` of wall time have passed; returns whether it
    came true (evaluated once more at the deadline)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(poll_s)
    return bool(cond())

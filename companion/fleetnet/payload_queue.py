"""What a Zenoh subscriber delivers, queued on Zenoh's thread and taken in the caller's.

Zenoh calls a subscriber back on its own threads; :meth:`PayloadQueue.on_sample` only queues the
payload's bytes and its key, so the callback holds the GIL for microseconds, and
:meth:`PayloadQueue.take` hands them over in the thread that decodes and validates them. With a
``limit``, samples beyond that many waiting are dropped and counted (``overflow``).
"""

from __future__ import annotations

import queue
from collections.abc import Iterator

__all__ = ["PayloadQueue"]


class PayloadQueue:
    """``(payload, key)`` pairs between a Zenoh callback and their reader (module docstring)."""

    def __init__(self, limit: int = 0):
        self.limit = int(limit)
        self._queue: queue.SimpleQueue[tuple[bytes, str]] = queue.SimpleQueue()
        self.overflow = 0  # (the callback's thread is its only writer)

    def on_sample(self, sample) -> None:
        """A Zenoh subscriber's callback: queue only."""
        if self.limit and self._queue.qsize() >= self.limit:
            self.overflow += 1
            return
        self._queue.put((sample.payload.to_bytes(), str(sample.key_expr)))

    def take(self) -> Iterator[tuple[bytes, str]]:
        """Every pair queued so far, oldest first."""
        while True:
            try:
                yield self._queue.get_nowait()
            except queue.Empty:
                return

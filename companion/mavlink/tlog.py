"""The .tlog writer: the frames a port sends and accepts, each after its UNIX time.

Format (MAVProxy / MAVExplorer, readable by pymavlink): per message an 8-byte big-endian UNIX
time in microseconds, then the raw frame.

A daemon left running must not fill its disk: once the file reaches ``max_mb`` the writer
rotates it as logrotate does (``link1.tlog`` becomes ``link1.1.tlog``, the older ones move up to
``link1.<keep>.tlog``, the oldest beyond that is deleted) and starts a new ``link1.tlog``; a
frame never spans two files, so each opens in any pymavlink tool. At most ``(keep + 1) max_mb``
per link stay on disk (:data:`TLOG_MAX_MB`, :data:`TLOG_KEEP` by default; ``max_mb=None``: one
file that grows).
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["TlogWriter", "TLOG_MAX_MB", "TLOG_KEEP", "rotated_paths"]

#: a tlog is rotated when it reaches this size [MB] ...
TLOG_MAX_MB = 64.0
#: ... keeping this many older files
TLOG_KEEP = 3


def rotated_paths(path: str | Path, keep: int) -> list[Path]:
    """``path`` and its rotated files, newest first (``x.tlog``, ``x.1.tlog``, ... ``x.<keep>.tlog``)."""
    path = Path(path)
    return [path] + [path.with_name(f"{path.stem}.{k}{path.suffix}") for k in range(1, keep + 1)]


class TlogWriter:
    """Append MAVLink frames to a .tlog file; ``wall_clock`` gives the UNIX time [s] of each;
    rotated at ``max_mb`` keeping ``keep`` older files (module docstring)."""

    def __init__(self, path: str | Path, wall_clock: Callable[[], float] = time.time,
                 max_mb: float | None = TLOG_MAX_MB, keep: int = TLOG_KEEP):
        if max_mb is not None and not max_mb > 0.0:
            raise ValueError(f"max_mb must be positive (or None), got {max_mb}")
        if int(keep) != keep or keep < 0:
            raise ValueError(f"keep must be a non-negative integer, got {keep}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.wall_clock = wall_clock
        self.max_bytes = None if max_mb is None else int(max_mb * 1e6)
        self.keep = int(keep)
        self.rotations = 0
        self._fh = open(self.path, "ab", buffering=1 << 16)
        self._size = self._fh.tell()

    def write(self, frame: bytes) -> None:
        record = struct.pack(">Q", int(self.wall_clock() * 1e6)) + frame
        if self.max_bytes is not None and self._size > 0 and self._size + len(record) > self.max_bytes:
            self._rotate()
        self._fh.write(record)
        self._size += len(record)

    def _rotate(self) -> None:
        self._fh.close()
        paths = rotated_paths(self.path, self.keep)
        if self.keep == 0:
            self.path.unlink(missing_ok=True)
        else:
            paths[-1].unlink(missing_ok=True)
            for older, newer in zip(reversed(paths[1:]), reversed(paths[:-1])):
                if newer.exists():
                    newer.replace(older)
        self._fh = open(self.path, "ab", buffering=1 << 16)
        self._size = 0
        self.rotations += 1

    def close(self) -> None:
        self._fh.close()

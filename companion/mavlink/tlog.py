"""The .tlog writer: the frames a port sends and accepts, each after its UNIX time.

Format (MAVProxy / MAVExplorer, readable by pymavlink): per message an 8-byte big-endian UNIX
time in microseconds, then the raw frame.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["TlogWriter"]


class TlogWriter:
    """Append MAVLink frames to a .tlog file; ``wall_clock`` gives the UNIX time [s] of each."""

    def __init__(self, path: str | Path, wall_clock: Callable[[], float] = time.time):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.wall_clock = wall_clock
        self._fh = open(self.path, "ab", buffering=1 << 16)

    def write(self, frame: bytes) -> None:
        self._fh.write(struct.pack(">Q", int(self.wall_clock() * 1e6)) + frame)

    def close(self) -> None:
        self._fh.close()

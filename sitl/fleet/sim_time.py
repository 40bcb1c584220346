"""The lockstep's simulated time, shared with helper processes through a small memory-mapped file.

The fleet launcher writes the simulated time at every firmware tick (:class:`SimTimeWriter`); the
impaired wire (:mod:`.wire`) reads it (:class:`SimTimeClock`), so that its delays are simulated
milliseconds, as the vehicles and the companion measure time, whatever pace the fleet runs at (an
unpaced fleet at five times real time would otherwise turn a 10 ms delay into 50 simulated ms).

The file holds two little-endian 64-bit integers: a sequence number, odd while a write is under
way, and the time in microseconds. A reader retries until it sees the same even sequence number
before and after the time (a seqlock), so a torn write is never read.
"""

from __future__ import annotations

import mmap
import struct
import time
from pathlib import Path

__all__ = ["SIM_TIME_BYTES", "SimTimeClock", "SimTimeWriter"]

_LAYOUT = struct.Struct("<qq")
SIM_TIME_BYTES = _LAYOUT.size


class SimTimeWriter:
    """Creates (or truncates) ``path`` at simulated time 0 and publishes the time [s] given to
    :meth:`publish`."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "wb") as f:
            f.write(bytes(SIM_TIME_BYTES))
        self._file = open(self.path, "r+b")
        self._map = mmap.mmap(self._file.fileno(), SIM_TIME_BYTES)
        self._seq = 0

    def publish(self, t_s: float) -> None:
        self._seq += 1
        struct.pack_into("<q", self._map, 0, self._seq)  # odd: a write under way
        struct.pack_into("<q", self._map, 8, int(round(t_s * 1e6)))
        self._seq += 1
        struct.pack_into("<q", self._map, 0, self._seq)

    def close(self) -> None:
        if not self._map.closed:
            self._map.close()
            self._file.close()


class SimTimeClock:
    """A clock [s] that follows the simulated time in ``path`` while the lockstep advances it.

    While the simulated time stands still for more than ``stall_s`` of ``wall`` time (before the
    lockstep starts, after it ends, while it is held up), the clock runs on wall time from there, so
    that whoever waits on it (a datagram held for its delay) is never held for good; once the
    simulated time moves again the clock follows it, never stepping back. The clock is monotonic.
    A file that is missing or too short reads as a lockstep not yet started.
    """

    def __init__(self, path: Path, wall=time.monotonic, stall_s: float = 0.25):
        self.path = Path(path)
        self._wall = wall
        self.stall_s = stall_s
        self._file = None
        self._map = None
        self._sim_s = 0.0  # the newest simulated time read
        self._moved_wall_s = wall()  # when it last moved
        self._offset_s = 0.0  # wall time added during earlier stalls

    def _read(self) -> float | None:
        if self._map is None:
            try:
                self._file = open(self.path, "rb")
                self._map = mmap.mmap(self._file.fileno(), SIM_TIME_BYTES, access=mmap.ACCESS_READ)
            except (OSError, ValueError):
                if self._file is not None:
                    self._file.close()
                    self._file = None
                return None
        for _ in range(100):
            seq, t_us = _LAYOUT.unpack_from(self._map, 0)
            if seq % 2 == 0 and struct.unpack_from("<q", self._map, 0)[0] == seq:
                return t_us * 1e-6
        return None  # a writer that died mid-write: as if the time stood still

    def stalled_s(self, wall_s: float) -> float:
        """Wall time beyond ``stall_s`` since the simulated time last moved."""
        return max(0.0, wall_s - self._moved_wall_s - self.stall_s)

    def __call__(self) -> float:
        wall_s = self._wall()
        sim = self._read()
        if sim is not None and sim > self._sim_s:
            self._offset_s += self.stalled_s(wall_s)
            self._sim_s = sim
            self._moved_wall_s = wall_s
        # monotonic: while the simulated time stands still the stall grows with the wall clock, and
        # when it moves on the stall so far is kept in the offset
        return self._sim_s + self._offset_s + self.stalled_s(wall_s)

    def close(self) -> None:
        if self._map is not None:
            self._map.close()
            self._file.close()
            self._map = self._file = None

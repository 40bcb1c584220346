"""Append-only flight logs that survive a killed process.

A daemon's log (the companion's step log, a vehicle's flight log) grows by rows. Rewriting it
whole at every checkpoint costs more as the flight gets longer; a process that is killed (power
lost, SIGKILL) writes nothing at exit. :class:`LogStream` appends the rows logged since its last
flush as one chunk: a header (the keys) and one ``.npy`` record per key, written with
:func:`numpy.save` to one open file and flushed to the OS, so a killed process loses at most the
rows since its last flush. :func:`read_log_stream` concatenates the chunks per key and stops at
a truncated last chunk (the process died while writing it); :class:`LogStreamReader` reads the
chunks as they come. A long flight keeps its memory flat by flushing with ``keep``: the rows
written out leave the lists but for the newest ``keep``, and the whole log is read back from the
file at the end. No pickles: keys are a unicode array,
values numeric arrays, read with ``allow_pickle=False``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

__all__ = ["LogStream", "LogStreamReader", "read_log_stream"]

log = logging.getLogger(__name__)


class LogStream:
    """Chunks of rows appended to ``path`` (created, or truncated if it exists).

    ``flush(rows)`` takes the log as ``{key: list of rows}`` and writes the rows of every key
    that were not written yet; the lists are not modified unless ``keep`` is given."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "wb")
        self._written: dict[str, int] = {}
        self.chunks = 0

    def flush(self, rows: dict[str, list], keep: int | None = None) -> int:
        """Append the new rows as one chunk; returns the number of keys written (0: nothing new).
        ``keep``: then trim every list in place to its newest ``keep`` rows (0: empty), the rows
        dropped being in the file; the lists must keep growing only by appends."""
        if self._fh.closed:
            raise ValueError(f"{self.path}: log stream closed")
        if keep is not None and keep < 0:
            raise ValueError(f"keep must be >= 0, got {keep}")
        fresh = {}
        for key, values in rows.items():
            start = self._written.get(key, 0)
            if len(values) > start:
                fresh[key] = np.asarray(values[start:])
        if fresh:
            np.save(self._fh, np.array(list(fresh), dtype=np.str_), allow_pickle=False)
            for key, arr in fresh.items():
                np.save(self._fh, arr, allow_pickle=False)
                self._written[key] = self._written.get(key, 0) + len(arr)
            self._fh.flush()
            self.chunks += 1
        if keep is not None:
            for key, values in rows.items():
                excess = len(values) - keep
                if excess > 0:
                    del values[:excess]
                    self._written[key] = self._written.get(key, 0) - excess
        return len(fresh)

    @property
    def closed(self) -> bool:
        return self._fh.closed

    def read_back(self, rows: dict[str, list], keep: int | None = None) -> dict[str, np.ndarray]:
        """The whole log: ``rows`` not written yet flushed first (with ``keep``, while the stream is
        open), then every chunk read back from the file (:func:`read_log_stream`)."""
        if not self.closed:
            self.flush(rows, keep=keep)
        return read_log_stream(self.path)

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()


class LogStreamReader:
    """Reads a log stream as it grows: :meth:`read_new` returns the rows appended since its last
    call. A chunk still being written (or cut short) is read again at the next call."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.offset = 0

    def read_new(self, final: bool = False) -> dict[str, np.ndarray]:
        """The rows of every key in the whole chunks after the last read (none while the file does
        not exist); ``final``: a chunk that cannot be read is logged as left out."""
        parts: dict[str, list[np.ndarray]] = {}
        try:
            fh = open(self.path, "rb")
        except FileNotFoundError:
            return {}
        with fh:
            size = self.path.stat().st_size
            fh.seek(self.offset)
            while fh.tell() < size:
                start = fh.tell()
                try:
                    keys = np.load(fh, allow_pickle=False)
                    if keys.dtype.kind != "U" or keys.ndim != 1:
                        raise ValueError("chunk header is not a list of keys")
                    chunk = [(str(k), np.load(fh, allow_pickle=False)) for k in keys]
                except (ValueError, EOFError, OSError) as exc:
                    if final:
                        log.warning("%s: chunk at byte %d unreadable (%s): the %d byte(s) after it are left out",
                                    self.path, start, exc, size - start)
                    break
                self.offset = fh.tell()
                for key, arr in chunk:
                    parts.setdefault(key, []).append(arr)
        return {k: np.concatenate(v, axis=0) for k, v in parts.items()}


def read_log_stream(path: str | Path) -> dict[str, np.ndarray]:
    """The rows of every key, in the order written (a truncated last chunk is left out, logged)."""
    if not Path(path).exists():
        raise FileNotFoundError(path)
    return LogStreamReader(path).read_new(final=True)

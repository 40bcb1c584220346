"""The vehicle's flight log: on flight-controller time at the log rate, the EKF's estimate, the
control estimate (with the companion's correction), the active target, PSPM's reservoirs (NaN
while PSPM is off) and the correction latencies; streamed to ``link<i>_firmware.stream`` every
second (a killed vehicle keeps what it flew) and saved as ``link<i>_firmware.npz`` at the end.
Rows leave memory once they are in the stream (a long flight's memory stays flat); the whole
log is read back from it. Without an output folder nothing is recorded."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from companion.logstream import LogStream

from .streams.schedule import Stream

__all__ = ["FlightRecorder"]

_COLUMNS = ("t", "p_ekf", "q_ekf", "p_ctrl", "q_ctrl", "p_target", "q_target", "pspm", "flags")


class FlightRecorder:
    """The flight log of link ``system_id``'s firmware ``fw``, in ``out_dir`` (``None``: none)."""

    def __init__(self, fw, system_id: int, out_dir: Path | None, rate_hz: float):
        self.fw = fw
        self.out_dir = out_dir
        self.system_id = system_id
        self._grid = Stream.at_rate(rate_hz)
        #: the log's columns since the last flush; pspm: PSPM's reservoirs E_t, E_r [J] and the set
        #: position's lag [m]; flags: the state flags it reports (SKELETON_STATE_FLAGS)
        self.rows: dict[str, list] = {k: [] for k in _COLUMNS}
        #: the STATUSTEXTs the vehicle sent since the last flush: time [s], MAV_SEVERITY, text
        self.texts: dict[str, list] = {"statustext_t": [], "statustext_severity": [], "statustext_text": []}
        self._stream = LogStream(out_dir / f"link{system_id}_firmware.stream") if out_dir is not None else None

    @property
    def due_us(self) -> float:
        """When the next row is due [us of flight-controller time] (``inf`` without an output folder)."""
        return math.inf if self.out_dir is None else self._grid.next_us

    def after_tick(self, t_us: int, t_s: float) -> None:
        """A row when one is due at this tick."""
        if self.out_dir is not None and t_us >= self._grid.next_us:
            interval = self._grid.interval_us  # the next grid point (a vehicle started in flight skips ahead)
            self._grid.next_us = (t_us // interval + 1) * interval
            self._row(t_s)

    def _row(self, t_s: float) -> None:
        fw = self.fw
        estimate = fw.control_estimate(t_s)
        p, _, q = estimate
        target = fw.active_target(t_s, estimate)
        r = self.rows
        r["t"].append(t_s)
        r["p_ekf"].append(fw.ekf.p_w_m)
        r["q_ekf"].append(fw.ekf.q_wxyz)
        r["p_ctrl"].append(p)
        r["q_ctrl"].append(q)
        r["p_target"].append(target.p_w_m)
        r["q_target"].append(target.q_wxyz)
        r["pspm"].append(fw.pspm_report() or (math.nan,) * 3)
        r["flags"].append(fw.flags(t_s))  # the SKELETON_STATE_FLAGS it reports

    def statustext(self, t_s: float, severity: int, text: str) -> None:
        """A STATUSTEXT the vehicle sent at ``t_s``, for the log."""
        self.texts["statustext_t"].append(float(t_s))
        self.texts["statustext_severity"].append(int(severity))
        self.texts["statustext_text"].append(str(text))

    def _lists(self) -> dict[str, list]:
        return {**self.rows, **self.texts, "correction_latency": self.fw.latency_log}

    def flush(self) -> None:
        """The rows since the last flush to the stream file, and out of memory (every second)."""
        if self._stream is not None:
            self._stream.flush(self._lists(), keep=0)

    def arrays(self) -> dict[str, np.ndarray]:
        """The whole log so far (read back from the stream file; empty without an output folder)."""
        got: dict[str, np.ndarray] = {}
        if self._stream is not None:
            got = self._stream.read_back(self._lists(), keep=0)
        out = {k: got.get(k, np.zeros(0)) for k in _COLUMNS}
        out["correction_latency"] = np.asarray(got.get("correction_latency", np.zeros(0)), dtype=float).reshape(-1, 2)
        for key, dtype in (("statustext_t", float), ("statustext_severity", np.int64), ("statustext_text", np.str_)):
            out[key] = np.asarray(got.get(key, np.zeros(0, dtype)), dtype=dtype)
        return out

    def save(self) -> None:
        """The stream file's last rows, then the whole log as ``link<i>_firmware.npz``."""
        if self.out_dir is None:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.flush()
        self._stream.close()
        np.savez_compressed(self.out_dir / f"link{self.system_id}_firmware.npz", **self.arrays())

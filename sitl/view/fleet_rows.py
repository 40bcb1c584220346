"""A flying fleet's newest rows for the live view: the harness's truth (in this process) joined
with what the vehicles and companions write as they fly (their log streams, flushed once a
second: :mod:`companion.logstream`), the companions' home with them (the targets in the truth's
frame).

The estimates arrive up to a second after the truth, so the view shows the fleet at the newest
time every running vehicle has logged: truth, estimates and corrections of one instant, a second
or so behind the lockstep.
"""

from __future__ import annotations

import bisect
import time
from pathlib import Path

import numpy as np

from companion.logstream import LogStreamReader
from link_firmware_sim.vehicle.hil import SITL_GPS_EPOCH_US
from companion.linkstate import EXCLUDED
from companion.linkstate import word as state_word

from .live import chain_step_row

__all__ = ["FleetRows", "fleet_rows", "POLL_S", "KEEP_S"]

#: the log streams are read at most this often [wall s]
POLL_S = 0.25
#: rows kept per vehicle and companion [simulated s]
KEEP_S = 10.0
_VEHICLE_KEYS = ("p_ekf", "q_ekf", "p_target", "q_target", "flags")


class _Buffer:
    """The newest rows of one log stream by their time key ``stamp`` (``shift_s`` added)."""

    def __init__(self, path: Path, stamp: str, shift_s: float = 0.0):
        self.reader = LogStreamReader(path)
        self.stamp, self.shift_s = stamp, shift_s
        self.t = np.zeros(0)
        self.rows: dict[str, np.ndarray] = {}

    def poll(self) -> None:
        new = self.reader.read_new()
        if self.stamp not in new or not len(new[self.stamp]):
            return
        k = len(new[self.stamp])
        new = {key: a for key, a in new.items() if len(a) == k and (not self.rows or key in self.rows)}
        new[self.stamp] = np.asarray(new[self.stamp], dtype=float) + self.shift_s  # on the simulation's clock
        t = np.concatenate((self.t, new[self.stamp]))
        keep = t >= t[-1] - KEEP_S
        self.t = t[keep]
        self.rows = {key: (np.concatenate((self.rows[key], a)) if key in self.rows else a)[keep] for key, a in new.items()}

    @property
    def newest_s(self) -> float:
        return float(self.t[-1]) if self.t.size else -np.inf

    def at(self, t_s: float) -> dict | None:
        """The newest row at or before ``t_s`` (``None``: none)."""
        k = int(np.searchsorted(self.t, t_s + 1e-9, side="right")) - 1
        return {key: a[k] for key, a in self.rows.items()} if k >= 0 else None


class FleetRows:
    """``newest()``: ``(t, log row, step row)`` of the fleet behind ``harness`` whose processes log
    into ``out_dir`` (``clock``: wall seconds, for the polling period)."""

    def __init__(self, harness, out_dir: Path, clock=time.monotonic):
        sc = harness.scenario
        self.harness, self.n, self.clock = harness, harness.n, clock
        self.d = np.asarray(sc.skeleton.d_b_m, dtype=float)
        self.vehicles = [[_Buffer(out_dir / folder / f"link{i + 1}_firmware.stream", "t")
                          for folder in (f"link{i + 1}", f"link{i + 1}-restart")] for i in range(self.n)]
        shift = -SITL_GPS_EPOCH_US * 1e-6 if sc.companion.time_base == "gps" else 0.0
        if not sc.companion.enabled:
            self.companions = []
        elif sc.companion.distributed:
            self.companions = [(list(g), [_Buffer(out_dir / folder / "companion_log.stream", "t_sckf", shift)
                                          for folder in (f"companion-g{j + 1}", f"companion-g{j + 1}-restart")])
                               for j, g in enumerate(sc.companion.group_layout(self.n))]
        else:
            self.companions = [(list(range(self.n)), [_Buffer(out_dir / "companion" / "companion_log.stream",
                                                              "t_sckf", shift)])]
        self._polled = -np.inf

    def _poll(self) -> None:
        now = self.clock()
        if now - self._polled < POLL_S:
            return
        self._polled = now
        for buffers in self.vehicles:
            for b in buffers:
                b.poll()
        for _, buffers in self.companions:
            for b in buffers:
                b.poll()

    def newest(self):
        self._poll()
        rows = self.harness.rows
        t_truth = rows["t"]
        if not t_truth:
            return None
        running = [i for i in range(self.n) if i not in self.harness.down]
        logged = [max(b.newest_s for b in self.vehicles[i]) for i in running]
        t_show = min([t_truth[-1], *logged]) if logged else t_truth[-1]
        k = bisect.bisect_right(t_truth, t_show + 1e-9) - 1
        if k < 0:
            k = 0
        t = t_truth[k]
        row = {"t": t, "p_true": rows["p_true"][k], "q_true": rows["q_true"][k]}
        est = {key: np.full((self.n, 4 if key.startswith("q") else 3), np.nan) for key in _VEHICLE_KEYS[:-1]}
        words = np.zeros(self.n, dtype=np.uint8)
        for i, buffers in enumerate(self.vehicles):
            found = max((r for r in (b.at(t) for b in buffers) if r is not None), key=lambda r: float(r["t"]),
                        default=None)
            down = i in self.harness.down
            if found is not None and not down:
                for key in est:
                    est[key][i] = found[key]
            words[i] = state_word(int(found.get("flags", 0)) if found is not None and not down else 0,
                                  down=down or found is None)
        groups = []
        for indices, buffers in self.companions:
            steps = [r for r in (b.at(t) for b in buffers) if r is not None]
            step = max(steps, key=lambda r: float(r["t_sckf"]), default=None)
            if step is not None:
                groups.append((indices, step))
                if "home_offset_sckf" in step and "home_offset_w_m" not in row:
                    # where the companions fly the targets from (the groups share one home): the
                    # targets back in the truth's frame
                    row["home_offset_w_m"] = np.asarray(step["home_offset_sckf"], dtype=float)
                if "corrected_sckf" in step:  # left out of its companion's newest step
                    out = np.asarray(indices)[~np.asarray(step["corrected_sckf"], dtype=bool)]
                    words[out] |= EXCLUDED
        row.update(est, link_state=words)
        return t, row, chain_step_row(groups, self.n, self.d)


def fleet_rows(harness, out_dir: Path):
    """:meth:`FleetRows.newest` of ``harness`` and ``out_dir``."""
    return FleetRows(harness, Path(out_dir)).newest

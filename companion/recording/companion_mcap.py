"""The companion daemon's own MCAP (``companion.mcap`` in its run folder): a real flight as the
companion saw it, for Foxglove and Lichtblick.

Every message is stamped on the companion's time base (the links' flight-controller clock, or GPS
time with ``time_base = "gps"``). The channels, links numbered by their place in the chain:

- from the step log (:func:`companion.recording.mcap_log.channels`): ``/link{i}/state_in`` (the
  state each step took in), ``/link{i}/corrected`` (what it sent back as the corrected pose),
  ``/link{i}/correction`` (the move), and ``/companion/step`` (the eq. 3 joint errors before and
  after, iterations, global step, NIS, cycle time);
- ``/link{i}/health`` (``skeleton.Series``): the health table's figures at each report: state rate
  [Hz], age of the newest state [ms], states rejected, reboots, steps left out in the period,
  ``left_out`` (1 while it is out of the step), correction latency p50 / p99 [ms];
- ``/statustext`` (``foxglove.Log``): every STATUSTEXT a link sent, named ``link <i>``.
"""

from __future__ import annotations

import numpy as np

from ..estimation.constraints import joint_error_norms
from .foxglove import SERIES, stamp
from .mcap_log import _json, _nanoseconds, export_log, statustext_channel

__all__ = ["COMPANION_MCAP", "HEALTH_FIELDS", "health_channels", "write_companion_mcap"]

COMPANION_MCAP = "companion.mcap"
#: ``/link{i}/health`` fields: the health row's numbers (:meth:`~companion.engine.CompanionEngine.health_rows`)
HEALTH_FIELDS = ("state_hz", "age_ms", "rejected", "replayed", "future", "reboots", "excluded", "latency_p50_ms",
                 "latency_p99_ms")


def _number(x):
    return None if x is None or not np.isfinite(x) else float(x)


def health_channels(health: list[tuple[float, list[dict]]]) -> list:
    """``/link{i}/health`` of the health reports ``(time base [s], rows)``, a channel per link."""
    per_link: dict[int, list[tuple[int, bytes]]] = {}
    for t_s, rows in health:
        ns = int(_nanoseconds(np.array([t_s]))[0])
        for row in rows:
            message = {"timestamp": stamp(ns), **{k: _number(row.get(k)) for k in HEALTH_FIELDS},
                       "left_out": 0.0 if not row.get("status") else 1.0}
            per_link.setdefault(int(row["link"]), []).append((ns, _json(message)))
    return [(f"/link{link}/health", SERIES, np.array([ns for ns, _ in rows], dtype=np.int64), iter([m for _, m in rows]))
            for link, rows in sorted(per_link.items())]


def write_companion_mcap(path, step_log: dict[str, np.ndarray], d_b_m: np.ndarray, first_link: int = 1,
                         health=(), statustext=()) -> dict[str, int]:
    """Write the companion's MCAP to ``path`` from its step log (the engine's ``log_arrays()``),
    its links' tip vectors ``d_b_m`` (n, 3), its health reports and STATUSTEXTs; ``first_link``:
    the chain number of its first link (a group's companion). Returns the message count per topic."""
    log = dict(step_log)
    if "p_ekf_sckf" in log and len(log["p_ekf_sckf"]):
        for when, suffix in (("before", "ekf"), ("after", "corr")):
            pos, vel = joint_error_norms(log[f"p_{suffix}_sckf"], log[f"v_{suffix}_sckf"], log[f"q_{suffix}_sckf"],
                                         log["w_sckf"], np.asarray(d_b_m, dtype=float))
            log[f"con_pos_{when}"], log[f"con_vel_{when}"] = pos, vel
    extra = health_channels(list(health)) + statustext_channel(list(statustext))
    return export_log(log, path, extra=extra, first_link=first_link)

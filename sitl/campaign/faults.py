"""Random fault schedules for a campaign, and what each kind of fault did (pure).

:func:`draw_schedule` draws one flight's faults from a NumPy generator: each kind below is in
the flight with probability :data:`P_KIND` (at least one is), on a random link (or group), at a
random time after the take-off and with a random length, so faults overlap as they happen to
(a GPS glitch while a neighbour reboots over a lossy wire, a companion killed while another
link is down). A flight has at most one GPS glitch and one injected failure (the scenario scripts
one of each). A schedule is a set of scenario settings (``faults.*`` keys of
:class:`sitl.scenario.FaultConfig`), so each flight's ``scenario.toml`` replays it.

=================  =====================================================================
kind               what
=================  =====================================================================
``link_reboot``    a link's Pixhawk loses power and comes back 1-6 s later
``gps_step``       a link's GPS position jumps 2-10 m for 1-5 s (multipath)
``gps_ramp``       it drifts to 2-10 m over 2-8 s, holds 0-4 s, then snaps back (spoofing)
``gps_outage``     it has no fix for 2-15 s
``gps_failure``    its GPS receiver fails for 2-10 s: stuck on its last fix, or 50 m off
                   (MAV_CMD_INJECT_FAILURE, ``[faults.inject]``)
``imu_failure``    its gyro or accelerometer is stuck or outputs garbage for 1-5 s (injected)
``motor_off``      one of its eight rotors stops for 1-5 s (injected)
``mavlink_off``    its MAVLink link to the companion is lost both ways for 1-5 s (injected,
                   PX4's MAVLink signal failure)
``mavlink_loss``   the wires of 1..n links lose 2-15 % of their datagrams, with 0-20 ms of
                   delay and 0-10 ms of jitter, all flight long (fleet mode)
``companion_kill`` a group's companion is killed and restarted 1-5 s later (fleet mode,
                   distributed scenarios)
=================  =====================================================================

:func:`event_figures` measures each fault in its flight's log: the worst link's true tracking
RMS and the constraint p95 after the SCKF during the fault and in the :data:`AFTER_S` after it,
the largest fraction of steps a link it did not hit went uncorrected during it, and the time to
recover (:func:`recovery_s`: from the fault's end until every link tracks within
:data:`RECOVERED_M` of its target again). :func:`fault_table` reduces the flights to one row per
kind: the flights that had it, their crashes, the crashes *near* a fault of that kind (from its
start to :data:`AFTER_S` after its end: the crashes it may have caused), the lowest altitude, and
the worst of each figure over the flights that did not crash (a crashed flight's figures measure
the wreck).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.trajectory import planned_positions

from ..metrics import p95, rms

__all__ = ["KINDS", "INJECTED", "FLEET_ONLY", "P_KIND", "RECOVERED_M", "AFTER_S", "FaultEvent", "draw_schedule",
           "power_loss_near", "recovery_s",
           "event_figures", "flight_row", "fault_table", "markdown_fault_table"]

KINDS = ("link_reboot", "gps_step", "gps_ramp", "gps_outage", "gps_failure", "imu_failure", "motor_off",
         "mavlink_off", "mavlink_loss", "companion_kill")
#: the kinds scripted by ``[faults.inject]`` (one per flight)
INJECTED = ("gps_failure", "imu_failure", "motor_off", "mavlink_off")
#: the kinds only a fleet can play (processes, wires)
FLEET_ONLY = ("mavlink_loss", "companion_kill")
#: the probability that a flight has a given kind (of those its mode and scenario allow)
P_KIND = 0.5
#: a link has recovered when its true tracking error is back under this [m]
RECOVERED_M = 0.25
#: the window after a fault its figures "after" are taken in [s]
AFTER_S = 10.0
#: faults start this long after the take-off ends and this long before the flight does [s] ...
_MARGIN_AFTER_TAKEOFF_S = 1.0
_MARGIN_AT_END_S = 8.0
#: ... and end at least this long before it (their lengths are cut to fit) [s]
_RECOVERY_ROOM_S = 3.0


@dataclass(frozen=True)
class FaultEvent:
    """One drawn fault: its kind, the link or group it hits (1-based; 0: every link; a lossy wire
    on some links names the first), its window on simulated time (``end_s`` the end of the flight
    for a fault that lasts: it has no recovery)."""

    kind: str
    target: int
    start_s: float
    end_s: float

    def as_dict(self) -> dict:
        return {"kind": self.kind, "target": self.target, "start_s": round(self.start_s, 3),
                "end_s": round(self.end_s, 3)}


def _unit(rng: np.random.Generator) -> list[float]:
    v = rng.normal(size=3)
    v[2] *= 0.3  # mostly horizontal, as GNSS glitches are
    return (v / np.linalg.norm(v)).tolist()


def _r(x: float) -> float:
    return round(float(x), 3)


def draw_schedule(rng: np.random.Generator, n_links: int, flight_start_s: float, duration_s: float,
                  fleet: bool, n_groups: int = 0) -> tuple[list[FaultEvent], tuple[tuple[str, Any], ...]]:
    """One flight's faults: the events and the scenario settings that script them (each fault
    starts after the take-off and at least 8 s before the end, and ends at least 3 s before it:
    its length is cut to fit). ``fleet``:
    the fleet-only kinds may be drawn; ``n_groups``: the companion groups of a distributed
    scenario (0: not distributed, no companion kill). ``ValueError`` when the flight leaves no
    room for a fault after the take-off."""
    t0, t1 = flight_start_s + _MARGIN_AFTER_TAKEOFF_S, duration_s - _MARGIN_AT_END_S
    if not t1 > t0:
        raise ValueError(f"no room for faults: the take-off ends at {flight_start_s:g} s and the flight at "
                         f"{duration_s:g} s (faults need {_MARGIN_AFTER_TAKEOFF_S + _MARGIN_AT_END_S:g} s more)")
    allowed = [k for k in KINDS if (fleet or k not in FLEET_ONLY) and (k != "companion_kill" or n_groups > 1)]
    gps_kinds = [k for k in allowed if k.startswith("gps_") and k not in INJECTED]
    chosen = [k for k in allowed if rng.random() < P_KIND]
    for family in (gps_kinds, INJECTED):  # one GPS glitch and one injected failure per flight
        drawn = [k for k in chosen if k in family]
        if len(drawn) > 1:
            keep = drawn[int(rng.integers(len(drawn)))]
            chosen = [k for k in chosen if k not in family or k == keep]
    if not chosen:
        chosen = [allowed[int(rng.integers(len(allowed)))]]
    events: list[FaultEvent] = []
    settings: list[tuple[str, Any]] = []
    for kind in chosen:
        start = float(rng.uniform(t0, t1))
        room = duration_s - _RECOVERY_ROOM_S - start  # at least _MARGIN_AT_END_S - _RECOVERY_ROOM_S
        if kind == "link_reboot":
            link, length = int(rng.integers(1, n_links + 1)), min(float(rng.uniform(1.0, 6.0)), room)
            settings += [("faults.link.kill", link), ("faults.link.kill_at_s", _r(start)),
                         ("faults.link.restart_after_s", _r(length))]
            events.append(FaultEvent(kind, link, start, start + length))
        elif kind in gps_kinds:
            link = int(rng.integers(1, n_links + 1))
            settings.append(("faults.gps.link", link))
            size = float(rng.uniform(2.0, 10.0))
            if kind == "gps_step":
                length = min(float(rng.uniform(1.0, 5.0)), room)
                settings += [("faults.gps.step_m", [_r(size * c) for c in _unit(rng)]),
                             ("faults.gps.step_at_s", _r(start)), ("faults.gps.step_duration_s", _r(length))]
            elif kind == "gps_ramp":
                ramp = min(float(rng.uniform(2.0, 8.0)), room)
                hold = min(float(rng.uniform(0.0, 4.0)), room - ramp)
                length = ramp + hold
                settings += [("faults.gps.ramp_m", [_r(size * c) for c in _unit(rng)]),
                             ("faults.gps.ramp_at_s", _r(start)), ("faults.gps.ramp_duration_s", _r(ramp)),
                             ("faults.gps.ramp_hold_s", _r(hold))]
            else:
                length = min(float(rng.uniform(2.0, 15.0)), room)
                settings += [("faults.gps.outage_at_s", _r(start)), ("faults.gps.outage_s", _r(length))]
            events.append(FaultEvent(kind, link, start, start + length))
        elif kind in INJECTED:
            link = int(rng.integers(1, n_links + 1))
            if kind == "gps_failure":
                unit, ftype, instance, length = "gps", ("stuck", "wrong")[int(rng.integers(2))], 0, rng.uniform(2, 10)
            elif kind == "imu_failure":
                unit, ftype, instance = ("gyro", "accel")[int(rng.integers(2))], ("stuck", "garbage")[int(rng.integers(2))], 0
                length = rng.uniform(1.0, 5.0)
            elif kind == "motor_off":
                unit, ftype, instance, length = "motor", "off", int(rng.integers(1, 9)), rng.uniform(1.0, 5.0)
            else:
                unit, ftype, instance, length = "mavlink_signal", "off", 0, rng.uniform(1.0, 5.0)
            length = min(float(length), room)
            settings += [("faults.inject.link", link), ("faults.inject.unit", unit), ("faults.inject.type", ftype),
                         ("faults.inject.instance", instance), ("faults.inject.at_s", _r(start)),
                         ("faults.inject.duration_s", _r(length))]
            events.append(FaultEvent(kind, link, start, start + length))
        elif kind == "mavlink_loss":
            count = int(rng.integers(1, n_links + 1))
            links = sorted(int(i) + 1 for i in rng.choice(n_links, size=count, replace=False))
            settings += [("faults.mavlink.loss", _r(rng.uniform(0.02, 0.15))),
                         ("faults.mavlink.delay_ms", _r(rng.uniform(0.0, 20.0))),
                         ("faults.mavlink.jitter_ms", _r(rng.uniform(0.0, 10.0))),
                         ("faults.mavlink.links", links)]
            events.append(FaultEvent(kind, 0 if count == n_links else links[0], flight_start_s, duration_s))
        else:  # companion_kill
            group, length = int(rng.integers(1, n_groups + 1)), min(float(rng.uniform(1.0, 5.0)), room)
            settings += [("faults.kill_companion_group", group), ("faults.kill_at_s", _r(start)),
                         ("faults.restart_after_s", _r(length))]
            events.append(FaultEvent(kind, group, start, start + length))
    return events, tuple(settings)


def power_loss_near(row: dict) -> dict | None:
    """A crashed flight's (:func:`flight_row`) power loss, a ``link_reboot`` whose window (from its
    start to :data:`AFTER_S` after its end) holds the crash, else ``None``: the crashes to read
    against what the rotors can carry (the campaign report's carry table)."""
    t = row.get("crash_time_s")
    if not row.get("crashed") or t is None:
        return None
    for e in row["events"]:
        if e["kind"] == "link_reboot" and e["start_s"] <= t <= e["end_s"] + AFTER_S:
            return e
    return None


def recovery_s(t: np.ndarray, err_m: np.ndarray, end_s: float, threshold_m: float = RECOVERED_M) -> float | None:
    """Seconds from ``end_s`` until every link's true tracking error (``err_m`` (k, n) at times
    ``t``) is under ``threshold_m`` and stays there to the end of the log; 0 if it never left,
    ``None`` if it never came back (or the log ends before ``end_s``)."""
    t = np.asarray(t, dtype=float)
    bad = ~(np.nan_to_num(np.asarray(err_m, dtype=float), nan=np.inf) < threshold_m).all(axis=1)
    after = t >= end_s
    if not np.any(after):
        return None
    idx = np.flatnonzero(after & bad)
    if idx.size == 0:
        return 0.0
    last = idx[-1]
    if last + 1 >= t.size:
        return None
    return max(float(t[last + 1]) - end_s, 0.0)


def _max(values: Iterable) -> float | None:
    a = np.asarray([v for v in values if v is not None], dtype=float).ravel()
    a = a[np.isfinite(a)]
    return float(a.max()) if a.size else None


def _worst_rms(err: np.ndarray) -> float | None:
    """The largest per-link RMS of ``err`` (k, n) over its finite samples (``None``: none)."""
    return _max(rms(err)) if err.size else None


def event_figures(event: FaultEvent, log: dict, kind_links: Sequence[int] = ()) -> dict:
    """One fault's figures in its flight's ``log`` (``log.npz``: ``t``, ``p_target``, ``p_true``,
    ``home_offset_w_m``, and the step log's ``t_sckf``, ``con_pos_after``, ``corrected_sckf`` when it has them):
    ``track_during_m`` / ``track_after_m`` (the worst link's true tracking RMS during the fault and
    in the :data:`AFTER_S` after it), ``constraint_during_m`` / ``constraint_after_m`` (constraint
    p95 after the SCKF), ``uncorrected_max`` (the largest fraction of steps during it that a link
    not in ``kind_links``, 1-based, went uncorrected) and ``recovery_s`` (:func:`recovery_s`; left
    out for a fault lasting to the end of the log)."""
    t = np.asarray(log["t"], dtype=float)
    err = np.linalg.norm(planned_positions(log) - np.asarray(log["p_true"]), axis=-1)
    during = (t >= event.start_s) & (t <= event.end_s)
    after = (t > event.end_s) & (t <= event.end_s + AFTER_S)
    out: dict[str, Any] = {"track_during_m": _worst_rms(err[during]), "track_after_m": _worst_rms(err[after])}
    if t.size and event.end_s < t[-1]:  # (a fault lasting to the end has no recovery)
        out["recovery_s"] = recovery_s(t, err, event.end_s)
    if "t_sckf" in log and "con_pos_after" in log:
        ts = np.asarray(log["t_sckf"], dtype=float)
        sd, sa = (ts >= event.start_s) & (ts <= event.end_s), (ts > event.end_s) & (ts <= event.end_s + AFTER_S)
        out["constraint_during_m"] = p95(np.asarray(log["con_pos_after"])[sd])
        out["constraint_after_m"] = p95(np.asarray(log["con_pos_after"])[sa])
        if "corrected_sckf" in log and np.any(sd):
            corrected = np.asarray(log["corrected_sckf"], dtype=bool)[sd]
            live = [i for i in range(corrected.shape[1]) if i + 1 not in set(kind_links)]
            out["uncorrected_max"] = float((1.0 - corrected[:, live].mean(axis=0)).max()) if live else None
    return out


def _hit_links(event: FaultEvent, n_links: int, groups: Sequence[Sequence[int]] = ()) -> list[int]:
    """The links (1-based) a fault takes out by itself: the rebooted link, the link whose MAVLink
    link is lost, a killed companion's group; none for the others (a glitching GPS or a lossy wire
    leaves the link in the chain)."""
    if event.kind in ("link_reboot", "mavlink_off"):
        return [event.target]
    if event.kind == "companion_kill" and groups:
        return [i + 1 for i in groups[event.target - 1]]
    return []


def flight_row(events: Sequence[FaultEvent], metrics: dict | None, log: dict | None, status: str,
               groups: Sequence[Sequence[int]] = ()) -> dict:
    """One flight of a fault campaign: its events (each with its :func:`event_figures` when the
    flight has a log), whether it ran, took off and crashed, and its lowest altitude. ``groups``:
    the companion groups (0-based links), for the links a killed companion takes out."""
    row: dict[str, Any] = {"events": [e.as_dict() for e in events], "status": status}
    if metrics is None:
        return row
    row.update(took_off=bool(metrics.get("took_off", True)), crashed=bool(metrics.get("crashed")),
               crash_reason=metrics.get("crash_reason") or "", crash_time_s=metrics.get("crash_time_s"),
               min_altitude_m=metrics.get("min_altitude_m"))
    if log is not None and {"t", "p_target", "p_true"} <= set(log) and len(log["t"]):
        n = np.asarray(log["p_true"]).shape[1]
        for e, entry in zip(events, row["events"]):
            entry.update(event_figures(e, log, _hit_links(e, n, groups)))
    return row


_FIGURES = ("track_during_m", "track_after_m", "constraint_during_m", "constraint_after_m", "uncorrected_max")


def fault_table(rows: Sequence[dict]) -> dict[str, dict]:
    """Per kind, over the flights that had it: ``flights``, ``failed`` (runs that did not finish),
    ``crashes``, ``crashes_near`` (a crash from a fault's start to :data:`AFTER_S` after its end),
    ``min_altitude_m`` (lowest), and over the flights that did not crash the worst of each of
    :func:`event_figures`' figures, ``recovery_s_max`` (the slowest recovery) and
    ``not_recovered`` (faults after which the chain never tracked again)."""
    table: dict[str, dict] = {}
    for kind in KINDS:
        mine = [(r, [e for e in r["events"] if e["kind"] == kind]) for r in rows]
        mine = [(r, evs) for r, evs in mine if evs]
        if not mine:
            continue
        done = [(r, evs) for r, evs in mine if "crashed" in r]
        evs = [e for r, es in done if not r["crashed"] for e in es]
        lows = [r["min_altitude_m"] for r, _ in done if r.get("min_altitude_m") is not None]
        rec = [e["recovery_s"] for e in evs if "recovery_s" in e]
        near = sum(1 for r, es in done if r["crashed"] and r.get("crash_time_s") is not None
                   and any(e["start_s"] <= r["crash_time_s"] <= e["end_s"] + AFTER_S for e in es))
        table[kind] = {
            "flights": len(mine), "failed": len(mine) - len(done),
            "crashes": sum(1 for r, _ in done if r["crashed"]), "crashes_near": near,
            "min_altitude_m": min(lows) if lows else None,
            **{key: _max(e.get(key) for e in evs) for key in _FIGURES},
            "recovery_s_max": _max(rec), "not_recovered": sum(1 for x in rec if x is None),
        }
    return table


def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def markdown_fault_table(table: dict[str, dict]) -> str:
    """:func:`fault_table` as a Markdown table (the figures from ``track during`` on: the flights
    that did not crash)."""
    head = ("| kind | flights | failed | crashes | crashes near | lowest m | track during m | track after m "
            "| constraint during m | constraint after m | uncorrected max | recovery max s | not recovered |")
    lines = [head, "| :--- " + "| ---: " * 12 + "|"]
    for kind, r in table.items():
        lines.append(f"| {kind} | {r['flights']} | {r['failed']} | {r['crashes']} | {r['crashes_near']} | "
                     f"{_fmt(r['min_altitude_m'], 2)} | "
                     f"{_fmt(r['track_during_m'])} | {_fmt(r['track_after_m'])} | {_fmt(r['constraint_during_m'])} | "
                     f"{_fmt(r['constraint_after_m'])} | {_fmt(r['uncorrected_max'])} | {_fmt(r['recovery_s_max'], 2)} | "
                     f"{r['not_recovered']} |")
    return "\n".join(lines) + "\n"

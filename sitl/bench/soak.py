"""A long unpaced fleet flight watched for growth: ``python -m sitl.bench soak``.

One fleet (``python -m sitl launch --speed 0 --no-plots``) flies as a child process; every
``sample_s`` wall seconds the bench reads from ``/proc`` (:mod:`.procfs`), for the launcher (the
harness) and each of its fleet children by role (vehicle i, companion, wire), the current RSS
(``VmRSS``, not the high-water mark) and the number of open file descriptors, and the run
folder's size on disk. Each sample gets its simulated time from the launcher's progress bar
(``n/total sim s`` on its stderr, counted from the lockstep's start), or, where that is missing,
from the fraction of the wall time between the harness's ``lockstep started`` / ``lockstep
ended`` lines.

Per process and for the run folder the figures are taken after a warm-up (the first 60 simulated
seconds or 10 % of the flight, whichever is less): the mean in the first and in the last 10 % of
the rest, the growth between them in %, and the slope of a straight-line fit over the whole rest
per simulated hour. The vehicles' correction latencies (each correction's ``[t, latency s]`` in
their flight logs) give p50 / p99 in the first and last ten minutes (10 % of the span for a
flight shorter than 30 minutes after the warm-up).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ..fleet.layout import LOCKSTEP_ENDED, LOCKSTEP_STARTED
from .procfs import command, descendants, disk_usage, memory, role

__all__ = ["resolve_config", "run_soak", "sim_times", "analyse", "window_mean", "growth_per_hour", "windows",
           "latency_windows", "process_keys", "format_soak", "markdown_soak"]

WARM_UP_S = 60.0
EDGE_FRACTION = 0.1
LATENCY_WINDOW_S = 600.0
_PROGRESS = re.compile(rb"(\d+(?:\.\d+)?)/(\d+(?:\.\d+)?) sim s")
_FROM_T = re.compile(rb"from t = (-?\d+(?:\.\d+)?) s")
_AT_T = re.compile(rb"at t = (-?\d+(?:\.\d+)?) s")


def resolve_config(config: str) -> Path:
    """A scenario file: ``config`` itself if it is a file, else the scenario of that name."""
    from .speed import scenario_file

    path = Path(config)
    return path if path.is_file() else scenario_file(config)


# -- the pure parts --------------------------------------------------------------------------------
def process_keys(pid_roles: dict[int, str | None], harness_pid: int) -> dict[int, str]:
    """Each watched process's key, in the order first seen: ``harness`` for the launcher, else its
    role (:func:`.procfs.role`); a role seen again (a restarted vehicle, a second wire) gets ``#2``,
    ``#3``, ... Processes without a fleet role are left out."""
    keys: dict[int, str] = {}
    for pid, r in pid_roles.items():
        r = "harness" if pid == harness_pid else r
        if r is None:
            continue
        key, k = r, 1
        while key in keys.values():
            k += 1
            key = f"{r} #{k}"
        keys[pid] = key
    return keys


def sim_times(wall: np.ndarray, progress: np.ndarray, marks: dict) -> tuple[np.ndarray, str]:
    """Each sample's simulated time: its progress reading (NaN before any) where the launcher printed
    one, else the fraction of wall time between the lockstep marks (``marks``: ``start_wall``,
    ``end_wall``, ``start_t``, ``end_t``). Returns the times and which source they came from."""
    wall = np.asarray(wall, dtype=float)
    progress = np.asarray(progress, dtype=float)
    if np.isfinite(progress).any():
        return progress, "progress"
    w0, w1 = marks.get("start_wall"), marks.get("end_wall")
    t0, t1 = marks.get("start_t"), marks.get("end_t")
    if None in (w0, w1, t0, t1) or w1 <= w0:
        return np.full(wall.shape, np.nan), "none"
    t = t0 + (wall - w0) / (w1 - w0) * (t1 - t0)
    return np.where((wall >= w0) & (wall <= w1), t, np.nan), "lockstep markers"


def windows(t_end: float, t_start: float = 0.0) -> dict[str, tuple[float, float]]:
    """The warm-up's end and the first / last 10 % of the flight after it."""
    warm = min(WARM_UP_S, EDGE_FRACTION * (t_end - t_start))
    w0 = t_start + warm
    edge = EDGE_FRACTION * (t_end - w0)
    return {"fit": (w0, t_end), "first": (w0, w0 + edge), "last": (t_end - edge, t_end)}


def latency_windows(t_end: float, t_start: float = 0.0) -> dict[str, tuple[float, float]]:
    """The latency's first / last ten minutes after the warm-up (10 % of the span below 30 min)."""
    w0 = windows(t_end, t_start)["fit"][0]
    span = t_end - w0
    edge = LATENCY_WINDOW_S if span >= 3 * LATENCY_WINDOW_S else EDGE_FRACTION * span
    return {"first": (w0, w0 + edge), "last": (t_end - edge, t_end)}


def window_mean(t: np.ndarray, y: np.ndarray, lo: float, hi: float) -> float | None:
    """The mean of ``y`` over the samples with ``lo <= t <= hi`` (finite ones); with none in the
    window, the finite sample nearest its middle; ``None`` without any."""
    t, y = np.asarray(t, dtype=float), np.asarray(y, dtype=float)
    ok = np.isfinite(t) & np.isfinite(y)
    inside = ok & (t >= lo) & (t <= hi)
    if inside.any():
        return float(y[inside].mean())
    if not ok.any():
        return None
    k = np.flatnonzero(ok)[np.argmin(np.abs(t[ok] - 0.5 * (lo + hi)))]
    return float(y[k])


def growth_per_hour(t: np.ndarray, y: np.ndarray, lo: float = -np.inf, hi: float = np.inf) -> float | None:
    """The slope of a least-squares line through the finite samples with ``lo <= t <= hi``, per
    3600 units of ``t`` (simulated seconds); ``None`` with fewer than two distinct times."""
    t, y = np.asarray(t, dtype=float), np.asarray(y, dtype=float)
    ok = np.isfinite(t) & np.isfinite(y) & (t >= lo) & (t <= hi)
    if np.unique(t[ok]).size < 2:
        return None
    return round(float(np.polyfit(t[ok], y[ok], 1)[0] * 3600.0), 6) + 0.0  # (no -0.0 for a flat series)


def _series_stats(t, y, win, unit: str) -> dict:
    first = window_mean(t, y, *win["first"])
    last = window_mean(t, y, *win["last"])
    pct = None if first in (None, 0.0) or last is None else 100.0 * (last - first) / first
    return {f"{unit}_first": first, f"{unit}_last": last, "growth_pct": pct,
            f"{unit}_per_sim_h": growth_per_hour(t, y, *win["fit"])}


def analyse(t: np.ndarray, rss_mb: dict[str, np.ndarray], fds: dict[str, np.ndarray], disk_mb: np.ndarray,
            t_end: float, t_start: float = 0.0) -> dict:
    """The soak's figures from sampled series on simulated times ``t`` (NaN: outside the lockstep,
    a process not alive): per process RSS and fds, the run folder's size (:func:`windows`)."""
    win = windows(t_end, t_start)
    procs = {}
    for key in rss_mb:
        r = _series_stats(t, rss_mb[key], win, "rss_mb")
        f = _series_stats(t, fds[key], win, "fds")
        procs[key] = {**r, "fds_first": f["fds_first"], "fds_last": f["fds_last"], "fds_per_sim_h": f["fds_per_sim_h"],
                      "samples": int(np.sum(np.isfinite(t) & np.isfinite(np.asarray(rss_mb[key], dtype=float))))}
    return {"windows_s": {k: list(v) for k, v in win.items()}, "processes": procs,
            "run_folder": _series_stats(t, disk_mb, win, "mb")}


def latency_stats(lat: np.ndarray, t_end: float, t_start: float = 0.0) -> dict | None:
    """p50 / p99 [ms] of the correction latencies ``lat`` (rows ``[t, latency s]``) in the first
    and last :func:`latency_windows`; ``None`` without any."""
    lat = np.asarray(lat, dtype=float).reshape(-1, 2)
    lat = lat[np.isfinite(lat).all(axis=1)]
    if not lat.size:
        return None
    win = latency_windows(t_end, t_start)
    out = {"windows_s": {k: list(v) for k, v in win.items()}}
    for name, (lo, hi) in win.items():
        x = 1e3 * lat[(lat[:, 0] >= lo) & (lat[:, 0] <= hi), 1]
        out[name] = ({"p50": float(np.percentile(x, 50)), "p99": float(np.percentile(x, 99)), "samples": int(x.size)}
                     if x.size else None)
    return out


# -- the flight ------------------------------------------------------------------------------------
def _flight_latencies(folder: Path) -> np.ndarray:
    """Every vehicle's correction latencies (``[t, s]`` rows) from its flight log in ``folder``."""
    from ..fleet.logs import vehicle_log

    logs, i = [], 0
    while (folder / f"link{i + 1}").is_dir():
        lg = vehicle_log(folder, i)
        if lg is not None:
            logs.append(lg["correction_latency"])
        i += 1
    return np.concatenate(logs) if logs else np.zeros((0, 2))


def run_soak(config: str | Path, duration_s: float, sample_s: float, out_dir: Path, python: str = sys.executable,
             progress=None) -> dict:
    """Fly the fleet of ``config`` unpaced for ``duration_s`` simulated seconds in ``out_dir/fleet``
    (its console in ``out_dir/fleet.log``), sampling every ``sample_s`` wall seconds;
    ``progress(sim_s)`` after each sample. The figures of :func:`analyse` and :func:`latency_stats`
    with every sample's series."""
    path = resolve_config(str(config))
    folder = out_dir / "fleet"
    log_path = out_dir / "fleet.log"
    # no --quiet: the progress bar, written to the log, times the samples in simulated seconds
    argv = [python, "-m", "sitl", "launch", "--config", str(path), "--duration", f"{duration_s:g}", "--speed", "0",
            "--no-plots", "--out", str(folder)]
    roles: dict[int, str | None] = {}
    samples: list[dict] = []
    marks: dict = {}
    offset, tail, sim_now = 0, b"", np.nan
    wall0 = time.perf_counter()
    with open(log_path, "wb") as fh:
        proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT)
        roles[proc.pid] = "harness"
        while True:
            with open(log_path, "rb") as logf:
                logf.seek(offset)
                chunk = logf.read()
            offset += len(chunk)
            text, tail = tail + chunk, (tail + chunk)[-300:]
            wall = time.perf_counter() - wall0
            for mark, line, pattern in (("start", LOCKSTEP_STARTED, _FROM_T), ("end", LOCKSTEP_ENDED, _AT_T)):
                k = text.find(line.encode())
                if f"{mark}_wall" not in marks and k >= 0:
                    marks[f"{mark}_wall"] = wall
                    m = pattern.search(text, k)
                    marks[f"{mark}_t"] = float(m.group(1)) if m else None
            hits = _PROGRESS.findall(text)
            if hits and "start_wall" in marks:
                sim_now = (marks.get("start_t") or 0.0) + float(hits[-1][0])
            loop = "start_wall" in marks and "end_wall" not in marks
            procs = {}
            for pid in descendants(proc.pid) | {proc.pid}:
                if pid not in roles:
                    cmd = command(pid)
                    if cmd is None:
                        continue
                    roles[pid] = role(cmd)
                if roles[pid] is None:
                    continue
                m = memory(pid)
                if m is not None:
                    procs[pid] = m
            samples.append({"wall_s": wall, "progress_s": sim_now if loop else np.nan, "loop": loop,
                            "disk_b": disk_usage(folder), "procs": procs})
            if progress is not None and np.isfinite(sim_now):
                progress(sim_now)
            try:
                proc.wait(timeout=sample_s)
                break
            except subprocess.TimeoutExpired:
                pass
    wall_total = time.perf_counter() - wall0
    try:
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        metrics = {}
    t_end = float(metrics.get("duration_s") or marks.get("end_t") or duration_s)
    t_start = float(marks.get("start_t") or 0.0)
    marks.setdefault("end_t", t_end)
    loop = np.array([s["loop"] for s in samples])
    t, source = sim_times(np.array([s["wall_s"] for s in samples]), np.array([s["progress_s"] for s in samples]),
                          marks)
    t = np.where(loop, t, np.nan)
    keys = process_keys(roles, proc.pid)
    rss = {key: np.array([s["procs"][pid][0] / 1024.0 if pid in s["procs"] else np.nan for s in samples])
           for pid, key in keys.items()}
    fds = {key: np.array([float(s["procs"][pid][1]) if pid in s["procs"] else np.nan for s in samples])
           for pid, key in keys.items()}
    disk = np.array([s["disk_b"] / 2**20 for s in samples])
    result = {"config": str(path), "duration_s": duration_s, "sim_s": t_end, "sample_s": sample_s,
              "exit_code": proc.returncode, "wall_s": wall_total, "realtime_factor": metrics.get("realtime_factor"),
              "crashed": metrics.get("crashed"), "time_source": source, "samples": len(samples),
              **analyse(t, rss, fds, disk, t_end, t_start)}
    result["run_folder"]["mb_final"] = disk_usage(folder) / 2**20
    try:
        result["correction_latency_ms"] = latency_stats(_flight_latencies(folder), t_end, t_start)
    except (OSError, ValueError, KeyError) as exc:
        result["correction_latency_ms"] = None
        result["correction_latency_error"] = str(exc)

    def clean(xs):
        return [None if not np.isfinite(x) else round(float(x), 3) for x in xs]

    result["series"] = {"wall_s": clean([s["wall_s"] for s in samples]), "sim_s": clean(t), "run_folder_mb": clean(disk),
                        "rss_mb": {k: clean(v) for k, v in rss.items()}, "fds": {k: clean(v) for k, v in fds.items()}}
    return result


# -- the report ------------------------------------------------------------------------------------
def _f(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _rows(result: dict) -> list[tuple]:
    rows = []
    order = sorted(result["processes"], key=lambda k: (k != "harness", k))
    for key in order:
        p = result["processes"][key]
        rows.append((key, _f(p["rss_mb_first"], ".0f"), _f(p["rss_mb_last"], ".0f"), _f(p["growth_pct"], "+.1f"),
                     _f(p["rss_mb_per_sim_h"], "+.1f"), _f(p["fds_first"], ".0f"), _f(p["fds_last"], ".0f"),
                     _f(p["fds_per_sim_h"], "+.1f")))
    d = result["run_folder"]
    rows.append(("run folder (disk)", _f(d["mb_first"], ".1f"), _f(d["mb_last"], ".1f"), _f(d["growth_pct"], "+.1f"),
                 _f(d["mb_per_sim_h"], "+.1f"), "", "", ""))
    return rows


HEADER = ("process", "MB first", "MB last", "growth %", "MB/sim h", "fds first", "fds last", "fds/sim h")


def _facts(result: dict) -> list[str]:
    w = result["windows_s"]
    facts = [f"{result['config']}: {result['sim_s']:g} simulated s unpaced in {result['wall_s']:.0f} wall s "
             f"(real-time factor {_f(result['realtime_factor'], '.2f')}, exit {result['exit_code']}); "
             f"{result['samples']} samples every {result['sample_s']:g} s, simulated time from "
             f"{result['time_source']}",
             f"windows (simulated s): first {w['first'][0]:.0f}-{w['first'][1]:.0f}, last {w['last'][0]:.0f}-"
             f"{w['last'][1]:.0f}, fit {w['fit'][0]:.0f}-{w['fit'][1]:.0f}; RSS is VmRSS (current); "
             f"run folder at the end {result['run_folder']['mb_final']:.1f} MB"]
    lat = result.get("correction_latency_ms")
    if lat:
        parts = []
        for name in ("first", "last"):
            lo, hi = lat["windows_s"][name]
            x = lat[name]
            parts.append(f"{name} {lo:.0f}-{hi:.0f} s: " + ("-" if x is None else
                                                             f"p50 {x['p50']:.2f} / p99 {x['p99']:.2f} ms "
                                                             f"({x['samples']})"))
        facts.append("correction latency " + "; ".join(parts))
    else:
        facts.append("correction latency: not in this run's flight logs")
    return facts


def format_soak(result: dict) -> str:
    widths = (20, 9, 9, 9, 9, 10, 9, 10)
    line = lambda cells: " ".join(f"{c:<{w}}" if i == 0 else f"{c:>{w}}"  # noqa: E731
                                  for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([*_facts(result), line(HEADER), *(line(r) for r in _rows(result))])


def markdown_soak(result: dict) -> str:
    from .report import md_table

    return "\n".join([*(f"- {f}" for f in _facts(result)), "", "## Growth per process and of the run folder", "",
                      "MB first / last: mean VmRSS (the run folder: its size on disk) in the first and last 10 % of "
                      "the flight after the warm-up; growth %: between them; MB/sim h and fds/sim h: the slope of "
                      "a straight line fitted over the flight after the warm-up, per simulated hour.", "",
                      md_table(HEADER, _rows(result))])

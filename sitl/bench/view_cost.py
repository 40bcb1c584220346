"""The live view's cost: one batch scenario flown with and without ``--view``, interleaved.

Each flight is ``python -m sitl fly ... --no-plots --no-mcap`` in a child process; the view's
modes are ``off``, ``on`` (the view served, no browser connected) and ``browser`` (headless
Chromium connected to it for the whole flight, drawing every frame). The figure is each flight's
wall time from the real-time factor it reports (the flight loop, view updates included; not the
process's start-up), and the ratio of the median of each mode to the median without the view;
beside it the flight process's CPU seconds (start-up included), which tell the view's own work
from a browser's competing for the same cores.
"""

from __future__ import annotations

import os
import re
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

from .report import fmt, md_table

__all__ = ["MODES", "run_view_cost", "format_view_cost", "markdown_view_cost"]

MODES = ("off", "on", "browser")
_URL = re.compile(r"view: (http://\S+)")


def _browse(url: str, done: threading.Event, errors: list) -> None:
    from sitl.view.browser import HeadlessBrowser

    try:
        with HeadlessBrowser(width=1280, height=800) as browser:
            browser.open(url)
            done.wait()
    except Exception as exc:  # noqa: BLE001 (reported with the flight)
        errors.append(str(exc))


def fly(config: str, duration_s: float, mode: str, out_dir: Path, python: str = sys.executable) -> dict:
    """One flight of ``config`` in view mode ``mode``; its wall time, real-time factor and exit code."""
    argv = [python, "-m", "sitl", "fly", "--config", config, "--duration", str(duration_s), "--out", str(out_dir),
            "--quiet", "--no-plots", "--no-mcap"]
    if mode != "off":
        argv += ["--view", "--view-port", "0"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines, done, errors, browser = [], threading.Event(), [], None
    for line in proc.stdout:
        lines.append(line)
        m = _URL.search(line)
        if m and mode == "browser" and browser is None:
            browser = threading.Thread(target=_browse, args=(m.group(1), done, errors), daemon=True)
            browser.start()
        if "replays it until Ctrl-C" in line:
            proc.send_signal(signal.SIGINT)
    _, status, usage = os.wait4(proc.pid, 0)  # the flight process's own CPU time (not the browser's)
    code = proc.returncode = os.waitstatus_to_exitcode(status)
    done.set()
    if browser is not None:
        browser.join(timeout=30)
    text = "".join(lines)
    m = re.search(r'"realtime_factor": ([0-9.eE+-]+)', text)
    rtf = float(m.group(1)) if m else float("nan")
    return {"mode": mode, "exit_code": code, "realtime_factor": rtf, "flight_wall_s": duration_s / rtf if m else None,
            "process_wall_s": time.perf_counter() - t0, "process_cpu_s": usage.ru_utime + usage.ru_stime,
            "browser_error": errors[0] if errors else None,
            "tail": None if code == 0 else text[-2000:]}


def run_view_cost(config: str, duration_s: float, repeat: int, out_dir: Path, modes=MODES, progress=None) -> dict:
    """``repeat`` rounds of one flight per mode, the modes interleaved in each round."""
    runs = []
    for r in range(repeat):
        for mode in modes:
            runs.append(fly(config, duration_s, mode, out_dir / f"{mode}-{r + 1}") | {"round": r + 1})
            if progress is not None:
                progress(1)
    medians = {}
    for mode in modes:
        walls = [x["flight_wall_s"] for x in runs if x["mode"] == mode and x["flight_wall_s"] is not None]
        medians[mode] = statistics.median(walls) if walls else None
    base = medians.get("off")
    ratios = {m: (w / base if w and base else None) for m, w in medians.items()}
    return {"config": config, "duration_s": duration_s, "repeat": repeat, "runs": runs,
            "median_flight_wall_s": medians, "ratio_to_off": ratios}


def format_view_cost(result: dict) -> str:
    lines = [f"{result['config']}, {result['duration_s']:g} s simulated, {result['repeat']} round(s), modes interleaved"]
    for mode, wall in result["median_flight_wall_s"].items():
        runs = [x for x in result["runs"] if x["mode"] == mode]
        walls = ", ".join(fmt(x["flight_wall_s"], ".2f") for x in runs)
        cpu = statistics.median(x["process_cpu_s"] for x in runs)
        lines.append(f"  view {mode:8s} flight wall {fmt(wall, '.2f')} s (runs: {walls}), "
                     f"x{fmt(result['ratio_to_off'][mode], '.3f')} of no view; flight process CPU {cpu:.2f} s")
    bad = [x for x in result["runs"] if x["exit_code"] != 0 or x["browser_error"]]
    for x in bad:
        lines.append(f"  round {x['round']} {x['mode']}: exit {x['exit_code']} {x['browser_error'] or ''}")
    return "\n".join(lines)


def markdown_view_cost(result: dict) -> str:
    rows = []
    for mode, wall in result["median_flight_wall_s"].items():
        runs = [x for x in result["runs"] if x["mode"] == mode]
        rows.append((f"`{mode}`", fmt(wall, ".2f"), fmt(result["ratio_to_off"][mode], ".3f"),
                     ", ".join(fmt(x["flight_wall_s"], ".2f") for x in runs),
                     ", ".join(fmt(x["realtime_factor"], ".2f") for x in runs),
                     ", ".join(fmt(x["process_cpu_s"], ".2f") for x in runs)))
    head = (f"`{result['config']}`, {result['duration_s']:g} s simulated per flight, {result['repeat']} rounds; in "
            "each round one flight per mode, one after the other. `off`: no view; `on`: `--view`, no browser; "
            "`browser`: `--view` with headless Chromium drawing it (software WebGL, on the same cores). Flight wall "
            "time: simulated seconds over the reported real-time factor; process CPU: the flight process's user and "
            "system seconds, start-up included (the browser's are not).\n\n")
    return head + md_table(("view", "median flight wall [s]", "ratio to `off`", "flights [s]", "real-time factors",
                            "process CPU [s]"),
                           rows) + "\n"

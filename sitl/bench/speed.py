"""How fast the SITL runs: ``python -m sitl.bench sitl``.

In one run, each figure beside the ceiling (MuJoCo alone stepping the same model):

* batch mode (``python -m sitl fly``, one process) for each scenario: the real-time factor of the
  flight loop (simulated seconds per wall second, ``metrics.json``), the process's CPU seconds per
  simulated second and its peak RSS;
* fleet mode unpaced (``python -m sitl launch --speed 0``) for each scenario and simulator link
  (``--sim-link``: PX4's TCP link, the default, and the same-host UNIX-socket link): the
  harness's real-time factor and, per process (harness, each vehicle, each companion), CPU
  seconds per simulated second over the process's life and in the lockstep loop alone (between
  the harness's "lockstep started" and "lockstep ended" log lines), and peak RSS, sampled from
  ``/proc`` while the fleet runs (Linux);
* the MuJoCo-only real-time factor of each scenario's model (the rotors held at hover, no
  firmware, no sensors): what the physics alone allows, the ceiling;
* where each batch scenario's wall time goes, part by part, in one more flight in this process
  (:mod:`.batch_parts`).

Every flight runs as its own process (the ``sitl`` CLIs), its output in a subfolder of the run
folder; the figures go to ``speed.json`` there. Wall-clock figures depend on the machine's load:
the CPU figures are the steadier ones on a shared machine.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ..fleet.layout import LOCKSTEP_ENDED, LOCKSTEP_STARTED, SIM_LINKS
from ..fleet.processes import last_error
from . import procfs
from .batch_parts import batch_parts, markdown_batch_parts

__all__ = ["BATCH_SCENARIOS", "FLEET_SCENARIOS", "firmware_tick", "fleet_args", "fleet_scaling", "mujoco_ceiling",
           "run_batch", "run_fleet", "run_speed", "format_speed", "markdown_speed", "scenario_file"]

log = logging.getLogger(__name__)

BATCH_SCENARIOS = ("three_link", "seven_link", "seven_link_cpg")
#: the fleets: three, seven and fifteen links (how the fleet's speed grows with its length)
FLEET_SCENARIOS = ("three_link", "seven_link", "fifteen_link")
#: the scenario files, by name, in their kinds' folders (configs/sitl/<folder>/<name>.toml)
CONFIG_DIR = Path("configs/sitl")
#: the targets on a 2-core machine: each flight's least real-time factor (a fleet's over
#: every simulator link measured: the same-host link is the one built to meet them, PX4's TCP link
#: stays the default), and the firmware tick's most CPU microseconds per link
RTF_TARGETS = {("batch", "three_link"): 10.0, ("batch", "seven_link"): 5.0, ("fleet", "three_link"): 3.0,
               ("fleet", "seven_link"): 1.5}
TICK_TARGET_US = 30.0


def scenario_file(name: str) -> Path:
    """The scenario file named ``name`` (``configs/sitl/*/<name>.toml``)."""
    paths = sorted(CONFIG_DIR.glob(f"*/{name}.toml"))
    if len(paths) != 1:
        raise ValueError(f"no scenario {name!r} ({CONFIG_DIR}/*/{name}.toml: {len(paths)} files)")
    return paths[0]


def mujoco_ceiling(name: str, duration_s: float) -> dict:
    """MuJoCo alone on the scenario's model (rotors at the hover thrusts, no firmware): its
    real-time factor and CPU seconds per simulated second, in this process."""
    from link_firmware_sim.allocation import Allocator
    from link_firmware_sim.controllers import weight_wrench
    from sitl.plant.plant import Plant
    from sitl.scenario import load_scenario

    sc = load_scenario(scenario_file(name))
    plant = Plant(sc)
    model = plant.model
    allocator = Allocator(plant.geometry, sc.firmware.allocation)
    thrust = np.stack([allocator.allocate(weight_wrench(plant.inertia, q)).command_n
                       for q in model.truth().q_wxyz])  # (n, 8): each link's weight, as at an in-air start
    steps = int(round(duration_s / plant.dt))
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        model.begin_step()
        model.end_step(thrust)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    sim = steps * plant.dt
    return {"scenario": name, "sim_s": sim, "realtime_factor": sim / wall, "cpu_s_per_sim_s": cpu / sim,
            "physics_step_us": 1e6 * wall / steps}


def firmware_tick(n_ticks: int = 5000, seed: int = 0, repeat: int = 5) -> dict:
    """CPU microseconds per firmware tick of one armed link (``LinkFirmware.on_imu`` at 500 Hz, the
    outdoor EKF tuning) as in flight: a new target every 10 ticks (50 Hz), an attitude reference
    every 10 and a GPS fix every 50 (10 Hz), seeded noisy IMU samples; through the one-kernel tick
    (``fused``) and the step-by-step path (``step_by_step``), each after a warm-up. Each is measured
    ``repeat`` times (a fresh firmware each): ``<path>_us`` is the least (what the tick costs; a
    busy host only adds to it), ``<path>_us_runs`` every run."""
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    runs = [_firmware_tick_once(n_ticks, seed) for _ in range(repeat)]
    out = {}
    for key in runs[0]:
        out[key] = min(r[key] for r in runs)
        out[f"{key}_runs"] = [r[key] for r in runs]
    return out


def _firmware_tick_once(n_ticks: int, seed: int) -> dict:
    from companion.messages import PoseTarget
    from companion.skeleton.body import link_inertia
    from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware
    from sitl.scenario import load_scenario

    if n_ticks < 1:
        raise ValueError(f"n_ticks must be at least 1, got {n_ticks}")
    sc = load_scenario(scenario_file("three_link"))
    plant_inertia = link_inertia(sc.skeleton, sc.geometry())
    out = {}
    for label, fused in (("fused", True), ("step_by_step", False)):
        rng = np.random.default_rng(seed)
        fw = LinkFirmware(0, FirmwareConfig(), plant_inertia, sc.geometry())
        fw.fused_tick = fused
        q = np.array([1.0, 0.0, 0.0, 0.0])
        p = np.array([0.0, 0.0, 2.0])
        fw.initialize(0.0, p, np.zeros(3), q)
        fw.arm(0.0)
        gyro = rng.normal(size=(n_ticks + 50, 3)) * 0.01
        accel = np.array([0.0, 0.0, 9.81]) + rng.normal(size=(n_ticks + 50, 3)) * 0.05
        cpu = 0.0
        for k in range(1, n_ticks + 51):
            t = k * 0.002
            if k % 10 == 1:
                fw.set_target(t, PoseTarget.hold(p, q))
                fw.on_attitude(t, q)
            if k % 50 == 1:
                fw.on_gps(t, p + rng.normal(size=3) * 0.1, np.zeros(3))
            c0 = time.process_time()
            fw.on_imu(t, gyro[k - 1], accel[k - 1])
            if k > 50:  # after the warm-up (compiled code loaded)
                cpu += time.process_time() - c0
        out[f"{label}_us"] = 1e6 * cpu / n_ticks
    return out


def _wait_child(proc: subprocess.Popen) -> tuple[int, float, int]:
    """Wait for a child: (return code, CPU seconds, peak RSS [kB])."""
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage.ru_utime + usage.ru_stime, int(usage.ru_maxrss)


def run_batch(name: str, duration_s: float, out_dir: Path, python: str = sys.executable, tag: str = "") -> dict:
    """One batch flight (``python -m sitl fly``) as a child process (``tag``: its folder's suffix)."""
    folder = out_dir / f"batch-{name}{tag}"
    argv = [python, "-m", "sitl", "fly", "--config", str(scenario_file(name)), "--duration", f"{duration_s:g}",
            "--no-plots", "--quiet", "--out", str(folder)]
    wall0 = time.perf_counter()
    with open(out_dir / f"batch-{name}{tag}.log", "wb") as fh:
        proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT)
        code, cpu, rss = _wait_child(proc)
    wall = time.perf_counter() - wall0
    try:
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        metrics = {}
    sim = float(metrics.get("duration_s", duration_s))
    return {"scenario": name, "mode": "batch", "exit_code": code, "sim_s": sim,
            "realtime_factor": metrics.get("realtime_factor"), "process_wall_s": wall,
            "cpu_s_per_sim_s": cpu / sim, "peak_rss_mb": rss / 1024.0, "crashed": metrics.get("crashed"),
            "error": None if code == 0 else last_error(out_dir / f"batch-{name}{tag}.log")}


def fleet_args(name: str, duration_s: float, folder: Path, sim_link: str = "tcp",
               instance_offset: int = 0) -> list[str]:
    """``python -m sitl`` arguments of an unpaced fleet flight without plots (the harness's CPU is
    the lockstep's, not matplotlib's) over ``sim_link``, on PX4 instances from ``instance_offset``
    K; a chain whose companion ports 14540+K+i would reach the GCS port 14550 takes instances from
    11 + K instead."""
    from companion.configfile import load_toml

    path = scenario_file(name)
    n_links = int(load_toml(path).get("skeleton", {}).get("n_links", 0))
    k = instance_offset if n_links + instance_offset <= 10 or instance_offset >= 11 else 11 + instance_offset
    return ["launch", "--config", str(path), "--duration", f"{duration_s:g}", "--speed", "0", "--quiet",
            "--no-plots", "--sim-link", sim_link, "--instance-offset", str(k), "--out", str(folder)]


def run_fleet(name: str, duration_s: float, out_dir: Path, python: str = sys.executable,
              sample_s: float = 0.25, sim_link: str = "tcp", tag: str = "", instance_offset: int = 0) -> dict:
    """One unpaced fleet flight (``python -m sitl launch --speed 0 --sim-link SIM_LINK``): the
    launcher is the harness; its children's CPU and peak RSS are sampled from /proc until they
    exit (the last sample is up to ``sample_s`` before a process's end)."""
    folder = out_dir / f"fleet-{name}-{sim_link}{tag}"
    argv = [python, "-m", "sitl", *fleet_args(name, duration_s, folder, sim_link, instance_offset)]
    log_path = folder.with_name(folder.name + ".log")
    seen: dict[int, tuple[str, float, int]] = {}
    # every process's CPU seconds when the harness logged the lockstep's start and its end
    marks: dict[str, dict[int, float]] = {}
    stop = threading.Event()
    wall0 = time.perf_counter()
    with open(log_path, "wb") as fh:
        proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT)

        def sampler() -> None:
            offset, text = 0, ""
            latest: dict[int, float] = {}  # every process's newest CPU figure (one gone keeps its last)
            while not stop.is_set():
                # the markers first, then the samples: a mark is at most one period early
                with open(log_path, "rb") as logf:
                    logf.seek(offset)
                    chunk = logf.read()
                offset += len(chunk)
                text = text[-200:] + chunk.decode(errors="replace")
                due = [m for m, line in (("start", LOCKSTEP_STARTED), ("end", LOCKSTEP_ENDED))
                       if m not in marks and line in text]
                for pid in procfs.descendants(proc.pid) | {proc.pid}:
                    s = procfs.sample(pid)
                    if s is not None and (pid == proc.pid or procfs.role(s[0]) is not None):
                        latest[pid] = s[1]
                        if pid != proc.pid:
                            seen[pid] = s
                for m in due:  # (a process stopped right after the loop: its last figure)
                    marks[m] = dict(latest)
                stop.wait(sample_s)

        thread = threading.Thread(target=sampler, daemon=True)
        thread.start()
        code, cpu, rss = _wait_child(proc)
        stop.set()
        thread.join()
    wall = time.perf_counter() - wall0
    try:
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        metrics = {}
    sim = float(metrics.get("duration_s") or duration_s)
    processes = {"harness": {"cpu_s_per_sim_s": None, "peak_rss_mb": rss / 1024.0}}
    # The launcher's own rusage covers it and its waited-for children: its own CPU is what is left.
    children_cpu = 0.0
    for cmd, c, hwm in seen.values():
        role = procfs.role(cmd)
        processes[role] = {"cpu_s_per_sim_s": c / sim, "peak_rss_mb": hwm / 1024.0}
        children_cpu += c
    processes["harness"]["cpu_s_per_sim_s"] = max(cpu - children_cpu, 0.0) / sim
    # In the loop only (start-up and the end's log merging left out): the CPU between the marks,
    # each sampled up to sample_s after its log line; a process started in flight from zero.
    loop_total = None
    if "start" in marks and "end" in marks:
        loop_total = 0.0
        for pid, c_end in marks["end"].items():
            c = c_end - marks["start"].get(pid, 0.0)
            role = "harness" if pid == proc.pid else procfs.role(seen[pid][0]) if pid in seen else None
            if role in processes:
                processes[role]["loop_cpu_s_per_sim_s"] = c / sim
                loop_total += c
    return {"scenario": name, "mode": "fleet", "sim_link": sim_link, "scheduling": metrics.get("scheduling"),
            "companion_kernels": metrics.get("companion_kernels"), "exit_code": code, "sim_s": sim,
            "realtime_factor": metrics.get("realtime_factor"), "process_wall_s": wall,
            "cpu_s_per_sim_s": cpu / sim, "loop_cpu_s_per_sim_s": None if loop_total is None else loop_total / sim,
            "processes": processes, "crashed": metrics.get("crashed"),
            "error": None if code == 0 else last_error(log_path)}


def median_of(runs: list[dict]) -> dict:
    """The run with the median real-time factor of repeated runs of one thing (the lower middle one
    of an even count), with every run's real-time factor and CPU figure beside it
    (``realtime_factor_runs``, ``cpu_s_per_sim_s_runs``, in run order): a VM's speed varies by
    tens of percent from minute to minute, and one sample can land anywhere in that range."""
    ok = [r for r in runs if r.get("realtime_factor") is not None]
    if not ok:
        return dict(runs[0])
    out = dict(sorted(ok, key=lambda r: r["realtime_factor"])[(len(ok) - 1) // 2])
    if len(runs) > 1:
        out["realtime_factor_runs"] = [r.get("realtime_factor") for r in runs]
        out["cpu_s_per_sim_s_runs"] = [r.get("cpu_s_per_sim_s") for r in runs]
    return out


def run_speed(out_dir: Path, batch_s: float, fleet_s: float, batch: tuple[str, ...] = BATCH_SCENARIOS,
              fleet: tuple[str, ...] = FLEET_SCENARIOS, ceiling_s: float = 5.0, progress=None, repeat: int = 1,
              sim_links: tuple[str, ...] = SIM_LINKS, instance_offset: int = 0) -> dict:
    """Every figure of the bench; ``progress(label)`` after each flight; the fleets on PX4
    instances from ``instance_offset`` (:func:`fleet_args`). ``repeat``: every figure
    (the MuJoCo ceilings, the batch flights, the fleets over each of ``sim_links``) is measured
    that many times, interleaved (everything once, then again), and each is the median run
    (:func:`median_of`)."""
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    bad = [x for x in sim_links if x not in SIM_LINKS]
    if bad or (fleet and not sim_links):
        raise ValueError(f"sim links {', '.join(bad) or '(none)'}: one or more of {', '.join(SIM_LINKS)}")
    from companion.kernels.jit import ENABLED as compiled

    from ..runner import warm_up_kernels

    for name in {*batch, *fleet}:
        scenario_file(name)  # a clear error before anything runs
    # compiled (or loaded) once, before the flights load the cache
    compile_s = warm_up_kernels()
    tick = firmware_tick()
    models = list(dict.fromkeys((*batch, *fleet)))
    ceiling_runs: dict[str, list] = {name: [] for name in models}
    batch_runs: dict[str, list] = {name: [] for name in batch}
    fleet_runs: dict[tuple[str, str], list] = {(name, link): [] for name in fleet for link in sim_links}
    for k in range(repeat):
        for name in models:
            ceiling_runs[name].append(mujoco_ceiling(name, ceiling_s))
            if progress:
                progress(f"MuJoCo {name}")
        for name in batch:
            batch_runs[name].append(run_batch(name, batch_s, out_dir, tag=f"-{k + 1}" if repeat > 1 else ""))
            if progress:
                progress(f"batch {name}")
        for name, link in fleet_runs:
            fleet_runs[name, link].append(run_fleet(name, fleet_s, out_dir, sim_link=link,
                                                    tag=f"-{k + 1}" if repeat > 1 else "",
                                                    instance_offset=instance_offset))
            if progress:
                progress(f"fleet {name} ({link})")
    parts = {}
    for name in batch:
        parts[name] = batch_parts(scenario_file(name), batch_s)
        if progress:
            progress(f"batch {name}, part by part")
    ceilings = {name: median_of(ceiling_runs[name]) for name in models}
    runs = [median_of(batch_runs[name]) for name in batch] + [median_of(r) for r in fleet_runs.values()]
    for r in runs:
        ceiling = ceilings[r["scenario"]]["realtime_factor"]
        r["ratio_to_ceiling"] = None if r["realtime_factor"] is None else r["realtime_factor"] / ceiling
        _judge(r)
    if tick:
        tick["target_us"] = TICK_TARGET_US
        tick["target_met"] = tick["fused_us"] <= TICK_TARGET_US
    return {"compiled": compiled, "warm_up_s": compile_s, "firmware_tick_us": tick, "cpu_count": os.cpu_count(),
            "load_average_at_end": os.getloadavg(), "repeat": repeat, "mujoco_ceiling": ceilings, "runs": runs,
            "batch_parts": parts}


def _judge(r: dict) -> None:
    """Give run ``r`` its target (:data:`RTF_TARGETS`, ``None`` for a flight without one) and whether
    it met it (a flight that failed, with no real-time factor, did not)."""
    target = RTF_TARGETS.get((r.get("mode"), r.get("scenario")))
    r["target_rtf"] = target
    r["target_met"] = None if target is None else (r.get("realtime_factor") or 0.0) >= target and r.get("exit_code") == 0


def _verdict(result: dict) -> str:
    """One line: which figures met their targets and which did not."""
    met, missed = [], []
    tick = result.get("firmware_tick_us")
    if tick and "target_met" in tick:
        (met if tick["target_met"] else missed).append(f"firmware tick <= {tick['target_us']:g} us")
    for r in result["runs"]:
        if r.get("target_rtf") is not None:
            label = f"{r['mode']} {r['scenario']}" + (f" ({r['sim_link']})" if "sim_link" in r else "")
            (met if r["target_met"] else missed).append(f"{label} >= {r['target_rtf']:g}x")
    if not met and not missed:
        return ""
    return (f"targets met: {', '.join(met) or 'none'}; missed: {', '.join(missed) or 'none'}"
            f" (MuJoCo alone, the machine's phase: "
            + ", ".join(f"{name} {c['realtime_factor']:.0f}x" for name, c in result["mujoco_ceiling"].items()) + ")")


def _fleet_facts(result: dict) -> list[str]:
    """How the fleets ran: their scheduling policy (``sitl launch``: SCHED_BATCH unpaced, unless
    --default-scheduling or not Linux) and their companions' path (compiled kernels or numpy)."""
    fleets = [r for r in result["runs"] if r.get("mode") == "fleet"]
    facts = []
    for key, what in (("scheduling", "fleets' scheduling policy"), ("companion_kernels", "fleets' companions")):
        values = sorted({str(r.get(key)) for r in fleets})
        if values:
            facts.append(f"{what}: {', '.join(values)}")
    return facts


def format_speed(result: dict) -> str:
    rows = [f"kernels compiled: {result['compiled']} (warm-up {result['warm_up_s']:.1f} s); "
            f"load average at the end {', '.join(f'{x:.1f}' for x in result['load_average_at_end'])}",
            f"{'run':<28} {'RTF':>6} {'/ceiling':>9} {'CPU s/sim s':>12} {'in loop':>8} {'peak RSS MB':>12} {'target':>14}"]
    tick = result.get("firmware_tick_us")
    if tick:
        runs = len(tick.get("fused_us_runs", ())) or 1
        target = "" if "target_us" not in tick else \
            f" (target <= {tick['target_us']:g} us: {'met' if tick['target_met'] else 'MISSED'})"
        rows.insert(1, f"firmware tick per link (CPU, least of {runs}): {tick['fused_us']:.1f} us one-kernel, "
                       f"{tick['step_by_step_us']:.1f} us step by step{target}")
    if result.get("repeat", 1) > 1:
        rows.insert(1, f"every figure: the median of {result['repeat']} interleaved runs (all runs' "
                       f"real-time factors in brackets)")
    for fact in reversed(_fleet_facts(result)):
        rows.insert(1, fact)
    for name, c in result["mujoco_ceiling"].items():
        rows.append(f"{'MuJoCo only ' + name:<28} {c['realtime_factor']:>6.1f} {1.0:>9.3f} {c['cpu_s_per_sim_s']:>12.3f}"
                     f" {'':>8} {'':>12} {'':>14}{_runs_text(c)}")
    for r in result["runs"]:
        rtf = r["realtime_factor"]
        label = (f"{r['mode']} {r['scenario']}" + (f" ({r['sim_link']})" if "sim_link" in r else "")
                 + ("" if r["exit_code"] == 0 else f" (exit {r['exit_code']})"))
        rtf_s = "-" if rtf is None else f"{rtf:.2f}"
        ratio = "-" if r["ratio_to_ceiling"] is None else f"{r['ratio_to_ceiling']:.3f}"
        rss = f"{r['peak_rss_mb']:.0f}" if "peak_rss_mb" in r else ""
        target = "" if r.get("target_rtf") is None else \
            f">= {r['target_rtf']:g}x " + ("met" if r["target_met"] else "MISSED" if r["exit_code"] == 0 else "failed")
        rows.append(f"{label:<28} {rtf_s:>6} {ratio:>9} {r['cpu_s_per_sim_s']:>12.3f} {_loop(r):>8} {rss:>12}"
                    f" {target:>14}{_runs_text(r)}")
        if r.get("error"):  # (why a run failed: not a speed figure)
            rows.append(f"  {r['error']}")
        for role, p in sorted(r.get("processes", {}).items(), key=_role_key):
            rows.append(f"{'  ' + role:<28} {'':>6} {'':>9} {p['cpu_s_per_sim_s']:>12.3f} {_loop(p):>8}"
                        f" {p['peak_rss_mb']:>12.0f}")
    scaling = fleet_scaling(result)
    if len(scaling) > 1:
        rows += ["", f"fleet scaling, CPU s per simulated s {scaling[0]['cpu']} by process kind (total; per process):",
                 f"{'fleet':<28} {'links':>5} {'RTF':>6} {'/ceiling':>9} {'harness':>8} {'vehicles':>16} "
                 f"{'companions':>16} {'all':>7} {'cores busy':>10} {'CPU-bound RTF':>13}"]
        for f in scaling:
            rows.append(f"{f['label']:<28} {f['links']:>5} {fmt_x(f['realtime_factor'], '.2f'):>6} "
                        f"{fmt_x(f['ratio_to_ceiling'], '.3f'):>9} {f['harness']:>8.3f} "
                        f"{f['vehicles']:>7.3f}; {f['per_vehicle']:>6.3f} {f['companions']:>7.3f}; "
                        f"{f['per_companion']:>6.3f} {f['all']:>7.3f} {fmt_x(f['cores_busy'], '.2f'):>10} "
                        f"{fmt_x(f['cpu_bound_rtf'], '.2f'):>13}")
    for name, p in (result.get("batch_parts") or {}).items():
        c = result["mujoco_ceiling"].get(name)
        mujoco = "" if c is None else f", MuJoCo alone {1e3 / c['realtime_factor']:.1f}"
        rows.append(f"batch {name}, wall ms per simulated s: total {p['total_ms_per_sim_s']:.1f}{mujoco}; "
                    + ", ".join(f"{k} {v:.1f}" for k, v in p["ms_per_sim_s"].items()))
    verdict = _verdict(result)
    if verdict:
        rows.append(verdict)
    return "\n".join(rows)


def fmt_x(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _role_key(item) -> tuple:
    """A fleet's processes in their natural order: the harness, then vehicles and companions by number."""
    kind, _, number = item[0].partition(" ")
    return kind, int(number.lstrip("g")) if number.lstrip("g").isdigit() else 0


def fleet_scaling(result: dict) -> list[dict]:
    """Per fleet flight of a :func:`run_speed` result: its links, real-time factor and ratio to
    MuJoCo alone, and the CPU seconds per simulated second of each kind of process (harness,
    vehicles, companions: their total and per process) and of all; in the lockstep loop alone
    (``cpu`` says ``in loop``) when every process has that figure, else over their lives. With
    the loop's figures, also ``cores_busy``, the CPU seconds all the fleet's processes took per
    wall second (all times the real-time factor), and ``cpu_bound_rtf``, the real-time factor at
    which those CPU costs would keep every core of the machine (``cpu_count``) busy: no lockstep
    on it runs faster (``None`` where unknown)."""
    cores = result.get("cpu_count")
    out = []
    for r in result["runs"]:
        procs = r.get("processes") or {}
        if r.get("mode") != "fleet" or not procs:
            continue
        in_loop = all(p.get("loop_cpu_s_per_sim_s") is not None for p in procs.values())
        key = "loop_cpu_s_per_sim_s" if in_loop else "cpu_s_per_sim_s"
        kinds: dict[str, list[float]] = {"harness": [], "vehicle": [], "companion": []}
        for role, p in procs.items():
            kinds.setdefault(role.split()[0], []).append(p[key])
        n_v, n_c = len(kinds["vehicle"]), len(kinds["companion"])
        total, rtf = sum(sum(v) for v in kinds.values()), r["realtime_factor"]
        out.append({"label": f"{r['scenario']} ({r.get('sim_link')})", "links": n_v,
                    "realtime_factor": r["realtime_factor"], "ratio_to_ceiling": r["ratio_to_ceiling"],
                    "cpu": "in loop" if in_loop else "over their lives", "harness": sum(kinds["harness"]),
                    "vehicles": sum(kinds["vehicle"]), "per_vehicle": sum(kinds["vehicle"]) / max(n_v, 1),
                    "companions": sum(kinds["companion"]), "per_companion": sum(kinds["companion"]) / max(n_c, 1),
                    "all": total,
                    "cores_busy": total * rtf if in_loop and rtf is not None else None,
                    "cpu_bound_rtf": cores / total if in_loop and cores and total > 0 else None})
    return out


def _loop(r: dict) -> str:
    """A fleet figure's CPU seconds per simulated second in the lockstep loop alone (else blank)."""
    x = r.get("loop_cpu_s_per_sim_s")
    return "" if x is None else f"{x:.3f}"


def _runs_text(r: dict) -> str:
    runs = r.get("realtime_factor_runs")
    return "" if not runs else "  [" + " ".join("-" if x is None else f"{x:.2f}" for x in runs) + "]"


def markdown_speed(result: dict) -> str:
    """The Markdown tables of a :func:`run_speed` result (``speed.json``): :func:`format_speed`'s figures."""
    from .report import fmt, md_table

    parts = []
    facts = [f"kernels compiled: {result['compiled']} (warm-up {result['warm_up_s']:.1f} s)",
             f"load average at the end: {', '.join(f'{x:.2f}' for x in result['load_average_at_end'])}"]
    if result.get("batch_duration_s") is not None:
        facts.append(f"simulated seconds per batch flight {result['batch_duration_s']:g}, per fleet flight "
                     f"{result['fleet_duration_s']:g}")
    if result.get("repeat", 1) > 1:
        facts.append(f"every figure: the median of {result['repeat']} interleaved runs (every run's real-time "
                     "factor in the last column)")
    facts += _fleet_facts(result)
    parts += [f"- {f}" for f in facts]
    tick = result.get("firmware_tick_us")
    if tick:
        runs = len(tick.get("fused_us_runs", ())) or 1
        target = "" if "target_us" not in tick else \
            f"; target <= {tick['target_us']:g} us: {'met' if tick['target_met'] else '**missed**'}"
        parts += ["", "## Firmware tick per link (CPU)", "",
                  f"Least of {runs} runs: {tick['fused_us']:.1f} us one-kernel, {tick['step_by_step_us']:.1f} us "
                  f"step by step{target}."]

    def runs_cell(r):
        xs = r.get("realtime_factor_runs")
        return "" if not xs else " ".join("-" if x is None else f"{x:.2f}" for x in xs)

    rows = [(f"MuJoCo only {name}", f"{c['realtime_factor']:.1f}", "1.000", f"{c['cpu_s_per_sim_s']:.3f}", "", "", "",
             runs_cell(c)) for name, c in result["mujoco_ceiling"].items()]
    for r in result["runs"]:
        label = (f"{r['mode']} {r['scenario']}" + (f" ({r['sim_link']})" if "sim_link" in r else "")
                 + ("" if r["exit_code"] == 0 else f" (exit {r['exit_code']})"))
        target = "" if r.get("target_rtf") is None else \
            f">= {r['target_rtf']:g}x " + ("met" if r["target_met"]
                                           else "**missed**" if r["exit_code"] == 0 else "failed")
        rows.append((label, fmt(r["realtime_factor"], ".2f"), fmt(r["ratio_to_ceiling"], ".3f"),
                     f"{r['cpu_s_per_sim_s']:.3f}", fmt(r.get("loop_cpu_s_per_sim_s"), ".3f", ""),
                     fmt(r.get("peak_rss_mb"), ".0f", ""), target, runs_cell(r)))
        for role, p in sorted(r.get("processes", {}).items(), key=_role_key):
            rows.append((f"- {role}", "", "", fmt(p["cpu_s_per_sim_s"], ".3f"),
                         fmt(p.get("loop_cpu_s_per_sim_s"), ".3f", ""), f"{p['peak_rss_mb']:.0f}", "", ""))
    parts += ["", "## Real-time factors, CPU and memory", "",
              "RTF: simulated seconds per wall second; /ceiling: against MuJoCo alone on the same model; CPU s/sim s: "
              "CPU seconds per simulated second over the process's life, *in loop*: in the lockstep loop alone; "
              "the rows under a fleet that start with a dash are its processes.", "",
              md_table(("run", "RTF", "/ceiling", "CPU s/sim s", "in loop", "peak RSS [MB]", "target",
                        "every run's RTF"), rows)]
    scaling = fleet_scaling(result)
    if len(scaling) > 1:
        parts += ["", "## Fleet scaling", "",
                  f"CPU seconds per simulated second {scaling[0]['cpu']}, by kind of process: the total, and per process "
                  "in brackets. *Cores busy*: the CPU seconds all the fleet's processes took per wall second in the "
                  f"loop (all times the RTF), of the machine's {result.get('cpu_count') or '?'}; *CPU-bound RTF*: the "
                  "real-time factor at which these CPU costs would keep every core busy, which no lockstep on this "
                  "machine exceeds without cutting them.", "",
                  md_table(("fleet", "links", "RTF", "/ceiling", "harness", "vehicles", "companions", "all",
                            "cores busy", "CPU-bound RTF"),
                           [(f["label"], f["links"], fmt(f["realtime_factor"], ".2f"), fmt(f["ratio_to_ceiling"], ".3f"),
                             f"{f['harness']:.3f}", f"{f['vehicles']:.3f} ({f['per_vehicle']:.3f})",
                             f"{f['companions']:.3f} ({f['per_companion']:.3f})", f"{f['all']:.3f}",
                             fmt(f["cores_busy"], ".2f"), fmt(f["cpu_bound_rtf"], ".2f"))
                            for f in scaling])]
    if result.get("batch_parts"):
        parts += ["", "## Where a batch flight's time goes", "",
                  "Wall milliseconds per simulated second, part by part (`sitl/bench/batch_parts.py`), in one more "
                  "flight of each batch scenario in the bench's process, beside MuJoCo alone on the same model. "
                  "The firmware's column leaves the sensors out; its batch's gathers and syncs (last column) fall in "
                  "whichever part asked for them.", "",
                  markdown_batch_parts(result["batch_parts"], result["mujoco_ceiling"])]
    verdict = _verdict(result)
    if verdict:
        parts += ["", verdict + "."]
    return "\n".join(parts)

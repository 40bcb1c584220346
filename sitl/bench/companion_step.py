"""The companion's 20 Hz cycle on one chain, on the numpy path (the onboard base install: no
numba) and on the compiled path, against the cycle's budget (``python -m sitl.bench companion``).

Each path flies the scenario in batch mode in a child process of its own (``SKELETON_JIT=0`` for
the numpy path), with one centralised companion over every link (``companion.distributed =
false``: the onboard computer that steps the whole chain). The engine's own timers give each
step's compute time (the SCKF step: admission, gates, constraint application, corrections) and
each target computation's (the trajectory's targets with the whole-chain feed-forward). A cycle
computes one step and ``target_rate_hz / rate_hz`` target sets; the budget is the cycle,
``1 / rate_hz``. The figures are this machine's; the margin to the budget is what a slower
onboard computer has to spend.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys

from companion.cli import seconds

__all__ = ["PATHS", "measure", "run_companion_step", "format_companion_step", "markdown_companion_step",
           "add_companion_step_parser", "build_parser", "main"]

#: the two paths: name -> the ``SKELETON_JIT`` value of its child
PATHS = {"numpy": "0", "compiled": "1"}
DEFAULT_CONFIG = "configs/sitl/chain/seven_link.toml"


def _stats(q) -> dict | None:
    """A :class:`~companion.quantiles.Quantiles` of milliseconds as a record."""
    if not q.count:
        return None
    return {"count": q.count, "p50": q.percentile(50), "p99": q.percentile(99), "max": q.max,
            "mean": q.total / q.count}


def measure(config: str, duration_s: float) -> dict:
    """In this process: fly ``config`` for ``duration_s`` in batch mode with one centralised
    companion; the step's and the targets' compute times [ms] and what a cycle holds."""
    from companion.kernels.jit import ENABLED
    from sitl.runner import BatchRunner, warm_up_kernels
    from sitl.scenarios import load

    _, sc = load(config, duration_s=duration_s, settings={"companion.distributed": False})
    warm_up_kernels()  # loaded (or compiled) before anything is timed
    runner = BatchRunner(sc)
    runner.run(duration_s)
    (engine,) = runner.engines
    cfg = sc.companion
    return {"compiled": bool(ENABLED), "n_links": sc.skeleton.n_links, "rate_hz": cfg.rate_hz,
            "target_rate_hz": cfg.target_rate_hz, "duration_s": duration_s, "crashed": runner.crashed,
            "step_ms": _stats(engine.step.step_times_ms), "targets_ms": _stats(engine.targets.compute_ms)}


def run_companion_step(config: str = DEFAULT_CONFIG, duration_s: float = 20.0, python: str = sys.executable,
                       progress=None) -> dict:
    """Both paths, each in a child process (module docstring); per path :func:`measure`'s record
    and the cycle's figures: ``cycle_mean_ms`` (a step and its share of target sets, their means),
    ``cycle_worst_ms`` (the slowest step and as many of the slowest target set as a cycle can
    hold: a bound), the budget and the margin."""
    result = {"config": str(config), "duration_s": duration_s, "paths": {}}
    for name, jit in PATHS.items():
        env = {**os.environ, "SKELETON_JIT": jit, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "disable")}
        proc = subprocess.run([python, "-m", "sitl.bench.companion_step", str(config), f"{duration_s:g}"],
                              capture_output=True, text=True, env=env, timeout=3600)
        if proc.returncode != 0:
            raise RuntimeError(f"the {name} path's flight failed ({proc.returncode}): {proc.stderr[-2000:]}")
        rec = json.loads(proc.stdout.strip().splitlines()[-1])
        if rec["compiled"] != (jit == "1"):
            raise RuntimeError(f"the {name} path ran {'compiled' if rec['compiled'] else 'numpy'} kernels")
        per_cycle = rec["target_rate_hz"] / rec["rate_hz"]
        step, targets = rec["step_ms"], rec["targets_ms"]
        budget = 1e3 / rec["rate_hz"]
        rec["targets_per_cycle"] = per_cycle
        rec["cycle_mean_ms"] = step["mean"] + per_cycle * targets["mean"]
        rec["cycle_worst_ms"] = step["max"] + math.ceil(per_cycle) * targets["max"]
        rec["budget_ms"] = budget
        rec["margin"] = budget / rec["cycle_worst_ms"]
        result["paths"][name] = rec
        if progress is not None:
            progress(1)
    return result


def format_companion_step(result: dict) -> str:
    """The console table of a :func:`run_companion_step` result."""
    any_rec = next(iter(result["paths"].values()))
    lines = [f"Companion cycle on {any_rec['n_links']} links ({result['config']}, {result['duration_s']:g} s, one "
             f"centralised companion): compute per call [ms]", "",
             f"{'path':<9} | {'step p50':>8} {'p99':>6} {'max':>6} | {'targets p50':>11} {'p99':>6} {'max':>6} | "
             f"{'cycle mean':>10} {'worst':>6} | {'budget':>6} {'margin':>6}", "-" * 100]
    for name, r in result["paths"].items():
        s, t = r["step_ms"], r["targets_ms"]
        lines.append(f"{name:<9} | {s['p50']:8.2f} {s['p99']:6.2f} {s['max']:6.2f} | {t['p50']:11.2f} {t['p99']:6.2f} "
                     f"{t['max']:6.2f} | {r['cycle_mean_ms']:10.2f} {r['cycle_worst_ms']:6.2f} | {r['budget_ms']:6.1f} "
                     f"{r['margin']:5.1f}x")
    return "\n".join(lines)


def markdown_companion_step(result: dict) -> str:
    """The Markdown report's body of a :func:`run_companion_step` result."""
    from .report import md_table

    any_rec = next(iter(result["paths"].values()))
    rows = []
    for name, r in result["paths"].items():
        s, t = r["step_ms"], r["targets_ms"]
        rows.append((name, f"{s['p50']:.2f}", f"{s['p99']:.2f}", f"{s['max']:.2f}", f"{t['p50']:.2f}", f"{t['p99']:.2f}",
                     f"{t['max']:.2f}", f"{r['cycle_mean_ms']:.2f}", f"{r['cycle_worst_ms']:.2f}", f"{r['budget_ms']:.0f}",
                     f"{r['margin']:.1f}x"))
    intro = (f"One centralised companion over {any_rec['n_links']} links (`{result['config']}`, "
             f"{result['duration_s']:g} simulated seconds in batch mode), each path in its own process: milliseconds "
             f"of compute per call. A cycle is one step and {any_rec['targets_per_cycle']:g} target set(s) on average; "
             "*worst*: the slowest step and as many of the slowest target set as a cycle can hold (a bound); "
             "*margin*: the budget (the 20 Hz cycle) over the worst cycle.")
    return intro + "\n\n" + md_table(
        ("path", "step p50", "step p99", "step max", "targets p50", "targets p99", "targets max", "cycle mean",
         "cycle worst", "budget", "margin"), rows)


def add_companion_step_parser(sub, output_args, publish) -> None:
    """The ``companion`` bench's subcommand (``output_args``, ``publish``: the bench command's own)."""
    p = sub.add_parser(
        "companion",
        help="the companion's 20 Hz cycle on seven links: numpy path and compiled path against the budget",
        description=("Fly a chain in batch mode with one centralised companion, once without numba (SKELETON_JIT=0, "
                     "the onboard base install) and once with the compiled kernels, each in its own process; print "
                     "each path's step and target compute times per call and the worst cycle against the 50 ms "
                     "budget of a 20 Hz step."))
    p.add_argument("--config", default=DEFAULT_CONFIG, help=f"chain scenario (default {DEFAULT_CONFIG})")
    p.add_argument("--duration", type=seconds, default=20.0, help="simulated seconds per path (default 20)")
    output_args(p, "companion")
    p.set_defaults(func=lambda args: _cmd(args, publish))


def _cmd(args, publish) -> int:
    from companion.cli import make_run_dir

    if args.duration <= 0:
        print(f"error: --duration must be positive, got {args.duration}", file=sys.stderr)
        return 2
    from companion.configfile import ConfigError
    from sitl.scenarios import load

    try:  # the children's scenario, checked here (no MuJoCo): a bad file or duration is a usage error
        load(args.config, duration_s=args.duration, settings={"companion.distributed": False})
    except (OSError, ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run_dir = make_run_dir("companion", args.out)
    print(f"two flights of {args.duration:g} s (numpy path, compiled path) ...", file=sys.stderr)
    try:
        result = run_companion_step(args.config, args.duration)
    except RuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    publish(args, run_dir, result, "companion.json", format_companion_step(result), markdown_companion_step(result))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The command line of one path's child (:func:`run_companion_step` starts it with
    ``SKELETON_JIT`` set): ``CONFIG DURATION``; it prints :func:`measure`'s record as JSON."""
    p = argparse.ArgumentParser(prog="python -m sitl.bench.companion_step",
                                description="One path's flight of python -m sitl.bench companion: prints its JSON record.")
    p.add_argument("config", help="chain scenario")
    p.add_argument("duration", type=seconds, help="simulated seconds")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    print(json.dumps(measure(args.config, args.duration)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``python -m sitl campaign``: fly a grid of scenarios x settings x seeds on Dask, and compare tables.

    python -m sitl campaign run --config FILE [--config FILE ...] [--set KEY=V1,V2 ...] --seeds 0-9
        [--mode batch|fleet] [--speed F] [--duration S] [--out DIR] [--scheduler tcp://HOST:PORT | --workers N |
        --serial] [--retries R] [--worker-dir DIR] [--plot METRIC,...] [--quiet]
    python -m sitl campaign faults --config FILE --flights N [--seed S] [--mode batch|fleet] [--speed F]
        [--duration S] [--out DIR] [--scheduler tcp://HOST:PORT | --workers N | --serial] [--quiet]
    python -m sitl campaign diff A/results.csv B/results.csv
"""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path

from companion.cli import make_run_dir, pace, progress_bar
from companion.configfile import ConfigError

from .grid import MODES, make_grid, parse_seeds, parse_sweep

__all__ = ["add_campaign_parser"]

EXIT_FAILED_RUNS = 1
EXIT_BAD_CONFIG = 2
EXIT_INTERRUPTED = 130


class _Bar:
    """The campaign's progress bar: finished runs of all, with running / failed / lost."""

    def __init__(self, total: int, quiet: bool):
        self.bar = progress_bar(total=total, desc="campaign", unit="run", disable=quiet)

    def __call__(self, counts: dict) -> None:
        if not hasattr(self.bar, "n"):
            return
        self.bar.n = counts["done"]
        self.bar.set_postfix_str(f"running {counts['running']}, failed {counts['failed']}, lost {counts['lost']}",
                                 refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        if hasattr(self.bar, "close"):
            self.bar.close()


def _raise_interrupt(_signum, _frame):
    raise KeyboardInterrupt


def _grid(args):
    seeds = parse_seeds(args.seeds)
    sweeps = [parse_sweep(s) for s in args.set]
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be positive, got {args.duration}")
    # absolute: a worker's working folder is its own (a machine of the lab holds the repository at the same path)
    return make_grid([str(Path(c).resolve()) for c in args.config], sweeps, seeds, args.mode, args.duration,
                     speed=args.speed)


def _cmd_run(args) -> int:
    from .flights import RESULTS_FILE, check_specs, write_summaries

    try:
        specs = _grid(args)
        renders = check_specs(specs)
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    if args.workers is not None and args.workers < 1:
        print("error: --workers must be >= 1", file=sys.stderr)
        return EXIT_BAD_CONFIG
    root = make_run_dir("campaign", args.out)
    (root / "campaign.json").write_text(json.dumps({
        "configs": [str(c) for c in args.config], "set": args.set, "seeds": args.seeds, "mode": args.mode,
        "speed": args.speed, "duration_s": args.duration, "runs": len(specs)}, indent=1) + "\n")
    result = _fly(args, root, specs, renders)
    if isinstance(result, int):
        return result
    files = [root / RESULTS_FILE] + write_summaries(root, [r for r in result.records if r], f"Campaign {root.name}",
                                                    [p for p in args.plot.split(",") if p] if args.plot else None)
    counts = result.counts()
    print(f"{len(specs)} runs: {result.skipped} finished before, {result.ran} now "
          f"({counts['ok']} ok, {counts['failed']} failed, {counts['lost']} lost) in {result.wall_s:.1f} s")
    print(f"wrote {', '.join(str(p.relative_to(root)) for p in files[:4])}{' and plots/' if len(files) > 4 else ''} "
          f"in {root}")
    return 0 if counts["failed"] == counts["lost"] == 0 else EXIT_FAILED_RUNS


def _fly(args, root: Path, specs, renders: bool):
    """Fly ``specs`` in ``root`` where ``args`` say (a cluster, a scheduler, serially); the
    :class:`~sitl.campaign.engine.CampaignResult`, or the exit code of an interrupt or error."""
    from .cluster import open_executor
    from .flights import run_flights

    where = "serially in this process" if args.serial else (args.scheduler or f"a local cluster of "
                                                             f"{args.workers or 'one worker per core'}")
    print(f"campaign: {len(specs)} runs in {root} ({where})", file=sys.stderr)
    bar = _Bar(len(specs), args.quiet)
    signal.signal(signal.SIGTERM, _raise_interrupt)  # `kill` / a batch system's stop: as Ctrl-C
    try:
        return run_flights(root, specs, lambda: open_executor(args.scheduler, args.workers, args.serial, args.retries),
                           renders=renders, progress=bar,
                           worker_root=str(Path(args.worker_dir).resolve()) if args.worker_dir else None)
    except KeyboardInterrupt:
        again = "the same command" if args.out else f"the same command with --out {root}"
        print(f"interrupted: the finished runs are in {root / 'results.csv'}; {again} goes on where "
              "this one stopped", file=sys.stderr)
        return EXIT_INTERRUPTED
    except ImportError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    except OSError as exc:  # e.g. no scheduler at --scheduler
        print(f"error: {args.scheduler or 'local cluster'}: {exc}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    finally:
        bar.close()


def _cmd_faults(args) -> int:
    from .fault_campaign import fault_specs, write_fault_report

    if args.workers is not None and args.workers < 1:
        print("error: --workers must be >= 1", file=sys.stderr)
        return EXIT_BAD_CONFIG
    try:
        specs, events = fault_specs(str(Path(args.config).resolve()), args.flights, args.seed, args.mode, args.duration,
                                    args.speed)
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    root = make_run_dir("faults", args.out)
    result = _fly(args, root, specs, False)
    if isinstance(result, int):
        return result
    table, crashes, text = write_fault_report(root, specs, events, result.records, args)
    print(text, end="")
    counts = result.counts()
    print(f"{len(specs)} flights: {counts['ok']} flown, {counts['failed']} failed, {counts['lost']} lost; "
          f"{len(crashes)} crashed; wrote faults.md and faults.json in {root}")
    return 0 if counts["failed"] == counts["lost"] == 0 else EXIT_FAILED_RUNS


def _cmd_diff(args) -> int:
    from .table import compare, read_table

    try:
        a, b = read_table(args.a), read_table(args.b)
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_CONFIG
    diffs = compare(a, b)
    for line in diffs[:args.max]:
        print(line)
    if len(diffs) > args.max:
        print(f"... and {len(diffs) - args.max} more")
    print(f"{len(a)} and {len(b)} runs: " + ("identical (timing columns aside)" if not diffs
                                              else f"{len(diffs)} difference(s)"))
    return 0 if not diffs else 1


def _where_args(parser) -> None:
    """Where a campaign's runs fly: a scheduler, a local cluster or serially; retries, worker folder, bar."""
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="a running Dask scheduler (dask scheduler)")
    where.add_argument("--workers", type=int, metavar="N", help="local cluster of N worker processes (default: one "
                                                                "per core)")
    where.add_argument("--serial", action="store_true", help="no cluster: the runs one after another in this process")
    parser.add_argument("--retries", type=int, default=2, metavar="R",
                        help="local cluster: give a run whose worker died to another up to R times (default 2)")
    parser.add_argument("--worker-dir", metavar="DIR", help="where the workers write the run folders (default: the "
                                                            "campaign folder; for workers that do not share it)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _speed_arg(parser) -> None:
    parser.add_argument("--speed", type=pace, default=0.0, metavar="F",
                        help="fleet mode: pace the flights at F times real time (default 0: as fast as the lockstep "
                             "allows). The lockstep does not wait for the companions: unpaced, their wall-clock "
                             "latency is several times longer in simulated time than onboard; 1 keeps it as onboard")


def add_campaign_parser(sub) -> None:
    """``campaign run``, ``campaign faults`` and ``campaign diff`` on ``python -m sitl``'s subcommands."""
    cp = sub.add_parser("campaign", help="fly many runs (scenarios x settings x seeds) on Dask; one results table",
                        description="Campaigns: a grid of scenarios x parameter settings x seeds on a Dask cluster "
                                    "(local by default), resumable, with one results table and its summaries.")
    csub = cp.add_subparsers(dest="action", metavar="ACTION", required=True)
    run = csub.add_parser(
        "run", help="fly a campaign (the same command with the same --out goes on where it stopped)",
        description="Fly every combination of --config, --set values and --seeds; each run writes its folder, the "
                    "campaign keeps results.csv (a row per run), summary.csv/.md (mean, std, 95 % interval per "
                    "setting), box plots and the pooled NEES. Finished runs are never flown again.")
    run.add_argument("--config", action="append", required=True, metavar="FILE",
                     help="scenario file (repeat for several)")
    run.add_argument("--set", action="append", default=[], metavar="KEY=V1[,V2...]",
                     help="a scenario key and the values it takes, e.g. firmware.ekf.gate_sigma=3,5 (TOML values; "
                          "repeat for a grid of several)")
    run.add_argument("--seeds", required=True, metavar="SEEDS", help="seeds, e.g. 0-9 or 0,3,7-9")
    run.add_argument("--mode", choices=MODES, default="batch",
                     help="batch: python -m sitl fly; fleet: python -m sitl launch (paced by --speed) on instance "
                          "offsets leased per host (default batch)")
    _speed_arg(run)
    run.add_argument("--duration", type=float, metavar="S", help="simulated seconds per run (default: the scenario's)")
    run.add_argument("--out", metavar="DIR", help="campaign folder (default: runs/campaign-<UTC time>); "
                                                  "an existing one goes on where it stopped")
    _where_args(run)
    run.add_argument("--plot", metavar="METRICS", help="box plots of these metrics, comma-separated "
                                                       "(default: the headline metrics)")
    run.set_defaults(func=_cmd_run)
    faults = csub.add_parser(
        "faults", help="fly random fault schedules drawn from a seed and report per kind of fault",
        description="Draw --flights fault schedules from --seed (link reboots; GPS steps, ramps and outages; injected "
                    "GPS, IMU, motor and MAVLink link failures; in fleet mode also lossy wires and, in distributed scenarios, "
                    "companion kills: kind, link, start, "
                    "length, overlaps), fly them as a campaign and write faults.md / faults.json: per kind the "
                    "crashes, lowest altitude, worst tracking and constraint error during the outages and outside "
                    "them, corrections lost and time to recover, and every crash with its settings and seed. The "
                    "same command again goes on where it stopped.")
    faults.add_argument("--config", required=True, metavar="FILE", help="scenario file the faults are added to")
    faults.add_argument("--flights", type=int, required=True, metavar="N", help="how many flights")
    faults.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the schedules and the flights "
                                                                          "(default 0)")
    faults.add_argument("--mode", choices=MODES, default="fleet",
                        help="fleet (default: every kind of fault) or batch (no lossy wires, no companion kills)")
    _speed_arg(faults)
    faults.add_argument("--duration", type=float, metavar="S", help="simulated seconds per flight (default: the "
                                                                     "scenario's)")
    faults.add_argument("--out", metavar="DIR", help="campaign folder (default: runs/faults-<UTC time>); an "
                                                     "existing one goes on where it stopped")
    _where_args(faults)
    faults.set_defaults(func=_cmd_faults)
    diff = csub.add_parser("diff", help="compare two results tables (timing columns aside)",
                           description="Print the runs and values in which two results.csv differ; exit 0 when "
                                       "identical (wall time, worker, host, attempts and real-time factor aside).")
    diff.add_argument("a", type=Path, metavar="A")
    diff.add_argument("b", type=Path, metavar="B")
    diff.add_argument("--max", type=int, default=40, help="differences printed at most (default 40)")
    diff.set_defaults(func=_cmd_diff)

"""Benchmarks that print figures and write JSON.

    python -m sitl.bench table2 [--json PATH] [--seed S] [--seeds N] [--duration S] [--ekf {paper,consistent,both}]
                                [--jobs J | --scheduler tcp://HOST:PORT] [--out DIR]
    python -m sitl.bench scaling [--json PATH] [--seed S] [--out DIR]
    python -m sitl.bench zenoh [--duration S] [--groups 1,2/3,4,5/6,7] [--json PATH] [--out DIR]
    python -m sitl.bench nees [--config TOML] [--seeds N] [--duration S] [--profile P] [--jobs J | --scheduler ADDR]
    python -m sitl.bench static [--config TOML] [--seeds N] [--duration S] [--profile P] [--jobs J | --scheduler ADDR]
    python -m sitl.bench load_filter [--seeds N] [--seed S] [--duration S] [--latency S] [--out DIR]
    python -m sitl.bench corners [--config TOML] [--duration S] [--seed S] [--out DIR]
    python -m sitl.bench sitl [--duration S] [--fleet-duration S] [--batch A,B] [--fleet A,B] [--out DIR]
    python -m sitl.bench controllers [--config TOML] [--controllers A,B] [--duration S] [--seed S] [--out DIR]
    python -m sitl.bench view [--config TOML] [--duration S] [--repeat N] [--modes off,on,browser] [--out DIR]
    python -m sitl.bench soak [--config NAME|PATH] [--duration S] [--sample-s S] [--out DIR]
    python -m sitl.bench companion [--config TOML] [--duration S] [--out DIR]
    (every bench also takes [--doc [PATH] | --no-doc], below)

Each run writes into one folder (``--out``, default ``runs/<bench>-<UTC time>``): the JSON
result (or ``--json PATH`` instead) and, for table2, the EKF stream of the first seed in the
``companion replay`` input format (``ekf_stream.npz`` for the paper's tuning,
``ekf_stream_consistent.npz`` for the consistent one) with the truth (``truth.npz``).

Every bench also writes a Markdown report of the same result (``sitl/bench/report.py``: the
command, UTC date, git commit, machine, then the figures as tables): ``<bench>.md`` in the run
folder by default, ``docs/bench/<bench>.md`` (the published figures, never edited by hand) with
``--doc``, any other file with ``--doc PATH``, none with ``--no-doc``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from tqdm import tqdm

from companion.estimation.sckf import CAParams
from companion.estimation.semi import parse_groups
from companion.cli import make_run_dir, nonnegative_seconds, run_subcommand, seconds

from .companion_step import add_companion_step_parser
from .ekf_chain import EKF_CONFIGS, ChainRun
from .report import add_doc_options, doc_path, load_average, write_doc
from .scaling import LINK_COUNTS, format_scaling, markdown_scaling, run_scaling
from .table2 import aggregate_seeds, combine_configs, format_table2_configs, markdown_table2, table2_seed
from .zenoh_rtt import format_zenoh_rtt, markdown_zenoh_rtt, run_zenoh_rtt

#: per bench (the subcommand): the report's title and the packages whose versions it records
DOCS = {
    "table2": ("Table II protocol (paper sec. IV): accuracy and compute time vs. group size",
               ("numpy", "scipy", "numba")),
    "scaling": ("Constraint application per step vs. chain length", ("numpy", "scipy", "numba")),
    "zenoh": ("Global step over Zenoh on loopback: round trip", ("numpy", "scipy", "eclipse-zenoh")),
    "nees": ("Monte Carlo NEES of a SITL flight over seeds", ("numpy", "scipy", "mujoco", "numba")),
    "static": ("The thesis's static test over seeds", ("numpy", "scipy", "mujoco", "numba")),
    "load_filter": ("Slung load pose: EKF vs UKF vs unfiltered (synthetic)", ("numpy", "scipy")),
    "corners": ("ArUco corner refinement on rendered frames: corners, range bias, pose",
                ("numpy", "opencv-python-headless", "mujoco")),
    "sitl": ("SITL speed: batch and fleet real-time factors against MuJoCo alone",
             ("numpy", "scipy", "mujoco", "numba", "pymavlink", "eclipse-zenoh")),
    "controllers": ("One link's pose controllers on one scenario: tracking", ("numpy", "mujoco", "numba")),
    "view": ("The live 3D view's cost: a batch flight with and without --view", ("numpy", "mujoco", "numba", "viser")),
    "companion": ("The companion's 20 Hz cycle: numpy path and compiled path against the budget",
                  ("numpy", "scipy", "numba", "mujoco")),
    "soak": ("Soak: an unpaced fleet's memory, descriptors and disk over a long flight",
             ("numpy", "mujoco", "numba", "pymavlink", "eclipse-zenoh")),
}



def _write_json(result: dict, json_path: str | None, run_dir: Path, name: str) -> Path:
    path = Path(json_path) if json_path else run_dir / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    return path


def _write_doc(args, run_dir: Path, body: str, console: str, outputs) -> None:
    """This run's Markdown report (:mod:`.report`) where ``--doc`` / ``--no-doc`` say; ``args.command``
    names the bench (:data:`DOCS`)."""
    name = args.command
    path = doc_path(args, run_dir, name)
    if path is None:
        return
    title, packages = DOCS[name]
    argv = getattr(args, "argv", None) or [name]
    started = getattr(args, "started", None)
    write_doc(path, title=title, argv=argv, body=body, console=console, packages=packages,
              elapsed_s=None if started is None else time.perf_counter() - started, outputs=outputs,
              load_start=getattr(args, "load_start", None))
    print(f"wrote the Markdown report {path}")


def _publish(args, run_dir: Path, result: dict, json_name: str, text: str, body: str, also: str = "",
             outputs=()) -> None:
    """The end of every bench: the result's JSON (``--json`` or ``json_name`` in the run folder),
    the console table ``text`` and where everything went (``also``: the other outputs), and the
    Markdown report of ``body`` with ``outputs`` (:func:`_write_doc`)."""
    path = _write_json(result, args.json, run_dir, json_name)
    print(text)
    print(f"\nwrote {path}{also}")
    _write_doc(args, run_dir, body, text, [path, *outputs])


def _params(args) -> CAParams | None:
    """The CA parameters from the options, or ``None`` after printing what is wrong."""
    try:
        return CAParams(eps=args.eps, alpha=args.alpha)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None


def _executor(args):
    """The campaign engine's executor for a bench over seeds: ``--scheduler``'s cluster, else a
    local cluster of ``--jobs`` workers, or (``--jobs 1``) this process."""
    from sitl.campaign.cluster import open_executor

    return open_executor(args.scheduler, args.jobs, args.jobs == 1 and not args.scheduler)


def _runs_done(bar):
    """A campaign's progress callback that moves ``bar`` to the finished runs."""
    def progress(counts):
        bar.n = counts["done"]
        bar.refresh()

    return progress


def _cmd_table2(args) -> int:
    params = _params(args)
    if params is None:
        return 2
    if args.duration <= 0 or args.seeds < 1 or args.jobs < 1:
        print(f"error: --duration must be positive, --seeds and --jobs >= 1 (got {args.duration}, {args.seeds}, "
              f"{args.jobs})", file=sys.stderr)
        return 2
    from sitl.campaign.engine import Campaign, Job

    configs = EKF_CONFIGS if args.ekf == "both" else (args.ekf,)
    run = ChainRun(duration_s=args.duration)
    run_dir = make_run_dir("table2", args.out)
    seeds = list(range(args.seed, args.seed + args.seeds))
    jobs = [Job(f"table2|{','.join(configs)}|duration_s={args.duration!r}|eps={params.eps!r}|alpha={params.alpha!r}"
                f"|seed={seed}", Path(f"seed-{seed}"), table2_seed,
                (seed, run, configs, params, str(run_dir.resolve()) if seed == args.seed else None)) for seed in seeds]
    with tqdm(total=len(seeds), desc=f"EKF x {args.seeds} seed(s) x {len(configs)} tuning(s)", unit="seed",
              disable=args.quiet, file=sys.stderr) as bar:
        campaign = Campaign(run_dir, jobs).run(lambda: _executor(args), progress=_runs_done(bar))
    failed = [r for r in campaign.records if r["status"] != "ok"]
    if failed:
        print(f"error: seed {failed[0]['key'].rsplit('=', 1)[1]}: {failed[0]['error']}", file=sys.stderr)
        return 1
    results = {name: [r["result"][name] for r in campaign.records] for name in configs}
    result = combine_configs({name: aggregate_seeds(res) for name, res in results.items()})
    streams = ", ".join(f"ekf_stream{'' if n == 'paper' else '_' + n}.npz ({n})" for n in configs)
    _publish(args, run_dir, result, "table2.json", format_table2_configs(result), markdown_table2(result),
             f" and in {run_dir}: {streams}, replay inputs of seed {args.seed}")
    return 0


def _cmd_scaling(args) -> int:
    params = _params(args)
    if params is None:
        return 2
    run_dir = make_run_dir("scaling", args.out)
    with tqdm(total=len(LINK_COUNTS), desc="chain lengths", unit="n", disable=args.quiet, file=sys.stderr) as bar:
        result = run_scaling(args.seed, LINK_COUNTS, params=params, progress=bar.update)
    _publish(args, run_dir, result, "scaling.json", format_scaling(result), markdown_scaling(result))
    return 0


def _cmd_zenoh(args) -> int:
    try:
        links = [int(x) for part in args.groups.split("/") for x in part.split(",") if x.strip()]
        groups = parse_groups(args.groups, max(links))
    except ValueError as exc:
        print(f"error: --groups: {exc}", file=sys.stderr)
        return 2
    if args.duration <= 0 or len(groups) < 2:
        print("error: --duration must be positive and --groups name at least two groups", file=sys.stderr)
        return 2
    run_dir = make_run_dir("zenoh", args.out)
    print(f"{args.duration:g} s of global steps over Zenoh on loopback ...", file=sys.stderr)
    result = run_zenoh_rtt(groups, args.duration, seed=args.seed, base_port=args.base_port)
    _publish(args, run_dir, result, "zenoh.json", format_zenoh_rtt(result), markdown_zenoh_rtt(result))
    return 0


def _output_args(p: argparse.ArgumentParser, name: str, folder: str | None = None) -> None:
    """The outputs every bench takes: ``--json``, ``--out`` (default ``runs/<folder>-<UTC time>``,
    ``folder`` defaulting to the bench's name), ``--quiet`` and the Markdown report's options."""
    p.add_argument("--json", metavar="PATH", help="write the JSON result here (default: inside the run folder)")
    p.add_argument("--out", metavar="DIR", help=f"run folder (default: runs/{folder or name}-<UTC time>)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_doc_options(p, name)


def _flight_bench_args(p: argparse.ArgumentParser, name: str, config: str, what: str) -> None:
    """The options of a bench that flies one scenario: its file, length, seed, outputs."""
    p.add_argument("--config", default=config, help=f"{what} (default {config})")
    p.add_argument("--duration", type=seconds, help="simulated seconds per flight (default: the scenario's)")
    p.add_argument("--seed", type=int, help="random seed (default: the scenario's)")
    _output_args(p, name)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m sitl.bench", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", metavar="PATH", help="write the JSON result here (default: inside the run folder)")
    common.add_argument("--out", metavar="DIR", help="run folder (default: runs/<bench>-<UTC time>)")
    common.add_argument("--seed", type=int, default=0, help="seed of every random draw (default 0)")
    common.add_argument("--eps", type=float, default=CAParams.eps, help="CA stop threshold ||c|| [m] (default 0.01)")
    common.add_argument("--alpha", type=float, default=CAParams.alpha, help="weakening factor (default 0.01)")
    common.add_argument("--quiet", action="store_true", help="no progress bar")
    t2 = sub.add_parser(
        "table2",
        parents=[common],
        help="paper Table II: 12 links, 20 s, group sizes 2/3/4/6/12",
        description="The paper's sec. IV protocol: compute time and accuracy per group size.",
    )
    t2.add_argument("--duration", type=seconds, default=ChainRun.duration_s, help="simulated seconds (default 20)")
    t2.add_argument(
        "--seeds",
        type=int,
        default=5,
        metavar="N",
        help="repeat with seeds S..S+N-1 and report mean +- std and the noise check (default 5)",
    )
    t2.add_argument(
        "--ekf",
        choices=(*EKF_CONFIGS, "both"),
        default="both",
        help="EKF tuning: paper (Table I, drifts unmodelled), consistent (drifts carried in the noise) or both on "
        "the same sensor data (default both)",
    )
    t2.add_argument("--jobs", type=int, default=1,
                    help="seeds at once: a local Dask cluster of J worker processes (default 1: one after another in "
                         "this process, where the compute times are not disturbed by a neighbour)")
    t2.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="fly the seeds on this running Dask scheduler's "
                                                                  "workers (python -m sitl campaign's engine)")
    add_doc_options(t2, "table2")
    t2.set_defaults(func=_cmd_table2)
    sc = sub.add_parser(
        "scaling",
        parents=[common],
        help="per-step time of full and semi-distributed SCKF for n = 3..96",
        description="Per-step time of Alg. 1 (full chain) and Alg. 2 + eq. 6 (groups of 2) vs. chain length.",
    )
    add_doc_options(sc, "scaling")
    sc.set_defaults(func=_cmd_scaling)
    zb = sub.add_parser(
        "zenoh",
        parents=[common],
        help="global step over Zenoh on loopback: round trip printed by the leader",
        description=("One process and Zenoh peer session per group on 127.0.0.1; every 50 ms each publishes its "
                     "boundary, the leader solves eq. 6 and publishes the shifts. Prints the round trip "
                     "(boundary published -> shift received) the groups report to the leader."),
    )
    zb.add_argument("--duration", type=seconds, default=20.0, help="seconds of cycles (default 20)")
    zb.add_argument("--groups", default="1,2/3,4,5/6,7", metavar="LAYOUT",
                    help="group layout, 1-based links (default 1,2/3,4,5/6,7: the thesis's seven links)")
    zb.add_argument("--base-port", type=int, default=17447, help="group g listens on TCP base+g-1 (default 17447)")
    add_doc_options(zb, "zenoh")
    zb.set_defaults(func=_cmd_zenoh)
    for name, config, help_text, desc in (
        ("nees", "configs/sitl/chain/three_link.toml", "Monte Carlo NEES: a flight over N seeds, per link and block",
         "Fly a batch scenario once per seed and average each link's NEES (position, velocity, attitude; EKF and "
         "corrected) over the window and the seeds, with the 95 % bounds of that average for a consistent filter."),
        ("static", "configs/sitl/chain/seven_link_static.toml", "the thesis's static test over N seeds (GNSS receiver model)",
         "Fly the resting 7-link chain once per seed with a receiver-like GNSS (--profile, default m8) and report "
         "per link and axis the std and RMS error of the EKF, local and semi-distributed estimates, mean and spread "
         "over seeds, beside the thesis's sec. 3.5.2 figures."),
    ):
        sp = sub.add_parser(name, help=help_text, description=desc)
        sp.add_argument("--config", default=config, help=f"scenario file (default {config})")
        sp.add_argument("--seeds", type=int, default=10, metavar="N", help="seeds S..S+N-1 (default 10)")
        sp.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
        sp.add_argument("--duration", type=seconds, help="simulated seconds per seed (default: the scenario's)")
        sp.add_argument("--profile", default="m8" if name == "static" else None,
                        help="sensor profile instead of the scenario's" + (" (default m8)" if name == "static" else ""))
        sp.add_argument("--jobs", type=int, default=2,
                        help="flights at once: a local Dask cluster of J worker processes (1: one after another in "
                             "this process; default 2)")
        sp.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                        help="fly on this running Dask scheduler's workers instead (python -m sitl campaign's engine)")
        _output_args(sp, name)
        sp.set_defaults(func=_cmd_seeds, bench=name)
    _add_sitl_parser(sub)
    _add_view_parser(sub)
    _add_soak_parser(sub)
    add_companion_step_parser(sub, _output_args, _publish)
    lfb = sub.add_parser(
        "load_filter",
        help="slung load pose: EKF vs UKF vs unfiltered on the synthetic scenario, N seeds",
        description=("Three vehicles fly the report's 2 m circle at 1.5 m/s carrying a box by elastic cables "
                     "(sitl/scenarios/slung_load/synthetic.py, no MuJoCo); seeded GNSS and PnP-like images arriving late. Prints "
                     "the load position/orientation RMS of the EKF, UKF, unfiltered solve and open-loop model."),
    )
    lfb.add_argument("--seeds", type=int, default=3, metavar="N", help="seeds S..S+N-1 (default 3)")
    lfb.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    lfb.add_argument("--duration", type=seconds, default=12.0, help="simulated seconds per seed (default 12)")
    lfb.add_argument("--latency", type=nonnegative_seconds, default=0.08,
                     help="image latency before jitter [s] (default 0.08)")
    _output_args(lfb, "load_filter")
    lfb.set_defaults(func=_cmd_load_filter)
    co = sub.add_parser(
        "corners",
        help="ArUco corner refinement (none, subpix, contour, apriltag) on a flight's rendered frames",
        description=("Fly a scenario with cameras and detect every delivered frame's markers once per corner "
                     "refinement; report each method's corner error against the true corners (RMS and inward bias, "
                     "px), the PnP range bias, position and attitude error, and its detection time."))
    _flight_bench_args(co, "corners", "configs/sitl/load/slung_load_three.toml", "a scenario with cameras and markers")
    co.set_defaults(func=_cmd_corners)
    cb = sub.add_parser(
        "controllers",
        help="one link's pose controllers (impedance, SE(3) PID) on one scenario: tracking errors",
        description=("Fly a scenario once per controller ([firmware] controller: impedance, eq. 1; se3_pid, thesis "
                     "sec. 2.3.2), everything else equal, and report link 1's RMS position and attitude tracking "
                     "against the truth and the estimate, from the end of the figure eight's amplitude ramp."),
    )
    cb.add_argument("--controllers", default="impedance,se3_pid", metavar="A,B",
                    help="controllers, comma-separated (default impedance,se3_pid)")
    _flight_bench_args(cb, "controllers", "configs/sitl/odar/single_odar_figure8.toml", "scenario file")
    cb.set_defaults(func=_cmd_controllers)
    return parser


def _cmd_controllers(args) -> int:
    from typing import get_args, get_type_hints

    from link_firmware_sim.firmware_config import FirmwareConfig
    from sitl.scenario import load_scenario

    from .controllers import compare_controllers, format_controllers, markdown_controllers

    controllers = tuple(x for x in args.controllers.split(",") if x)
    known = get_args(get_type_hints(FirmwareConfig)["controller"])
    overrides = {k: v for k, v in (("duration_s", args.duration), ("seed", args.seed)) if v is not None}
    try:
        sc = load_scenario(args.config, **overrides)
        if not controllers or not set(controllers) <= set(known):
            raise ValueError(f"--controllers: one or more of {', '.join(known)}, got {args.controllers!r}")
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run_dir = make_run_dir("controllers", args.out)
    with tqdm(total=len(controllers) * sc.duration_s, desc="controllers", unit="sim s", disable=args.quiet,
              file=sys.stderr) as bar:
        result = compare_controllers(sc, run_dir, controllers, progress=bar.update)
    _publish(args, run_dir, result, "controllers.json", format_controllers(result), markdown_controllers(result),
             f", {run_dir / 'compare_tracking.png'} and each controller's log.npz in {run_dir}",
             [run_dir / "compare_tracking.png"])
    return 0 if not any(m["crashed"] for m in result["controllers"].values()) else 1


def _cmd_seeds(args) -> int:
    from sitl.scenario import load_scenario
    from sitl.plant.sensors import PROFILES

    from sitl.campaign.flights import run_flights

    from .seeds import (aggregate_nees, aggregate_static, format_nees, format_static, markdown_nees, markdown_static,
                        seed_folder, seed_specs)

    if args.seeds < 1 or args.jobs < 1 or (args.duration is not None and args.duration <= 0):
        print("error: --seeds and --jobs must be >= 1 and --duration positive", file=sys.stderr)
        return 2
    if args.profile is not None and args.profile not in PROFILES:
        print(f"error: --profile: unknown profile {args.profile!r} (one of {', '.join(PROFILES)})", file=sys.stderr)
        return 2
    overrides = {} if args.duration is None else {"duration_s": args.duration}
    try:
        sc = load_scenario(args.config, **overrides)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.bench == "static" and sc.trajectory.kind != "rest":
        print(f"error: {args.config}: the static protocol needs a resting chain (trajectory.kind = \"rest\")",
              file=sys.stderr)
        return 2
    run_dir = make_run_dir(args.bench, args.out)
    seeds = list(range(args.seed, args.seed + args.seeds))
    specs = seed_specs(Path(args.config).resolve(), seeds, args.duration, args.profile)
    with tqdm(total=len(seeds), desc=f"{sc.name} x {len(seeds)} seed(s)", unit="flight", disable=args.quiet,
              file=sys.stderr) as bar:
        campaign = run_flights(run_dir, specs, lambda: _executor(args), folder=seed_folder, progress=_runs_done(bar))
    failed = [r for r in campaign.records if r["status"] != "ok"]
    if failed:
        print(f"error: {len(failed)} of {len(seeds)} flights did not finish, e.g. {failed[0]['key']}: "
              f"{failed[0]['error']} (run.log and error.txt in its folder)", file=sys.stderr)
        return 1
    runs = [r["result"] for r in campaign.records]
    try:
        result = aggregate_nees(runs) if args.bench == "nees" else aggregate_static(runs)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    result["profile"] = args.profile or sc.sensors.profile
    result["duration_s"] = sc.duration_s
    fmt, markdown = (format_nees, markdown_nees) if args.bench == "nees" else (format_static, markdown_static)
    _publish(args, run_dir, result, f"{args.bench}.json", fmt(result), markdown(result),
             f" and one folder per seed in {run_dir}")
    return 0


def _cmd_sitl(args) -> int:
    from .speed import format_speed, markdown_speed, run_speed

    batch = tuple(x for x in args.batch.split(",") if x)
    fleet = tuple(x for x in args.fleet.split(",") if x)
    sim_links = tuple(x for x in args.sim_link.split(",") if x)
    if args.duration <= 0 or args.fleet_duration <= 0 or args.ceiling_duration <= 0:
        print("error: --duration, --fleet-duration and --ceiling-duration must be positive", file=sys.stderr)
        return 2
    if args.repeat < 1:
        print("error: --repeat must be at least 1", file=sys.stderr)
        return 2
    if not 0 <= args.instance_offset <= 20:
        print(f"error: --instance-offset {args.instance_offset}: 0 to 20 (PX4 SITL's ports have room for 40 "
              "instances; the fifteen-link fleet takes 15)", file=sys.stderr)
        return 2
    run_dir = make_run_dir("sitl-speed", args.out)
    total = args.repeat * (len(set(batch) | set(fleet)) + len(batch) + len(fleet) * len(sim_links))
    with tqdm(total=total, desc="speed", unit="run", disable=args.quiet, file=sys.stderr) as bar:
        try:
            result = run_speed(run_dir, args.duration, args.fleet_duration, batch, fleet, args.ceiling_duration,
                               progress=lambda label: (bar.set_postfix_str(label), bar.update()), repeat=args.repeat,
                               sim_links=sim_links, instance_offset=args.instance_offset)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    result.update(batch_duration_s=args.duration, fleet_duration_s=args.fleet_duration)
    _publish(args, run_dir, result, "speed.json", format_speed(result), markdown_speed(result),
             f"; every flight's folder and console log in {run_dir}")
    return 0 if all(r["exit_code"] == 0 for r in result["runs"]) else 1


def _add_sitl_parser(sub) -> None:
    from .speed import BATCH_SCENARIOS, FLEET_SCENARIOS

    sp = sub.add_parser(
        "sitl", help="SITL speed: batch and unpaced fleet real-time factors, CPU and RSS per process, MuJoCo ceiling",
        description=("Fly each batch scenario (python -m sitl fly) and each fleet scenario unpaced (python -m sitl "
                     "launch --speed 0) as child processes; report the real-time factor, CPU seconds per simulated "
                     "second and peak RSS of every process, and MuJoCo alone on the same model as the ceiling."))
    sp.add_argument("--duration", type=seconds, default=20.0, help="simulated seconds per batch flight (default 20)")
    sp.add_argument("--fleet-duration", type=seconds, default=20.0,
                    help="simulated seconds per fleet flight (default 20)")
    sp.add_argument("--ceiling-duration", type=seconds, default=5.0,
                    help="simulated seconds of MuJoCo alone per model (default 5)")
    sp.add_argument("--batch", default=",".join(BATCH_SCENARIOS),
                    help=f"batch scenarios, comma-separated (default {','.join(BATCH_SCENARIOS)}; empty: none)")
    sp.add_argument("--fleet", default=",".join(FLEET_SCENARIOS),
                    help=f"fleet scenarios, comma-separated (default {','.join(FLEET_SCENARIOS)}; empty: none)")
    sp.add_argument("--sim-link", default="tcp,unix", metavar="LINKS",
                    help="the fleets' simulator links, comma-separated: tcp (PX4's TCP 4560+i), unix (the same-host "
                         "link) (default tcp,unix: both, in one run)")
    sp.add_argument("--repeat", type=int, default=1,
                    help="measure every figure (MuJoCo ceilings, batch flights, fleets) N times, interleaved, and "
                         "report the median run with every run's real-time factor (default 1; a VM's speed drifts)")
    sp.add_argument("--instance-offset", type=int, default=0, metavar="K",
                    help="the fleets on PX4 instances from K (their ports shifted by K, as sitl launch's "
                         "--instance-offset), beside another fleet on this machine (default 0; a chain that would "
                         "reach the GCS port takes 11 + K)")
    _output_args(sp, "sitl", folder="sitl-speed")
    sp.set_defaults(func=_cmd_sitl)


def _cmd_view(args) -> int:
    from .view_cost import MODES, format_view_cost, markdown_view_cost, run_view_cost

    modes = tuple(m for m in args.modes.split(",") if m)
    if args.repeat < 1 or args.duration <= 0 or not modes or any(m not in MODES for m in modes):
        print(f"error: --repeat >= 1, --duration > 0 and --modes from {','.join(MODES)} (got {args.repeat}, "
              f"{args.duration}, {args.modes})", file=sys.stderr)
        return 2
    run_dir = make_run_dir("view-cost", args.out)
    with tqdm(total=args.repeat * len(modes), desc="flights", disable=args.quiet, file=sys.stderr) as bar:
        result = run_view_cost(args.config, args.duration, args.repeat, run_dir, modes, progress=bar.update)
    _publish(args, run_dir, result, "view_cost.json", format_view_cost(result), markdown_view_cost(result))
    return 0 if all(r["exit_code"] == 0 and not r["browser_error"] for r in result["runs"]) else 1


def _add_view_parser(sub) -> None:
    vp = sub.add_parser("view", help="the live 3D view's cost: a batch flight with and without --view, interleaved",
                        description="Fly one batch scenario N times in each view mode (off, on, on with headless "
                                    "Chromium connected), interleaved, and compare the flights' wall times.")
    vp.add_argument("--config", default="configs/sitl/chain/three_link.toml", help="scenario (default three_link)")
    vp.add_argument("--duration", type=seconds, default=30.0, help="simulated seconds per flight (default 30)")
    vp.add_argument("--repeat", type=int, default=3, help="rounds (default 3)")
    vp.add_argument("--modes", default="off,on,browser", help="view modes, comma-separated (default off,on,browser)")
    _output_args(vp, "view", folder="view-cost")
    vp.set_defaults(func=_cmd_view)


def _cmd_soak(args) -> int:
    from .soak import format_soak, markdown_soak, resolve_config, run_soak

    try:
        if args.duration <= 0 or args.sample_s <= 0:
            raise ValueError("--duration and --sample-s must be positive")
        resolve_config(args.config)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run_dir = make_run_dir("soak", args.out)
    with tqdm(total=args.duration, desc="soak", unit="sim s", disable=args.quiet, file=sys.stderr) as bar:
        result = run_soak(args.config, args.duration, args.sample_s, run_dir,
                          progress=lambda t: bar.update(max(0.0, min(t, bar.total) - bar.n)))
    _publish(args, run_dir, result, "soak.json", format_soak(result), markdown_soak(result),
             f"; the flight in {run_dir / 'fleet'}, its console in {run_dir / 'fleet.log'}")
    return 0 if result["exit_code"] == 0 else 1


def _add_soak_parser(sub) -> None:
    sp = sub.add_parser("soak", help="an unpaced fleet's RSS, open fds and run folder size over a long flight",
                        description=("Fly one fleet unpaced and sample /proc (current RSS, open fds per process by "
                                     "role) and the run folder's size; report each one's growth per simulated hour."))
    sp.add_argument("--config", default="three_link", help="scenario name or file (default three_link)")
    sp.add_argument("--duration", type=seconds, default=3600.0, help="simulated seconds (default 3600)")
    sp.add_argument("--sample-s", type=seconds, default=5.0, help="wall seconds between samples (default 5)")
    _output_args(sp, "soak")
    sp.set_defaults(func=_cmd_soak)


def _cmd_load_filter(args) -> int:
    from companion.load.estimate import LoadFilterConfig
    from sitl.scenarios.slung_load.synthetic import SlungLoadSim

    from .load_filter import format_load_filter, markdown_load_filter, plot_load_errors, run_load_filter_bench

    try:
        if args.seeds < 1:
            raise ValueError(f"--seeds must be >= 1, got {args.seeds}")
        sim = SlungLoadSim(duration_s=args.duration, latency_s=args.latency)
        cfg = LoadFilterConfig()
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run_dir = make_run_dir("load_filter", args.out)
    seeds = range(args.seed, args.seed + args.seeds)
    with tqdm(total=len(seeds), desc="load filters x seeds", unit="seed", disable=args.quiet, file=sys.stderr) as bar:
        result, first = run_load_filter_bench(seeds, sim, cfg, progress=bar.update)
    plot_load_errors(first, run_dir / "load_pose_error.png")
    _publish(args, run_dir, result, "load_filter.json", format_load_filter(result), markdown_load_filter(result),
             f" and {run_dir / 'load_pose_error.png'}", [run_dir / "load_pose_error.png"])
    return 0


def _cmd_corners(args) -> int:
    from companion.configfile import ConfigError

    from .corners import format_corners, markdown_corners, run_corners

    run_dir = make_run_dir("corners", args.out)
    try:
        with tqdm(desc="corners", unit="sim s", disable=args.quiet, file=sys.stderr) as bar:
            result = run_corners(args.config, run_dir, args.duration, args.seed, progress=bar.update)
    except (ConfigError, ValueError, RuntimeError) as exc:  # (RuntimeError: nothing renders on this machine)
        print(f"error: {exc}", file=sys.stderr)
        return 2
    _publish(args, run_dir, result, "corners.json", format_corners(result), markdown_corners(result),
             f" and the flight in {run_dir}")
    return 0


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = argv  # the report records the command as typed (report.command_line)
    args.started = time.perf_counter()
    args.load_start = load_average()
    return run_subcommand(parser, args=args)


if __name__ == "__main__":
    sys.exit(main())

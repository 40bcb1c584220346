"""Benchmarks that print figures and write JSON.

    python -m sitl.bench table2 [--json PATH] [--seed S] [--seeds N] [--duration S] [--out DIR]
    python -m sitl.bench scaling [--json PATH] [--seed S] [--out DIR]
    python -m sitl.bench zenoh [--duration S] [--groups 1,2/3,4,5/6,7] [--json PATH] [--out DIR]

Each run writes into one folder (``--out``, default ``runs/<bench>-<UTC time>``): the JSON
result (or ``--json PATH`` instead) and, for table2, the EKF stream in the
``companion replay`` input format (``ekf_stream.npz``) with the truth (``truth.npz``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from companion.estimation.sckf import CAParams
from companion.estimation.semi import parse_groups
from companion.cli import make_run_dir, run_subcommand

from .ekf_chain import ChainRun
from .scaling import LINK_COUNTS, format_scaling, run_scaling
from .table2 import GROUP_SIZES, aggregate_seeds, format_table2, run_table2
from .zenoh_rtt import format_zenoh_rtt, run_zenoh_rtt



def _write_json(result: dict, json_path: str | None, run_dir: Path, name: str) -> Path:
    path = Path(json_path) if json_path else run_dir / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    return path


def _params(args) -> CAParams | None:
    """The CA parameters from the options, or ``None`` after printing what is wrong."""
    try:
        return CAParams(eps=args.eps, alpha=args.alpha)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None


def _cmd_table2(args) -> int:
    params = _params(args)
    if params is None:
        return 2
    if args.duration <= 0 or args.seeds < 1:
        print(f"error: --duration must be positive and --seeds >= 1 (got {args.duration}, {args.seeds})", file=sys.stderr)
        return 2
    run = ChainRun(duration_s=args.duration)
    run_dir = make_run_dir("table2", args.out)
    n_ticks = int(round(run.duration_s * run.ekf_rate_hz))
    results = []
    with tqdm(
        total=n_ticks * args.seeds, desc=f"EKF x {args.seeds} seed(s)", unit="tick", disable=args.quiet, file=sys.stderr
    ) as bar:
        for seed in range(args.seed, args.seed + args.seeds):
            result, stream = run_table2(seed, run, GROUP_SIZES, params, progress=bar.update)
            results.append(result)
            if seed == args.seed:
                np.savez_compressed(run_dir / "ekf_stream.npz", **stream.replay_arrays())
                np.savez_compressed(
                    run_dir / "truth.npz", t=stream.t, p=stream.p_true, v=stream.v_true, q=stream.q_true
                )
    result = aggregate_seeds(results)
    path = _write_json(result, args.json, run_dir, "table2.json")
    print(format_table2(result))
    print(f"\nwrote {path} and {run_dir / 'ekf_stream.npz'} (replay input, seed {args.seed})")
    return 0


def _cmd_scaling(args) -> int:
    params = _params(args)
    if params is None:
        return 2
    run_dir = make_run_dir("scaling", args.out)
    with tqdm(total=len(LINK_COUNTS), desc="chain lengths", unit="n", disable=args.quiet, file=sys.stderr) as bar:
        result = run_scaling(args.seed, LINK_COUNTS, params=params, progress=bar.update)
    path = _write_json(result, args.json, run_dir, "scaling.json")
    print(format_scaling(result))
    print(f"\nwrote {path}")
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
    path = _write_json(result, args.json, run_dir, "zenoh.json")
    print(format_zenoh_rtt(result))
    print(f"\nwrote {path}")
    return 0


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
    t2.add_argument("--duration", type=float, default=ChainRun.duration_s, help="simulated seconds (default 20)")
    t2.add_argument(
        "--seeds",
        type=int,
        default=5,
        metavar="N",
        help="repeat with seeds S..S+N-1 and report mean +- std and the noise check (default 5)",
    )
    t2.set_defaults(func=_cmd_table2)
    sc = sub.add_parser(
        "scaling",
        parents=[common],
        help="per-step time of full and semi-distributed SCKF for n = 3..96",
        description="Per-step time of Alg. 1 (full chain) and Alg. 2 + eq. 6 (groups of 2) vs. chain length.",
    )
    sc.set_defaults(func=_cmd_scaling)
    zb = sub.add_parser(
        "zenoh",
        parents=[common],
        help="global step over Zenoh on loopback: round trip printed by the leader",
        description=("One process and Zenoh peer session per group on 127.0.0.1; every 50 ms each publishes its "
                     "boundary, the leader solves eq. 6 and publishes the shifts. Prints the round trip "
                     "(boundary published -> shift received) the groups report to the leader."),
    )
    zb.add_argument("--duration", type=float, default=20.0, help="seconds of cycles (default 20)")
    zb.add_argument("--groups", default="1,2/3,4,5/6,7", metavar="LAYOUT",
                    help="group layout, 1-based links (default 1,2/3,4,5/6,7: the thesis's seven links)")
    zb.add_argument("--base-port", type=int, default=17447, help="group g listens on TCP base+g-1 (default 17447)")
    zb.set_defaults(func=_cmd_zenoh)
    return parser


def main(argv=None) -> int:
    return run_subcommand(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

"""Motion-generation tools.

    python -m companion.motion dataset [--samples N] [--seed S] [--links N] [--out DIR]

``dataset`` simulates ``N`` seeded CPG parameter sets ``eta = [A_x, A_y, B_x, B_y]`` in the
expected physics (thesis sec. 4.4) to their steady body motion ``xi = [v; omega; theta]``
(sec. 4.5.1) and writes ``cpg_dataset.npz`` (``eta``, ``xi``, names, the settings) to the run
folder. The same seed gives the same file.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict

import numpy as np
from tqdm import tqdm

from companion.runtime import make_run_dir, run_subcommand

from .steady import ETA_NAMES, XI_NAMES, SteadyConfig, sample_parameters, steady_motion


def _cmd_dataset(args) -> int:
    try:
        cfg = SteadyConfig(n_links=args.links, settle_s=args.settle, periods=args.periods)
        eta = sample_parameters(args.samples, np.random.default_rng(args.seed), args.a_max, args.b_max)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = make_run_dir("cpg-dataset", args.out)
    period_s = 1.0 / cfg.cpg_params.frequency_hz
    total = cfg.settle_s + cfg.periods * period_s
    with tqdm(total=round(total, 2), desc=f"{args.samples} parameter sets", unit="sim s", disable=args.quiet,
              file=sys.stderr) as bar:
        xi = steady_motion(eta, cfg, progress=bar.update)
    settings = {"seed": args.seed, "a_max": args.a_max, "b_max": args.b_max, **{k: v for k, v in asdict(cfg).items()
                                                                                if k not in ("cpg", "water")},
                "water": asdict(cfg.water), "cpg": asdict(cfg.cpg_params)}
    path = out / "cpg_dataset.npz"
    np.savez_compressed(path, eta=eta, xi=xi, eta_names=np.array(ETA_NAMES), xi_names=np.array(XI_NAMES),
                        settings=json.dumps(settings))
    speed = -xi[:, 0]
    print(f"{args.samples} sets: forward speed {speed.min():.3f}..{speed.max():.3f} m/s, "
          f"yaw rate {xi[:, 5].min():.3f}..{xi[:, 5].max():.3f} rad/s; wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m companion.motion", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    ds = sub.add_parser("dataset", help="steady body motion of seeded CPG parameter sets (inverse-model data)",
                        description="Simulate seeded CPG parameter sets in the expected physics to their steady motion.")
    ds.add_argument("--samples", type=int, default=400, help="parameter sets (default 400)")
    ds.add_argument("--seed", type=int, default=0, help="seed of the parameter draw (default 0)")
    ds.add_argument("--links", type=int, default=7, help="links of the chain (default 7)")
    ds.add_argument("--a-max", type=float, default=0.6, help="largest amplitude A_x, A_y [rad] (default 0.6)")
    ds.add_argument("--b-max", type=float, default=0.3, help="largest bias B_x, B_y [rad] (default 0.3)")
    ds.add_argument("--settle", type=float, default=30.0, help="seconds simulated before averaging (default 30)")
    ds.add_argument("--periods", type=int, default=4, help="undulation periods averaged (default 4)")
    ds.add_argument("--out", metavar="DIR", help="run folder (default runs/cpg-dataset-<UTC time>)")
    ds.add_argument("--quiet", action="store_true", help="no progress bar")
    ds.set_defaults(func=_cmd_dataset)
    return parser


def main(argv=None) -> int:
    return run_subcommand(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

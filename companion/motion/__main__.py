"""Motion-generation tools.

    python -m companion.motion dataset [--samples N] [--seed S] [--links N] [--out DIR]
    python -m companion.motion train --dataset FILE [--seed S] [--holdout F] [--model FILE] [--out DIR]

``dataset`` simulates ``N`` seeded CPG parameter sets ``eta = [A_x, A_y, B_x, B_y]`` in the
expected physics (thesis sec. 4.4) to their steady body motion ``xi = [v; omega; theta]``
(sec. 4.5.1) and writes ``cpg_dataset.npz`` (``eta``, ``xi``, names, the settings) to the run
folder. The same seed gives the same file. ``train`` fits the inverse model (autoencoder with a
4-d hidden layer, tanh MLP to the parameters; thesis sec. 4.5.1) on a dataset, reports the
recovery error on the held-out part (the thesis's Fig. 4-8 check) and writes the model file
(versioned; it records the command that made it).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from companion.cli import make_run_dir, progress_bar, run_subcommand
from companion.configfile import ConfigError, build

from .cpg import CpgParams
from .inverse import train_inverse_model
from .steady import ETA_NAMES, XI_NAMES, SteadyConfig, sample_parameters, steady_motion


def _cmd_dataset(args) -> int:
    try:
        cpg = CpgParams(args.links, frequency_hz=args.frequency)
        cfg = SteadyConfig(n_links=args.links, settle_s=args.settle, periods=args.periods, cpg=cpg)
        eta = sample_parameters(args.samples, np.random.default_rng(args.seed), args.a_max, args.b_max)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = make_run_dir("cpg-dataset", args.out)
    period_s = 1.0 / cfg.cpg_params.frequency_hz
    total = cfg.settle_s + cfg.periods * period_s
    with progress_bar(total=round(total, 2), desc=f"{args.samples} parameter sets", unit="sim s",
                      disable=args.quiet) as bar:
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


def _cmd_train(args) -> int:
    try:
        data = np.load(args.dataset)
        eta, xi = data["eta"], data["xi"]
        settings = json.loads(str(data["settings"]))
        steady = build(SteadyConfig, {k: settings[k] for k in settings if k in SteadyConfig.__dataclass_fields__},
                       file=str(args.dataset), prefix="settings")
    except (OSError, KeyError, ValueError) as exc:  # ConfigError is a ValueError
        reason = exc if isinstance(exc, ConfigError) else f"not a cpg_dataset.npz ({exc})"
        print(f"error: {args.dataset}: {reason}", file=sys.stderr)
        return 2
    if not 0.0 <= args.holdout < 0.9 or len(eta) < 20:
        print("error: --holdout must be in [0, 0.9) and the dataset needs at least 20 samples", file=sys.stderr)
        return 2
    n_train = len(eta) - int(round(args.holdout * len(eta)))
    model = train_inverse_model(eta[:n_train], xi[:n_train], seed=args.seed, steady=steady)
    out = make_run_dir("cpg-inverse", args.out)
    path = Path(args.model) if args.model else out / "inverse_model.npz"
    report = {"dataset": str(args.dataset), "train": n_train, "holdout": len(eta) - n_train, **model.info}
    if n_train < len(eta):
        recovered = model(xi[n_train:])
        span = eta.max(axis=0) - eta.min(axis=0)
        err = np.abs(recovered - eta[n_train:]).mean(axis=0)
        report["holdout_mean_abs_error"] = dict(zip(ETA_NAMES, err.round(5).tolist()))
        report["holdout_error_of_range"] = dict(zip(ETA_NAMES, (err / span).round(4).tolist()))
    report["command"] = ("python -m companion.motion train --dataset " + str(args.dataset) + f" --seed {args.seed}"
                         + f" --holdout {args.holdout}")
    model = replace(model, info={**model.info, **report})
    model.save(path)
    (out / "inverse_model.json").write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    print(f"wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m companion.motion", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    ds = sub.add_parser("dataset", help="steady body motion of seeded CPG parameter sets (inverse-model data)",
                        description="Simulate seeded CPG parameter sets in the expected physics to their steady motion.")
    ds.add_argument("--samples", type=int, default=400, help="parameter sets (default 400)")
    ds.add_argument("--seed", type=int, default=0, help="seed of the parameter draw (default 0)")
    ds.add_argument("--links", type=int, default=7, help="links of the chain (default 7)")
    ds.add_argument("--frequency", type=float, default=CpgParams(2).frequency_hz,
                    help=f"undulation frequency [Hz] (default {CpgParams(2).frequency_hz:g})")
    ds.add_argument("--a-max", type=float, default=0.6, help="largest amplitude A_x, A_y [rad] (default 0.6)")
    ds.add_argument("--b-max", type=float, default=0.3, help="largest bias B_x, B_y [rad] (default 0.3)")
    ds.add_argument("--settle", type=float, default=30.0, help="seconds simulated before averaging (default 30)")
    ds.add_argument("--periods", type=int, default=4, help="undulation periods averaged (default 4)")
    ds.add_argument("--out", metavar="DIR", help="run folder (default runs/cpg-dataset-<UTC time>)")
    ds.add_argument("--quiet", action="store_true", help="no progress bar")
    ds.set_defaults(func=_cmd_dataset)
    tr = sub.add_parser("train", help="fit the inverse CPG model (autoencoder + tanh MLP) on a dataset",
                        description="Fit the inverse model on cpg_dataset.npz and report the held-out recovery error.")
    tr.add_argument("--dataset", required=True, metavar="FILE", help="cpg_dataset.npz from the dataset command")
    tr.add_argument("--seed", type=int, default=0, help="seed of the initial weights (default 0)")
    tr.add_argument("--holdout", type=float, default=0.2, help="fraction kept out of training (default 0.2)")
    tr.add_argument("--model", metavar="FILE", help="where to write the model (default: the run folder)")
    tr.add_argument("--out", metavar="DIR", help="run folder (default runs/cpg-inverse-<UTC time>)")
    tr.set_defaults(func=_cmd_train)
    return parser


def main(argv=None) -> int:
    return run_subcommand(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

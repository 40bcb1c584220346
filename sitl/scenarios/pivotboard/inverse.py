"""The pivotboard's inverse CPG model (thesis sec. 4.5.3, Fig. 4-7 B): its second step, from the
decaying-acceleration parameters ``xi = [v_s, d, c]`` (eq. 4.2) to the CPG's inputs
``eta = [A, B]``; one model per branch of the CPG (speeding up: the map's phase difference;
slowing down: zero phase difference). The first step, from a desired motion to ``xi``, is the
line search :func:`~companion.motion.decaying_acceleration.feasible_da` on these models.

The data: runs of the scenario's board with ``(A, B)`` drawn uniformly from the given ranges
(seeded); each run speeds up from rest for ``duration`` seconds, then slows down as long
(:func:`~.da_fit.fit_runs`), and each half's eq. 4.2 fit is one sample of its branch. The board is
symmetric: every run with bias ``B`` also gives the mirrored sample ``(A, -B) -> (v_s, d, -c)``.

The model: :func:`companion.motion.inverse.train_inverse_model`, the LASDRA and snake model's,
with a 2-d bottleneck (``R^3 -> R^2 -> R^3``: the feasible set of Fig. 4-11 is the decoder's
surface; the file's ``info`` keeps the training range of ``xi``, ``xi_low`` and ``xi_high``).
Held-out runs measure how well it recovers the inputs from the parameters they made. Each
model file records the data's seed, ranges, sample counts, the commit, the fits' residuals and the
held-out error (its ``info``).

Command line (writes ``OUT/inverse_accelerating.npz`` and ``OUT/inverse_decelerating.npz``)::

    python -m sitl.scenarios.pivotboard.inverse --config configs/sitl/ground/pivotboard.toml \\
        --samples 80 --held-out 20 --seed 0 --workers 2 --out sitl/scenarios/pivotboard/models
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

import numpy as np

from companion.motion.inverse import train_inverse_model

from ..ground.sweep import (commit, inverse_options, parse_inverse, recovery_error_deg, run_jobs, sweep_parser,
                           train_held)
from .config import BRANCHES, PivotScenario, model_path

__all__ = ["dataset", "build_parser", "main"]


def _fits(args):
    from .da_fit import fit_runs

    return fit_runs(*args)


def dataset(sc: PivotScenario, n: int, seed: int, A_range_deg, B_max_deg: float, duration_s: float, workers: int = 1,
            scheduler: str | None = None):
    """``(eta [rad] (2n, 2), {branch: xi (2n, 3)}, {branch: residual RMS [m/s] (n,)})`` of ``n`` runs
    with ``A`` uniform in ``A_range_deg`` and ``B`` in ``[0, B_max_deg]`` (seeded), each with its
    mirror image (after the ``n`` runs, in the same order)."""
    rng = np.random.default_rng(seed)
    A = rng.uniform(*A_range_deg, n)
    B = rng.uniform(0.0, B_max_deg, n)
    fits = run_jobs(_fits, [(sc, a, b, duration_s) for a, b in zip(A, B)], workers, scheduler)
    eta = np.radians(np.column_stack((A, B)))
    xi, residual = {}, {}
    for k, branch in enumerate(BRANCHES):
        x = np.array([[f[k].model.v_s_m_s, f[k].model.d_per_s, f[k].model.c_rad_per_m] for f in fits])
        xi[branch] = np.vstack((x, x * [1.0, 1.0, -1.0]))
        residual[branch] = np.array([f[k].v_rms_m_s for f in fits])
    return np.vstack((eta, eta * [1.0, -1.0])), xi, residual


def build_parser() -> argparse.ArgumentParser:
    p = sweep_parser("python -m sitl.scenarios.pivotboard.inverse", __doc__, "pivotboard",
                     "the folder the two model files go to", 12.0)
    inverse_options(p, 80, 20, "2,40", 30.0)
    return p


def main(argv=None) -> int:
    parsed = parse_inverse(build_parser(), argv, "pivotboard")
    if parsed is None:
        return 2
    args, sc, A_range = parsed
    N = args.samples + args.held_out
    eta, xi, residual = dataset(sc, N, args.seed, A_range, args.B_max, args.duration, args.workers,
                                     args.scheduler)
    train, held = train_held(args.samples, args.held_out)
    args.out.mkdir(parents=True, exist_ok=True)
    for branch in BRANCHES:
        x = xi[branch]
        model = train_inverse_model(eta[train], x[train], seed=args.seed, hidden=16, steady=None, bottleneck=2, info={
            "robot": "pivotboard", "branch": branch, "scenario": str(args.config), "commit": commit(),
            "A_range_deg": A_range, "B_max_deg": args.B_max, "duration_s": args.duration, "data_seed": args.seed,
            "da_fit_rms_m_s": {"median": float(np.median(residual[branch])), "max": float(residual[branch].max())},
            "xi_low": [float(v) for v in x[train].min(axis=0)], "xi_high": [float(v) for v in x[train].max(axis=0)]})
        err = recovery_error_deg(model, eta[held], x[held])
        recon = ((model.decode(model.encode(x[held])) - x[held]) / model.xi_std)
        model = replace(model, info={**model.info, "held_out_samples": int(len(held)),
                                     "held_out_eta_rms_deg": [float(e) for e in err],
                                     "held_out_xi_reconstruction_rms_std": float(np.sqrt(np.mean(recon ** 2)))})
        path = model_path(args.out, branch)
        model.save(path)
        print(f"{branch}: {len(train)} training samples, {len(held)} held out (seed {args.seed}); eq. 4.2 fit residual "
              f"median {np.median(residual[branch]) * 1e3:.2f} mm/s (max {residual[branch].max() * 1e3:.2f}); "
              f"v_s {x[:, 0].min():.4f}..{x[:, 0].max():.4f} m/s, d {x[:, 1].min():.3f}..{x[:, 1].max():.3f} /s, "
              f"c {x[:, 2].min():.3f}..{x[:, 2].max():.3f} rad/m; recovered inputs RMS: A {err[0]:.2f} deg, "
              f"B {err[1]:.2f} deg; wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The snake's inverse CPG model (thesis sec. 4.5.2): from a desired body velocity
``xi = [v_x, v_y, omega]`` (in {B}) to the CPG's inputs ``eta = [A, B]``.

The data: runs of the scenario's robot from rest with ``(A, B)`` drawn uniformly from the given
ranges (seeded), each one's steady motion (:func:`~.flight.steady_motion`: the period velocities'
means after ``settle_s``). The thesis learns from positive biases only "thanks to the symmetry":
here every run with bias ``B`` also gives the mirrored sample ``(A, -B) -> (v_x, -v_y, -omega)``.

The model: :func:`companion.motion.inverse.train_inverse_model`, the LASDRA model's, with a
2-d bottleneck: the stacked autoencoder (``R^3 -> R^2 -> R^3``) that projects a desired velocity
onto the velocities the robot can make, and the tanh MLP from its hidden layer to ``eta``. Held-out
runs measure how well it recovers the inputs from the velocities they made (the thesis's Fig. 4-9,
right). The model file records the data's seed, ranges, sample counts, the commit and the held-out
error (its ``info``).

Command line::

    python -m sitl.scenarios.snake.inverse --config configs/sitl/ground/snake.toml --samples 120 \\
        --held-out 30 --seed 0 --workers 2 --out sitl/scenarios/snake/models/inverse.npz
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

import numpy as np

from companion.motion.inverse import train_inverse_model

from ..ground.sweep import (commit, inverse_options, parse_inverse, recovery_error_deg, run_jobs, sweep_parser,
                           train_held)
from .config import SnakeScenario

__all__ = ["dataset", "build_parser", "main"]


def _motion(args) -> np.ndarray:
    from .flight import steady_motion

    return steady_motion(*args)


def dataset(sc: SnakeScenario, n: int, seed: int, A_range_deg, B_max_deg: float, workers: int = 1,
            scheduler: str | None = None):
    """``(eta [rad], xi)`` of ``n`` runs with ``A`` uniform in ``A_range_deg`` and ``B`` in
    ``[0, B_max_deg]`` (seeded), and their mirror images: (2n, 2), (2n, 3)."""
    rng = np.random.default_rng(seed)
    A = rng.uniform(*A_range_deg, n)
    B = rng.uniform(0.0, B_max_deg, n)
    xi = np.asarray(run_jobs(_motion, [(sc, a, b) for a, b in zip(A, B)], workers, scheduler))
    eta = np.radians(np.column_stack((A, B)))
    return np.vstack((eta, eta * [1.0, -1.0])), np.vstack((xi, xi * [1.0, -1.0, -1.0]))


def build_parser() -> argparse.ArgumentParser:
    p = sweep_parser("python -m sitl.scenarios.snake.inverse", __doc__, "snake", "the model file (.npz)", 8.0)
    inverse_options(p, 120, 30, "20,40", 8.0)
    return p


def main(argv=None) -> int:
    parsed = parse_inverse(build_parser(), argv, "snake")
    if parsed is None:
        return 2
    args, sc, A_range = parsed
    N = args.samples + args.held_out
    eta, xi = dataset(sc, N, args.seed, A_range, args.B_max, args.workers, args.scheduler)
    train, held = train_held(args.samples, args.held_out)
    train_eta, train_xi = eta[train], xi[train]
    model = train_inverse_model(train_eta, train_xi, seed=args.seed, hidden=16, steady=None, bottleneck=2, info={
        "robot": "snake", "scenario": str(args.config), "commit": commit(), "A_range_deg": A_range,
        "B_max_deg": args.B_max, "duration_s": args.duration, "data_seed": args.seed})
    err = recovery_error_deg(model, eta[held], xi[held])
    recon = float(np.sqrt(np.mean((model.decode(model.encode(xi[held])) - xi[held]) ** 2)))
    model = replace(model, info={**model.info, "held_out_samples": int(len(held)),
                                 "held_out_eta_rms_deg": [float(e) for e in err], "held_out_xi_reconstruction_rms": recon})
    model.save(args.out)
    print(f"{len(train_eta)} training samples, {len(held)} held out (seed {args.seed}); autoencoder reconstruction "
          f"RMS {recon:.4f} (held out, m/s and rad/s); recovered inputs RMS: A {err[0]:.2f} deg, B {err[1]:.2f} deg")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

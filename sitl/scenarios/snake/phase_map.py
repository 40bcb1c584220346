"""Eq. 4.1 for the snake: the phase difference between the vertical and the horizontal
oscillators that maximises the forward speed, as a map of the CPG's inputs.

    phi_hv(A, B) := argmax_{phi_hv} v_x(A, B, phi_hv)                                      (4.1)

As the thesis does (sec. 4.3.2), ``phi_hv`` is made an input for the sweep: every ``(A, B,
phi_hv)`` of a grid flies the scenario's robot with that command held (:func:`sweep`), ``v_x`` is
its forward speed in {B} averaged over whole CPG periods after ``settle_s``. Per ``(A, B)``, the
argmax over the ``phi_hv`` grid is refined by a parabola through it and its two neighbours (the
grid wraps at 2 pi) (:func:`best_phases`); the map is a
:class:`~companion.motion.oscillators.PhaseMap` on the ``(A, B)`` grid, its values unwrapped along
the grid so that its linear interpolation does not cross a 2 pi jump.

Command line (writes ``OUT``: the ``[phase_hv]`` table a scenario's ``phase_map_file`` names, with
the sweep's grid, settings and speeds in its header)::

    python -m sitl.scenarios.snake.phase_map --config configs/sitl/ground/snake.toml \\
        --A 20,30,40 --B 0,4,8 --phases 12 --duration 8 --workers 2 \\
        --out sitl/scenarios/snake/models/phase_hv.toml
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from companion.motion.oscillators import PhaseMap

from ..ground.sweep import commit, floats, parse_sweep, run_jobs, sweep_parser
from .config import SnakeScenario

__all__ = ["forward_speed", "sweep", "best_phases", "phase_map", "build_parser", "main"]


def forward_speed(sc: SnakeScenario, A_deg: float, B_deg: float, phi_hv_rad: float) -> float:
    """The mean forward speed ``v_x`` [m/s] of the robot with ``(A, B)`` held and ``phi_hv`` fixed,
    over the scenario's duration after ``settle_s`` (``nan`` if the window is empty)."""
    from .flight import steady_motion

    return float(steady_motion(sc, A_deg, B_deg, PhaseMap.constant(phi_hv_rad, 2))[0])


def _speed(args) -> float:
    return forward_speed(*args)


def sweep(sc: SnakeScenario, A_deg, B_deg, phi_rad, workers: int = 1) -> np.ndarray:
    """``v_x`` on the grid ``(len(A), len(B), len(phi))``; ``workers`` processes fly it."""
    jobs = [(sc, a, b, p) for a in A_deg for b in B_deg for p in phi_rad]
    return np.asarray(run_jobs(_speed, jobs, workers)).reshape(len(A_deg), len(B_deg), len(phi_rad))


def best_phases(v: np.ndarray, phi_rad: np.ndarray) -> np.ndarray:
    """Per row of ``v`` (..., len(phi)), the maximising phase: the grid's argmax refined by a
    parabola through it and its neighbours (``phi_rad``: an even grid over 2 pi, wrapping)."""
    k = np.nanargmax(v, axis=-1)
    n = v.shape[-1]
    step = 2.0 * math.pi / n
    left = np.take_along_axis(v, ((k - 1) % n)[..., None], -1)[..., 0]
    mid = np.take_along_axis(v, k[..., None], -1)[..., 0]
    right = np.take_along_axis(v, ((k + 1) % n)[..., None], -1)[..., 0]
    den = left - 2.0 * mid + right
    shift = np.where(den < 0, 0.5 * (left - right) / np.where(den < 0, den, 1.0), 0.0)
    return phi_rad[k] + np.clip(shift, -0.5, 0.5) * step


def phase_map(A_deg, B_deg, best_rad: np.ndarray) -> PhaseMap:
    """The map of the best phases on the ``(A, B)`` grid [rad], unwrapped along both axes."""
    values = np.unwrap(np.unwrap(best_rad, axis=0), axis=1)
    return PhaseMap((tuple(math.radians(a) for a in A_deg), tuple(math.radians(b) for b in B_deg)),
                    tuple(float(x) for x in values.ravel()))


def build_parser() -> argparse.ArgumentParser:
    p = sweep_parser("python -m sitl.scenarios.snake.phase_map", __doc__, "snake", "the map's TOML file", 8.0)
    p.add_argument("--A", default="15,30,45", help="amplitudes [deg], comma-separated")
    p.add_argument("--B", default="0,5,10", help="biases [deg], comma-separated")
    p.add_argument("--phases", type=int, default=12, help="phi_hv grid points over 2 pi")
    return p


def main(argv=None) -> int:
    args, sc = parse_sweep(build_parser(), argv, "snake")
    if sc is None:
        return 2
    A, B = floats(args.A), floats(args.B)
    phi = np.arange(args.phases) * 2.0 * math.pi / args.phases - math.pi
    v = sweep(sc, A, B, phi, args.workers)
    best = best_phases(v, phi)
    m = phase_map(A, B, best)
    header = [f"# eq. 4.1 for {sc.name}: phi_hv(A, B) maximising v_x; python -m sitl.scenarios.snake.phase_map",
              f"# --config {args.config} --A {args.A} --B {args.B} --phases {args.phases} --duration {args.duration}",
              f"# at commit {commit()} (the flights are deterministic: no seed)",
              f"# phi_hv grid [rad]: {', '.join(f'{x:.4f}' for x in phi)}"]
    for i, a in enumerate(A):
        for j, b in enumerate(B):
            header.append(f"# A = {a:g} deg, B = {b:g} deg: v_x [m/s] = {', '.join(f'{x:.4f}' for x in v[i, j])}; "
                          f"best {best[i, j]:.4f} rad")
    body = ["[phase_hv]", f"axes = [{', '.join('[' + ', '.join(f'{x:.9g}' for x in ax) + ']' for ax in m.axes)}]",
            f"values = [{', '.join(f'{x:.9g}' for x in m.values)}]"]
    args.out.write_text("\n".join(header + body) + "\n")
    print("\n".join(header))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

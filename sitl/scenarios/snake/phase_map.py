"""Eq. 4.1 for the snake: the phase difference between the vertical and the horizontal
oscillators that maximises the forward speed, as a map of the CPG's inputs.

    phi_hv(A, B) := argmax_{phi_hv} v_x(A, B, phi_hv)                                      (4.1)

As the thesis does (sec. 4.3.2), ``phi_hv`` is made an input for the sweep: every ``(A, B,
phi_hv)`` of a grid flies the scenario's robot with that command held (:func:`sweep`), ``v_x`` is
its forward speed in {B} averaged over whole CPG periods after ``settle_s``. The argmax and the
map on the ``(A, B)`` grid [rad]: :mod:`sitl.scenarios.ground.phase_sweep`.

Command line (writes ``OUT``: the ``[phase_hv]`` table a scenario's ``phase_map_file`` names, with
the sweep's grid, settings and speeds in its header)::

    python -m sitl.scenarios.snake.phase_map --config configs/sitl/ground/snake.toml \\
        --A 20,30,40 --B 0,4,8 --phases 12 --duration 8 --workers 2 \\
        --out sitl/scenarios/snake/models/phase_hv.toml
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from companion.motion.oscillators import PhaseMap

from ..ground.phase_sweep import grid_speeds, run_sweep
from ..ground.sweep import parse_sweep, sweep_parser
from .config import SnakeScenario

__all__ = ["forward_speed", "sweep", "build_parser", "main"]


def forward_speed(sc: SnakeScenario, A_deg: float, B_deg: float, phi_hv_rad: float) -> float:
    """The mean forward speed ``v_x`` [m/s] of the robot with ``(A, B)`` held and ``phi_hv`` fixed,
    over the scenario's duration after ``settle_s`` (``nan`` if the window is empty)."""
    from .flight import steady_motion

    return float(steady_motion(sc, A_deg, B_deg, PhaseMap.constant(phi_hv_rad, 2))[0])


def _speed(args) -> float:
    return forward_speed(*args)


def sweep(sc: SnakeScenario, A_deg, B_deg, phi_rad, workers: int = 1, scheduler: str | None = None) -> np.ndarray:
    """``v_x`` on the grid ``(len(A), len(B), len(phi))`` (:func:`~sitl.scenarios.ground.phase_sweep.grid_speeds`)."""
    return grid_speeds(_speed, sc, A_deg, B_deg, phi_rad, workers, scheduler)


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
    return run_sweep(args, sc, sweep, "phase_hv",
                      f"eq. 4.1 for {sc.name}: phi_hv(A, B) maximising v_x; "
                      "python -m sitl.scenarios.snake.phase_map")


if __name__ == "__main__":
    sys.exit(main())

"""Eq. 4.1 for the pivotboard (thesis sec. 4.3.3, Fig. 4-6 right): the plates' phase difference
that maximises the forward speed while speeding up, ``phi(A, B, v_dot_d)`` for ``v_dot_d >= 0``.

The phase difference is made an input for the sweep: every ``(A, B, phi)`` of a grid starts the
scenario's board at rest with that command held for ``duration`` seconds (:func:`sweep`); its speed
is ``v_x`` in {B} averaged over the run's last three CPG periods (the board's speed converges as
eq. 4.2 says; by then it has). The argmax and the map: :mod:`sitl.scenarios.ground.phase_sweep`.
The sweep holds ``v_dot_d`` positive, which only selects the accelerating branch: the map's
``v_dot_d`` axis is the one point 0 (constant along it), and ``v_dot_d < 0`` takes the CPG's zero
phase difference whatever the map says.

Command line (writes ``OUT``: the ``[phase]`` table a scenario's ``phase_map_file`` names, with the
sweep's grid, settings and speeds in its header)::

    python -m sitl.scenarios.pivotboard.phase_map --config configs/sitl/ground/pivotboard.toml \\
        --A 10,25,40 --B 0,15,30 --phases 12 --duration 12 --workers 2 \\
        --out sitl/scenarios/pivotboard/models/phase.toml
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

import numpy as np

from companion.motion.oscillators import PhaseMap

from ..ground.phase_sweep import grid_speeds, run_sweep
from ..ground.sweep import parse_sweep, sweep_parser
from .config import PivotCommand, PivotScenario

__all__ = ["final_speed", "sweep", "build_parser", "main"]

#: the CPG periods at the run's end its speed is averaged over
FINAL_PERIODS = 3


def final_speed(sc: PivotScenario, A_deg: float, B_deg: float, phi_rad: float) -> float:
    """The board's forward speed ``v_x`` [m/s] at the end of a run from rest with ``(A, B)`` held
    and the phase difference fixed at ``phi_rad`` (module docstring)."""
    from .flight import pivot_run

    cpg = replace(sc.cpg, phase=PhaseMap.constant(phi_rad, 3))
    run = pivot_run(replace(sc, cpg=cpg, commands=(PivotCommand(0.0, A_deg, B_deg, 1.0),)))
    run.run()
    a = run.arrays()
    w = a["period_t"] >= a["period_t"][-1] - FINAL_PERIODS * run.cpg.period_s + 1e-9
    return float(a["v_x"][w].mean())


def _speed(args) -> float:
    return final_speed(*args)


def sweep(sc: PivotScenario, A_deg, B_deg, phi_rad, workers: int = 1, scheduler: str | None = None) -> np.ndarray:
    """``v_x`` on the grid ``(len(A), len(B), len(phi))`` (:func:`~sitl.scenarios.ground.phase_sweep.grid_speeds`)."""
    return grid_speeds(_speed, sc, A_deg, B_deg, phi_rad, workers, scheduler)


def build_parser() -> argparse.ArgumentParser:
    p = sweep_parser("python -m sitl.scenarios.pivotboard.phase_map", __doc__, "pivotboard", "the map's TOML file",
                     12.0)
    p.add_argument("--A", default="10,25,40", help="amplitudes [deg], comma-separated")
    p.add_argument("--B", default="0,15,30", help="biases [deg], comma-separated")
    p.add_argument("--phases", type=int, default=12, help="phase grid points over 2 pi")
    return p


def main(argv=None) -> int:
    args, sc = parse_sweep(build_parser(), argv, "pivotboard")
    if sc is None:
        return 2
    return run_sweep(args, sc, sweep, "phase",
                      f"eq. 4.1 for {sc.name}: phi(A, B, v_dot_d >= 0) maximising v_x; "
                      "python -m sitl.scenarios.pivotboard.phase_map", extra_axes=((0.0,),))


if __name__ == "__main__":
    sys.exit(main())

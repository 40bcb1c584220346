"""The pivotboard's decaying-acceleration model (eq. 4.2) fitted on runs of the board, over a grid of
the CPG's inputs: the data its inverse model learns from (thesis sec. 4.5.3, Fig. 4-10).

For every ``(A, B)`` of the grid the board starts at rest and speeds up with the input held (the
scenario's phase map, ``v_dot_d > 0``) for ``duration`` seconds, then slows down (zero phase
difference) as long again. Each half's period-averaged ``v_x`` and ``omega`` (from one period
after its start) is fitted with :func:`~companion.motion.decaying_acceleration.fit_decaying_acceleration`:
``v_s``, ``d``, ``c`` and the residuals' RMS.

Command line (writes ``OUT``: a TOML table per grid point, ``[[accelerating]]`` and
``[[decelerating]]``, with the settings in its header)::

    python -m sitl.scenarios.pivotboard.da_fit --config configs/sitl/ground/pivotboard.toml \\
        --A 20,30,40 --B 0,5,10 --duration 12 --workers 2 --out sitl/scenarios/pivotboard/models/da_fits.toml
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from companion.motion.decaying_acceleration import DAFit, fit_decaying_acceleration

from ..ground.sweep import commit, floats, parse_sweep, run_jobs, sweep_parser
from .config import PivotCommand, PivotScenario

__all__ = ["fit_runs", "build_parser", "main"]


def fit_runs(sc: PivotScenario, A_deg: float, B_deg: float, duration_s: float) -> tuple[DAFit, DAFit]:
    """The accelerating and the decelerating half's fits of one ``(A, B)`` (module docstring)."""
    from .flight import pivot_run

    sc = replace(sc, duration_s=2.0 * duration_s, commands=(PivotCommand(0.0, A_deg, B_deg, 1.0),
                                                            PivotCommand(duration_s, A_deg, B_deg, -1.0)))
    run = pivot_run(sc)
    run.run()
    a = run.arrays()
    period = run.cpg.period_s
    out = []
    for t0, t1 in ((period, duration_s), (duration_s + period, 2.0 * duration_s)):
        w = (a["period_t"] >= t0 - 1e-9) & (a["period_t"] <= t1 + 1e-9)
        out.append(fit_decaying_acceleration(a["period_t"][w], a["v_x"][w], a["omega"][w]))
    return out[0], out[1]


def _job(args):
    return fit_runs(*args)


def build_parser() -> argparse.ArgumentParser:
    p = sweep_parser("python -m sitl.scenarios.pivotboard.da_fit", __doc__, "pivotboard", "the fits' TOML file", 12.0)
    p.add_argument("--A", default="20,30,40", help="amplitudes [deg], comma-separated")
    p.add_argument("--B", default="0,5,10", help="biases [deg], comma-separated")
    return p


def _row(A: float, B: float, f: DAFit) -> list[str]:
    m = f.model
    return [f"A_deg = {A:g}", f"B_deg = {B:g}", f"v_s_m_s = {m.v_s_m_s:.6g}", f"d_per_s = {m.d_per_s:.6g}",
            f"c_rad_per_m = {m.c_rad_per_m:.6g}", f"v0_m_s = {f.v0_m_s:.6g}", f"v_rms_m_s = {f.v_rms_m_s:.6g}",
            f"omega_rms_rad_s = {f.omega_rms_rad_s:.6g}"]


def main(argv=None) -> int:
    args, sc = parse_sweep(build_parser(), argv, "pivotboard")
    if sc is None:
        return 2
    jobs = [(sc, a, b, args.duration) for a in floats(args.A) for b in floats(args.B)]
    fits = run_jobs(_job, jobs, args.workers, args.scheduler)
    lines = [f"# eq. 4.2 fitted on {sc.name}: python -m sitl.scenarios.pivotboard.da_fit --config {args.config} "
             f"--A {args.A} --B {args.B} --duration {args.duration}",
             f"# at commit {commit()} (the runs are deterministic: no seed)"]
    for half, k in (("accelerating", 0), ("decelerating", 1)):
        for (_, a, b, _), pair in zip(jobs, fits):
            lines += ["", f"[[{half}]]", *_row(a, b, pair[k])]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"{'A':>4} {'B':>4} | {'v_s':>7} {'d':>6} {'c':>7} {'v rms':>7} {'w rms':>7} | decelerating: {'v_s':>7} {'d':>6} {'v rms':>7}")
    for (_, a, b, _), (up, down) in zip(jobs, fits):
        print(f"{a:4g} {b:4g} | {up.model.v_s_m_s:7.4f} {up.model.d_per_s:6.3f} {up.model.c_rad_per_m:7.4f} "
              f"{up.v_rms_m_s:7.4f} {up.omega_rms_rad_s:7.4f} | {'':>14}{down.model.v_s_m_s:7.4f} "
              f"{down.model.d_per_s:6.3f} {down.v_rms_m_s:7.4f}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

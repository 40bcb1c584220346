"""Eq. 4.1's search, shared by the ground robots: the phase difference that maximises the forward
speed, from a sweep that makes it an input.

    phi*(inputs) := argmax_{phi} v_x(inputs, phi)                                            (4.1)

Every point of a grid of the CPG's inputs flies with each phase of an even grid over 2 pi held
(the kind's own sweep command). Per input point, the argmax over the phase grid is refined by a
parabola through it and its two neighbours, the grid wrapping at 2 pi (:func:`best_phases`); the
map (:func:`phase_map`) is a :class:`~companion.motion.oscillators.PhaseMap` on the inputs' grid,
its values unwrapped along every axis so that its linear interpolation does not cross a 2 pi jump.
:func:`map_lines` writes it as the TOML table a scenario's ``phase_map_file`` names;
:func:`write_sweep` writes that file with the sweep's record in its header; :func:`run_sweep` is
what a robot's sweep command does with its parsed command line, refusing a grid with a point that
has no speed (:func:`speedless_points`).
"""

from __future__ import annotations

import math
import sys

import numpy as np

from companion.motion.oscillators import PhaseMap

from .sweep import commit, floats, run_jobs

__all__ = ["phase_grid", "grid_speeds", "best_phases", "phase_map", "map_lines", "write_sweep", "speedless_points",
           "run_sweep"]


def phase_grid(n: int) -> np.ndarray:
    """``n`` phases [rad] evenly over ``[-pi, pi)``."""
    return np.arange(n) * 2.0 * math.pi / n - math.pi


def grid_speeds(speed, sc, A_deg, B_deg, phi_rad, workers: int = 1, scheduler: str | None = None) -> np.ndarray:
    """``v_x`` on the grid ``(len(A), len(B), len(phi))``: ``speed((sc, A, B, phi))`` at every point
    (a module-level function: the points may fly in other processes), flown where
    :func:`~sitl.scenarios.ground.sweep.run_jobs` says."""
    jobs = [(sc, a, b, p) for a in A_deg for b in B_deg for p in phi_rad]
    return np.asarray(run_jobs(speed, jobs, workers, scheduler)).reshape(len(A_deg), len(B_deg), len(phi_rad))


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


def phase_map(axes, best_rad: np.ndarray) -> PhaseMap:
    """The map of the best phases ``best_rad`` (the grid's shape) on the input ``axes`` (one
    sequence per input, in the map's units), unwrapped along every axis."""
    values = np.asarray(best_rad, dtype=float)
    for k in range(values.ndim):
        values = np.unwrap(values, axis=k)
    return PhaseMap(tuple(tuple(float(x) for x in ax) for ax in axes), tuple(float(x) for x in values.ravel()))


def map_lines(table: str, m: PhaseMap) -> list[str]:
    """The TOML lines of ``m`` as the table ``[table]``."""
    return [f"[{table}]", f"axes = [{', '.join('[' + ', '.join(f'{x:.9g}' for x in ax) + ']' for ax in m.axes)}]",
            f"values = [{', '.join(f'{x:.9g}' for x in m.values)}]"]


def write_sweep(args, title: str, table: str, m: PhaseMap, A_deg, B_deg, phi_rad: np.ndarray, v: np.ndarray,
                best: np.ndarray, commit: str) -> None:
    """Write ``args.out``: a header (``title``, the command line of ``args``: ``config``, ``A``,
    ``B``, ``phases``, ``duration``; the ``commit``; the phase grid; per ``(A, B)`` every swept speed
    ``v`` and the best phase) and the map ``m`` as ``[table]``; print the header."""
    header = [f"# {title}",
              f"# --config {args.config} --A {args.A} --B {args.B} --phases {args.phases} --duration {args.duration}",
              f"# at commit {commit} (the runs are deterministic: no seed)",
              f"# phase grid [rad]: {', '.join(f'{x:.4f}' for x in phi_rad)}"]
    for i, a in enumerate(A_deg):
        for j, b in enumerate(B_deg):
            header.append(f"# A = {a:g} deg, B = {b:g} deg: v_x [m/s] = {', '.join(f'{x:.4f}' for x in v[i, j])}; "
                          f"best {best[i, j]:.4f} rad")
    args.out.write_text("\n".join(header + map_lines(table, m)) + "\n")
    print("\n".join(header))
    print(f"wrote {args.out}")


def speedless_points(v: np.ndarray, A_deg, B_deg, phi_rad) -> list[str]:
    """The grid points of ``v`` (``(len(A), len(B), len(phi))``) with no finite speed, named
    ``"A=.. B=.. phi=.."`` (a flight too short for its averaging window, or one that diverged)."""
    return [f"A={A_deg[i]:g} B={B_deg[j]:g} phi={phi_rad[k]:.4f}" for i, j, k in zip(*np.nonzero(~np.isfinite(v)))]


def run_sweep(args, sc, sweep, table: str, title: str, extra_axes=()) -> int:
    """A sweep command's work: the ``(A, B)`` grid of ``args`` [deg] and its ``phases``, the speeds
    ``sweep(sc, A, B, phi, workers, scheduler)`` flies, their best phases, and the map (on ``A``,
    ``B`` [rad] and ``extra_axes``, each of one point: constant along it) written as ``[table]``
    with ``title`` (:func:`write_sweep`). Returns the exit status: 2, with nothing written and the
    points named, when a point has no speed (:func:`speedless_points`)."""
    A, B = floats(args.A), floats(args.B)
    phi = phase_grid(args.phases)
    v = sweep(sc, A, B, phi, args.workers, args.scheduler)
    missing = speedless_points(v, A, B, phi)
    if missing:
        shown = ", ".join(missing[:6]) + (f" and {len(missing) - 6} more" if len(missing) > 6 else "")
        print(f"error: {len(missing)} of {v.size} grid points have no speed ({shown}); no map written. "
              f"A flight of --duration {args.duration:g} s may be shorter than the window its speed is "
              "averaged over: give a longer --duration.", file=sys.stderr)
        return 2
    best = best_phases(v, phi)
    m = phase_map((np.radians(A), np.radians(B), *extra_axes), best.reshape(best.shape + (1,) * len(extra_axes)))
    write_sweep(args, title, table, m, A, B, phi, v, best, commit())
    return 0

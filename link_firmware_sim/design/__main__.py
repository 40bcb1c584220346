"""ODAR design optimisation tool (thesis sec. 2.2.2).

    python -m link_firmware_sim.design evaluate [--config FILE] [--json PATH] [--plot] [--out DIR]
    python -m link_firmware_sim.design carry --config FILE [--json PATH]
    python -m link_firmware_sim.design search [--config FILE] [--fine] [--no-refine] [--tie-tolerance FRAC]
                                              [--scenario FILE] [--out DIR] [--json PATH]

``evaluate`` prints the metrics of a geometry as JSON: ``F_min`` (2.2), ``F_min_xz`` (the
sagittal plane), ``M_min`` (2.3), in units of ``lambda_max``, ``d_aero_m`` (2.6), and the
weighted ``F_min_W`` / ``M_min_V`` and constraints. Default geometry: thesis Table 2.1 as printed
(``sigma_1 = +1``). ``--config FILE``: the ``[rotors.geometry]`` of a design file, firmware
config or SITL scenario (without one: the Table 2.1 geometry such a config flies,
``sigma_1 = -1``), its ``[rotors] drag_ratio_m``, ``[skeleton] rotor_x_scale`` and an optional
``[design]`` table (:class:`~link_firmware_sim.design.metrics.DesignProblem`: R_max, L_max, W, V,
D, lambda_max, mass, ``[design.flow]``).

``carry --config FILE`` prints, for a scenario's (or firmware config's) chain, the largest rotor
thrust a link needs to hover with no link dead, with a dead link inside the chain and with a dead
end link: a neighbour alone (level and at its best pitch) and the whole level chain sharing the
load, against ``[rotors] thrust_max_n`` (:mod:`~link_firmware_sim.design.carry`): whether the
chain can hold a link that loses power in flight.

``search`` runs the sequential grid search (2.4)-(2.6) (step 1's directions then refined
continuously, near-ties of ``F_min^W`` broken by the larger ``F_min``; ``--no-refine``,
``--tie-tolerance``) with a progress bar and writes its run
folder (default ``runs/design-search-<UTC time>``): ``design.json`` (both optima, metrics, run
time), ``design.toml`` (``[design]`` and the flyable optimum's ``[rotors]``/``[rotors.geometry]``,
the table firmware configs and SITL scenarios accept), ``optimum_as_posed.toml`` (the optimum of
(2.4)-(2.6) without (2.11), for ``evaluate``), ``volumes.png`` (Fig. 2-2) and, with
``--scenario FILE``, ``scenario.toml``: that scenario flying the designed module
(``python -m sitl fly --config DIR/scenario.toml``). Exit code 2 on a bad config or option.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from companion.cli import make_run_dir, progress_bar, run_subcommand
from companion.configfile import ConfigError, build, dump_toml, load_toml, to_dict
from companion.skeleton.body import SkeletonConfig
from companion.skeleton.rotors import RotorGeometry, RotorGeometryConfig, RotorParams

from .carry import carry_cases
from .metrics import DesignProblem, OdarDesign, evaluate
from .search import SearchGrid, n_position_steps, search

log = logging.getLogger("link_firmware_sim.design")


def _load(path: str | None) -> tuple[RotorGeometry, DesignProblem, str]:
    """Geometry, problem and a description of the geometry from ``--config`` (or the defaults)."""
    if path is None:
        return RotorGeometry.odar(sigma1=1), DesignProblem(), "thesis Table 2.1 as printed (sigma_1 = +1)"
    data = load_toml(path)
    problem = build(DesignProblem, data.get("design", {}), file=path, prefix="design")
    rotors = build(RotorParams, data.get("rotors", {}), file=path, prefix="rotors")
    skeleton = build(SkeletonConfig, data.get("skeleton", {}), file=path, prefix="skeleton")
    x_scale = skeleton.rotor_x_scale
    if rotors.geometry is None:
        geometry = RotorGeometry.odar(drag_ratio=rotors.drag_ratio_m, x_scale=x_scale)
        what = f"{path}: thesis Table 2.1 with sigma_1 = -1 (no [rotors.geometry])"
    else:
        geometry = rotors.geometry.to_geometry(rotors.drag_ratio_m, x_scale)
        what = f"{path}: [rotors.geometry] {rotors.geometry.source}".rstrip()
    return geometry, problem, what


def _write_json(result: dict, path: str | Path) -> Path:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    return out


def _cmd_evaluate(args) -> int:
    try:
        geometry, problem, what = _load(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    metrics = evaluate(geometry, problem)
    result = {**metrics.as_dict(problem.thrust_max_n), "geometry": what,
              "problem": to_dict(problem), "weight_bound_lambda": problem.weight_lambda}
    print(json.dumps(result, indent=2))
    if args.json:
        _write_json(result, args.json)
    if args.plot or args.out:
        from .plots import plot_volumes

        run = make_run_dir("design-evaluate", args.out)
        _write_json(result, run / "metrics.json")
        plot_volumes({what: OdarDesign(geometry, problem)}, run / "volumes.png")
        log.info("wrote %s", run)
    return 0


def _cmd_carry(args) -> int:
    try:
        geometry, _, what = _load(args.config)
        data = load_toml(args.config)
        rotors = build(RotorParams, data.get("rotors", {}), file=args.config, prefix="rotors")
        skeleton = build(SkeletonConfig, data.get("skeleton", {}), file=args.config, prefix="skeleton")
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    cases = carry_cases(geometry, skeleton.n_links, skeleton.link_mass_kg, skeleton.link_length_m, rotors.thrust_max_n)
    result = {"geometry": what, "n_links": skeleton.n_links, "link_mass_kg": skeleton.link_mass_kg,
              "link_length_m": skeleton.link_length_m, "cases": [c.as_dict() for c in cases]}
    print(json.dumps(result, indent=2))
    if args.json:
        _write_json(result, args.json)
    return 0


def _geometry_table(geometry: RotorGeometry, problem: DesignProblem, source: str) -> dict:
    """``[design]`` + ``[rotors]`` (drag ratio and ``[rotors.geometry]``) as a TOML-ready dict."""
    return {
        "design": to_dict(problem),
        "rotors": {"drag_ratio_m": geometry.drag_ratio,
                   "geometry": to_dict(RotorGeometryConfig.from_geometry(geometry, source=source))},
    }


def _design_json(geometry: RotorGeometry | None, problem: DesignProblem) -> dict | None:
    if geometry is None:
        return None
    return {
        "metrics": evaluate(geometry, problem).as_dict(problem.thrust_max_n),
        "directions": geometry.directions[:4].tolist(),
        "positions_m": geometry.positions_m[:4].tolist(),
        "spin": [int(s) for s in geometry.spin[:4]],
        "torque_per_thrust_m": geometry.torque_per_thrust()[:4].tolist(),
    }


def _grid(args) -> SearchGrid:
    base = SearchGrid.fine() if args.fine else SearchGrid()
    return SearchGrid(
        direction_step_deg=args.direction_step_deg or base.direction_step_deg,
        x_count=args.x_count or base.x_count,
        radius_count=args.radius_count or base.radius_count,
        angle_step_deg=args.angle_step_deg or base.angle_step_deg,
        refine_directions=not args.no_refine,
        direction_tie_tolerance=base.direction_tie_tolerance if args.tie_tolerance is None else args.tie_tolerance,
    )


def _cmd_search(args) -> int:
    try:
        grid = _grid(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        problem = DesignProblem() if args.config is None else build(
            DesignProblem, load_toml(args.config).get("design", {}), file=args.config, prefix="design")
        scenario = load_toml(args.scenario) if args.scenario else None
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run = make_run_dir("design-search", args.out)
    t0 = time.perf_counter()
    try:
        with progress_bar(total=n_position_steps(problem, grid), desc="positions (r_1 candidates)", unit="r1",
                          disable=args.quiet) as bar:
            result = search(problem, grid, progress=bar.update)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - t0
    d = result.directions
    summary = {
        "run_time_s": elapsed,
        "grid": to_dict(grid),
        "problem": to_dict(problem),
        "weight_bound_lambda": problem.weight_lambda,
        "directions_step": {"azimuth_deg": d.azimuth_deg, "elevation_deg": d.elevation_deg,
                            "F_min_W": d.f_min_weighted, "F_min": d.f_min, "F_min_xz": d.f_min_xz,
                            "F_min_W_best": d.f_min_weighted_best, "grid_F_min_W": d.grid_f_min_weighted,
                            "tie_tolerance": d.tie_tolerance, "refined": d.refined,
                            "evaluated": d.n_evaluated, "feasible": d.n_feasible},
        "position_designs_evaluated": result.n_position_designs,
        "optimum_as_posed": _design_json(result.optimum, problem),
        "flyable_optimum": _design_json(result.flyable, problem),
        "table_2_1_as_printed": evaluate(RotorGeometry.odar(sigma1=1), problem).as_dict(),
        "table_2_1_modified_sigma1_minus1": evaluate(RotorGeometry.odar(sigma1=-1), problem).as_dict(),
    }
    _write_json(summary, run / "design.json")
    if args.json:
        _write_json(summary, args.json)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    if result.optimum is not None:
        (run / "optimum_as_posed.toml").write_text(
            "# Optimum of (2.4)-(2.6) as posed: without the null structure (2.11) the firmware cannot fly it.\n"
            + dump_toml(_geometry_table(result.optimum, problem, f"design search {stamp}, optimum as posed")))
    if result.flyable is None:
        print("error: no flyable design (null structure 2.11, principal axes) satisfies the constraints on this grid",
              file=sys.stderr)
        print(json.dumps(summary, indent=2))
        return 1
    tables = _geometry_table(result.flyable, problem, f"design search {stamp}, flyable optimum")
    (run / "design.toml").write_text(
        "# ODAR design (python -m link_firmware_sim.design search); copy [rotors.geometry] into a firmware\n"
        "# config or SITL scenario (its [rotors] drag_ratio_m must match).\n" + dump_toml(tables))
    if scenario is not None:
        scenario.setdefault("rotors", {})
        scenario["rotors"]["geometry"] = tables["rotors"]["geometry"]
        scenario["rotors"]["drag_ratio_m"] = tables["rotors"]["drag_ratio_m"]
        if "name" in scenario:
            scenario["name"] = f"{scenario['name']}_designed"
        (run / "scenario.toml").write_text(dump_toml(scenario))
    try:
        from .plots import plot_volumes
    except ImportError as exc:  # matplotlib is in the sim extra
        log.warning("no plots (%s); install the sim extra", exc)
    else:
        designs = {"flyable optimum (2.11)": OdarDesign(result.flyable, problem)}
        if result.optimum is not None:
            designs["optimum as posed"] = OdarDesign(result.optimum, problem)
        designs["Table 2.1 as printed"] = OdarDesign(RotorGeometry.odar(sigma1=1), problem)
        plot_volumes(designs, run / "volumes.png")
    print(json.dumps({k: summary[k] for k in ("run_time_s", "directions_step", "optimum_as_posed", "flyable_optimum")},
                     indent=2))
    log.info("wrote %s (%.1f s)", run, elapsed)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m link_firmware_sim.design", description=__doc__.split("\n\n")[0],
                                epilog="Run '<command> --help' for each command's options.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    ev = sub.add_parser("evaluate", help="metrics of a geometry (default: Table 2.1 as printed)",
                        description="Print F_min, F_min_xz, M_min (x lambda_max) and d_aero_m of a geometry as JSON.")
    ev.add_argument("--config", metavar="FILE",
                    help="TOML with [rotors.geometry] (design file, firmware config or SITL scenario) and optional "
                         "[design]; default: thesis Table 2.1 as printed")
    ev.add_argument("--json", metavar="PATH", help="also write the JSON here")
    ev.add_argument("--plot", action="store_true", help="write Fig. 2-2 (volumes.png) and metrics.json to a run folder")
    ev.add_argument("--out", metavar="DIR", help="run folder for --plot (default runs/design-evaluate-<UTC time>)")
    ev.set_defaults(func=_cmd_evaluate)
    ca = sub.add_parser("carry", help="can a link hold a neighbour that lost power? (thrust needed vs thrust_max_n)",
                        description="Print the rotor thrust a chain's links need to hover with a dead link inside "
                                    "the chain or at its end: one neighbour alone (level, best pitch) and the whole "
                                    "level chain, as JSON.")
    ca.add_argument("--config", metavar="FILE", required=True,
                    help="SITL scenario or firmware config ([skeleton], [rotors], optional [rotors.geometry])")
    ca.add_argument("--json", metavar="PATH", help="also write the JSON here")
    ca.set_defaults(func=_cmd_carry)
    se = sub.add_parser("search", help="grid search (2.4)-(2.6); writes a [rotors.geometry] table",
                        description="Sequential grid search of (2.4)-(2.6): directions U, then positions R and types S.")
    se.add_argument("--config", metavar="FILE", help="TOML whose [design] table sets the problem (default Table 2.1's)")
    se.add_argument("--fine", action="store_true",
                    help="finer grid: 0.1 deg directions, 9 x 4 x 72 positions (several minutes)")
    se.add_argument("--direction-step-deg", type=float, metavar="DEG", help="step of the u_1 grid (default 0.5)")
    se.add_argument("--angle-step-deg", type=float, metavar="DEG", help="step of the angle about the bar (default 7.5)")
    se.add_argument("--x-count", type=int, metavar="N", help="r_x values in [0, L_max/2] (default 5)")
    se.add_argument("--radius-count", type=int, metavar="N", help="radii in (0, R_max] (default 3)")
    se.add_argument("--no-refine", action="store_true",
                    help="grid only: no continuous refinement of the directions (step 1)")
    se.add_argument("--tie-tolerance", type=float, metavar="FRAC",
                    help="step 1's secondary criterion: within this relative window of the best F_min^W the "
                         "larger F_min wins (default 0.001; 0: F_min^W only)")
    se.add_argument("--scenario", metavar="FILE", help="also write DIR/scenario.toml: this scenario with the design")
    se.add_argument("--out", metavar="DIR", help="run folder (default runs/design-search-<UTC time>)")
    se.add_argument("--json", metavar="PATH", help="also write design.json here")
    se.add_argument("--quiet", action="store_true", help="no progress bar")
    se.set_defaults(func=_cmd_search)
    return p


def main(argv=None) -> int:
    return run_subcommand(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

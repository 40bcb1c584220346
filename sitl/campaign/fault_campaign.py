"""``python -m sitl campaign faults``: the runs of a random-fault campaign and its report.

:func:`fault_specs` draws every flight's schedule (:func:`sitl.campaign.faults.draw_schedule`)
from one seed: the same seed gives the same flights, so the command started again goes on where it
stopped. :func:`write_fault_report` reads each flight's ``metrics.json`` and ``log.npz`` and
writes ``faults.json`` (the schedules, every flight's figures and the per-kind table) and
``faults.md`` (the table, the crashes and the runs that failed, each with the settings and seed
that fly it again: ``python -m sitl fly --config FILE --seed S --set KEY=VALUE ...``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from link_firmware_sim.design.carry import carry_cases

from .faults import AFTER_S, FaultEvent, draw_schedule, fault_table, flight_row, markdown_fault_table, power_loss_near
from .grid import RunSpec, format_value

__all__ = ["fault_specs", "write_fault_report", "replay_command"]


def fault_specs(config: str, flights: int, seed: int, mode: str, duration_s: float | None = None,
                speed: float = 0.0) -> tuple[list[RunSpec], list[list[FaultEvent]]]:
    """``flights`` runs of ``config`` with schedules drawn from ``seed`` (each flight its own
    simulation seed from the same generator; fleet flights paced at ``speed``), and their events.
    ``ValueError`` for a bad count, a scenario that cannot fly in ``mode`` or that leaves no room
    for faults."""
    from sitl.scenarios import load

    if flights < 1:
        raise ValueError(f"--flights must be >= 1, got {flights}")
    kind, sc = load(config, **({"duration_s": duration_s} if duration_s is not None else {}))
    if mode == "fleet" and kind.launch is None:
        raise ValueError(f"{config}: a {kind.name} scenario has no fleet form")
    if sc.faults != type(sc.faults)():
        raise ValueError(f"{config}: the scenario scripts faults of its own; the random schedules start from one "
                         f"without [faults]")
    n = sc.skeleton.n_links
    n_groups = len(sc.companion.group_layout(n)) if sc.companion.distributed else 0
    rng = np.random.default_rng(seed)
    specs, events = [], []
    for _ in range(flights):
        ev, settings = draw_schedule(rng, n, sc.flight_start_s, sc.duration_s, mode == "fleet", n_groups)
        specs.append(RunSpec(config, settings, int(rng.integers(0, 2**31 - 1)), mode, duration_s, speed=speed))
        events.append(ev)
    return specs, events


def replay_command(spec: RunSpec) -> str:
    """The command that flies ``spec`` again on its own."""
    pace = format_value(float(spec.speed))
    head = "python -m sitl fly" if spec.mode == "batch" else f"python -m sitl launch --speed {pace}"
    sets = " ".join(f"--set '{k}={format_value(v)}'" for k, v in spec.settings)
    dur = f" --duration {format_value(float(spec.duration_s))}" if spec.duration_s is not None else ""
    return f"{head} --config {spec.config} --seed {spec.seed}{dur} {sets}"


def _load(folder: Path) -> tuple[dict | None, dict | None]:
    try:
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        metrics = None
    try:
        with np.load(folder / "log.npz") as f:
            log = {k: f[k] for k in ("t", "p_target", "p_true", "home_offset_w_m", "t_sckf", "con_pos_after",
                                     "corrected_sckf") if k in f.files}
    except (OSError, ValueError):
        log = None
    return metrics, log


def write_fault_report(root: Path, specs: list[RunSpec], events: list[list[FaultEvent]], records: list,
                       args) -> tuple[dict, list[dict], str]:
    """``faults.json`` and ``faults.md`` in ``root`` from the flights' folders and records; returns
    the per-kind table, the crashed flights and the Markdown text."""
    from sitl.scenarios import load

    root = Path(root)
    groups, carry = (), []
    if specs:
        _, sc = load(specs[0].config)
        groups = sc.companion.group_layout(sc.skeleton.n_links) if sc.companion.distributed else ()
        carry = [c.as_dict() for c in carry_cases(sc.vehicle_setup().geometry(), sc.skeleton.n_links,
                                                  sc.skeleton.link_mass_kg, sc.skeleton.link_length_m,
                                                  sc.rotors.thrust_max_n)]
    rows = []
    for spec, ev, rec in zip(specs, events, records):
        status = rec["status"] if rec else "not run"
        metrics, log = _load(root / spec.folder()) if status == "ok" else (None, None)
        row = flight_row(ev, metrics, log, status, groups)
        row.update(key=spec.key, seed=spec.seed, settings=[[k, v] for k, v in spec.settings],
                   folder=str(spec.folder()), replay=replay_command(spec))
        if rec and rec.get("error"):
            row["error"] = str(rec["error"])[:500]
        rows.append(row)
    table = fault_table(rows)
    crashes = [r for r in rows if r.get("crashed")]
    failed = [r for r in rows if r["status"] != "ok"]
    (root / "faults.json").write_text(json.dumps({
        "config": specs[0].config if specs else None, "flights": len(specs), "seed": args.seed, "mode": args.mode,
        "speed": args.speed, "table": table, "carry": carry, "runs": rows}, indent=1, default=str) + "\n")
    pace = f" at {args.speed:g}x real time" if args.mode == "fleet" and args.speed else ""
    lines = [f"# Random faults: {Path(specs[0].config).stem if specs else ''}, {len(specs)} flights, seed {args.seed}, "
             f"{args.mode} mode{pace}", "", "Written by `python -m sitl campaign faults`; each flight's schedule and "
             "figures are in faults.json.", "", markdown_fault_table(table), f"## Crashes ({len(crashes)})", ""]
    powerless = [r for r in crashes if power_loss_near(r) is not None]
    if crashes:
        lines += [f"{len(powerless)} with a link without power (a reboot from its start to {AFTER_S:g} s after its "
                  f"end), {len(crashes) - len(powerless)} without.", ""]
    for r in crashes:
        e = power_loss_near(r)
        near = (f" (link {e['target']} without power from {e['start_s']} to {e['end_s']} s)" if e is not None
                else " (no link without power)")
        lines += [f"- `{r['key']}`: {r.get('crash_reason') or 'crashed'}{near}; events "
                  f"{', '.join(e['kind'] + ' ' + str(e['target']) + ' at ' + str(e['start_s']) + ' s' for e in r['events'])}",
                  f"  `{r['replay']}`"]
    if carry:
        lines += ["", "## Holding a link that loses power", "",
                  "The largest rotor thrust the links need to hover with a powerless link: a neighbour holding it "
                  "alone, and the whole level chain sharing the load; static (`python -m link_firmware_sim.design "
                  "carry`), the fall and the swing come on top:", "",
                  "| case | neighbour alone N | chain N | thrust_max N | chain / max |",
                  "| :--- | ---: | ---: | ---: | ---: |"]
        lines += [f"| {c['case']} | {c['level_thrust_n']:.2f} | {c['chain_thrust_n']:.2f} | {c['thrust_max_n']:g} | "
                  f"{c['chain_ratio']:.2f} |" for c in carry]
    lines += ["", f"## Runs that did not finish ({len(failed)})", ""]
    for r in failed:
        lines += [f"- `{r['key']}` ({r['status']}): {r.get('error', '')}", f"  `{r['replay']}`"]
    text = "\n".join(lines) + "\n"
    (root / "faults.md").write_text(text)
    return table, crashes, text

"""A campaign of flights: the grid's runs as engine jobs, and the files a campaign folder holds.

``<campaign>/`` holds ``campaign.json`` (the grid), ``results.csv`` (:mod:`.table`, rewritten as
runs finish), ``summary.csv`` and ``summary.md`` (:mod:`.summary`), ``nees.json`` (the NEES pooled
per group, when the runs have it), ``plots/*.png`` (box plots), and a folder per run
(:meth:`~sitl.campaign.grid.RunSpec.folder`) with its usual files and ``run_record.json``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

from .engine import Campaign, CampaignResult, Job
from .grid import RunSpec
from .runs import fly_spec, load_spec
from .summary import box_plots, markdown_summary, pooled_nees, summarise, write_summary
from .table import rows, write_table

__all__ = ["flight_jobs", "check_specs", "run_flights", "write_summaries", "RESULTS_FILE"]

RESULTS_FILE = "results.csv"


def check_specs(specs: list[RunSpec]) -> bool:
    """Load every distinct scenario of ``specs`` (file, settings, mode; the first seed) before
    anything flies, so that a bad file or setting is an error now, not in every run; whether any
    renders. Raises :class:`~companion.configfile.ConfigError` or ``ValueError``."""
    seen, renders = set(), False
    for spec in specs:
        if spec.group in seen:
            continue
        seen.add(spec.group)
        _, sc = load_spec(spec)
        renders = renders or bool(sc.cameras)
    return renders


def flight_jobs(specs: list[RunSpec], renders: bool = False,
                folder: Callable[[RunSpec], Path] = RunSpec.folder) -> list[Job]:
    """One engine job per run: :func:`~sitl.campaign.runs.fly_spec` into ``folder(spec)``."""
    return [Job(s.key, folder(s), fly_spec, (s, renders), s.columns()) for s in specs]


def write_summaries(root: Path, records: list[dict], title: str, plots: list[str] | None = None) -> list[Path]:
    """``summary.csv``, ``summary.md``, ``nees.json`` and the box plots of ``records`` in
    ``root`` (:func:`run_flights` wrote ``results.csv``); the files written."""
    root = Path(root)
    summary = summarise(records)
    out = [write_summary(root, summary)]
    (root / "summary.md").write_text(markdown_summary(summary, title))
    out.append(root / "summary.md")
    nees = pooled_nees(records)
    if nees:
        (root / "nees.json").write_text(json.dumps(nees, indent=1) + "\n")
        out.append(root / "nees.json")
    return out + box_plots(records, root / "plots", plots)


def run_flights(root: Path, specs: list[RunSpec], open_executor, *, renders: bool = False,
                folder: Callable[[RunSpec], Path] = RunSpec.folder, progress=None,
                table_every_s: float = 5.0, worker_root: str | None = None) -> CampaignResult:
    """Fly ``specs`` as a campaign in ``root`` on the executor ``open_executor()`` opens (only
    if a run is left: :meth:`~sitl.campaign.engine.Campaign.run`), finished runs skipped;
    ``results.csv`` is rewritten at most every ``table_every_s`` while runs finish, and at the
    end (an interrupt included)."""
    campaign = Campaign(Path(root), flight_jobs(specs, renders, folder), worker_root=worker_root)
    last = [time.monotonic()]

    def flush() -> None:
        write_table(Path(root) / RESULTS_FILE, rows(r for r in campaign.in_order() if r))

    def on_record(_rec: dict) -> None:
        if time.monotonic() - last[0] >= table_every_s:
            flush()
            last[0] = time.monotonic()

    try:
        return campaign.run(open_executor, on_record=on_record, progress=progress)
    finally:
        flush()

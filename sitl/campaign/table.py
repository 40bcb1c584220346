"""The campaign's results table: one row per run, every scalar of its metrics a column.

A row holds the run's key columns (scenario, mode, one ``set:<key>`` column per swept setting,
seed), then what the engine knows of the run (``status``, ``attempts``, ``error``, ``wall_s``,
``worker``, ``host``), then its metrics flattened: a nested table's keys joined with dots, a list's
items indexed (``rms_track_true_m[0]`` is link 1's), e.g. ``constraint_pos_p95_m.after``. A run
that failed has its key and error and no metrics. The file is CSV with every float written to its
last digit (``repr``), so two tables of the same runs compare exactly (:func:`compare`).
"""

from __future__ import annotations

import csv
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from .grid import format_value

__all__ = ["flatten", "rows", "write_table", "read_table", "compare", "RUN_COLUMNS", "TIMING_COLUMNS", "cell"]

#: what the engine records of every run, after its key columns
RUN_COLUMNS = ("status", "attempts", "error", "wall_s", "worker", "host")
#: columns that measure the machine, not the flight: two runs of the same seed differ in them
TIMING_COLUMNS = frozenset({"attempts", "wall_s", "worker", "host", "realtime_factor"})


def flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    """The scalars of a metrics tree by flattened name (numbers, booleans, strings; ``None``
    kept as an empty cell)."""
    out: dict[str, Any] = {}
    if isinstance(obj, Mapping):
        for k, v in obj.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            out.update(flatten(v, f"{prefix}[{i}]"))
    elif hasattr(obj, "item") and not isinstance(obj, (str, bytes)):  # a numpy scalar
        out[prefix] = obj.item()
    else:
        out[prefix] = obj
    return out


def rows(records: Iterable[dict]) -> list[dict[str, Any]]:
    """One row per record (records of :class:`~sitl.campaign.engine.Campaign`): key columns, run
    columns, then the flattened result, minus the result's own copies of key columns."""
    out = []
    for rec in records:
        row = dict(rec.get("columns", {}))
        row.update({c: rec.get(c) for c in RUN_COLUMNS})
        result = rec.get("result")
        if isinstance(result, Mapping):
            for k, v in flatten(result).items():
                row.setdefault(k, v)
        out.append(row)
    return out


def cell(value: Any) -> str:
    """A value as written in the CSV: empty for none, else as in keys and folder names
    (:func:`~sitl.campaign.grid.format_value`: floats to their last digit, booleans ``true``/``false``)."""
    return "" if value is None else format_value(value)


def write_table(path: Path, table: list[dict[str, Any]]) -> None:
    """Write ``table`` as CSV at ``path`` (atomically: a reader never sees half a file); the
    columns in the order they first appear."""
    columns: dict[str, None] = {}
    for row in table:
        columns.update(dict.fromkeys(row))
    tmp = Path(path).with_suffix(".tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        for row in table:
            writer.writerow([cell(row.get(c)) for c in columns])
    os.replace(tmp, path)


def read_table(path: Path) -> list[dict[str, str]]:
    """The rows of a table written by :func:`write_table`, as strings (empty: no value)."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def compare(a: list[dict[str, str]], b: list[dict[str, str]], ignore: Iterable[str] = TIMING_COLUMNS,
            key: tuple[str, ...] | None = None) -> list[str]:
    """The differences between two tables (empty: the same runs with the same values to the
    last digit), leaving out the ``ignore`` columns. Rows are matched by their key columns
    (``key``; default: ``scenario``, ``mode``, every ``set:`` column and ``seed`` present)."""
    ignore = set(ignore)
    cols_a = set().union(*(r.keys() for r in a)) if a else set()
    cols_b = set().union(*(r.keys() for r in b)) if b else set()
    if key is None:
        key = tuple(c for c in sorted(cols_a | cols_b) if c in ("scenario", "mode", "seed") or c.startswith("set:"))
    diffs = [f"column {c!r} only in the {'first' if c in cols_a else 'second'} table"
             for c in sorted((cols_a ^ cols_b) - ignore)]

    def index(table):
        out = {}
        for r in table:
            out.setdefault(tuple(r.get(c, "") for c in key), r)
        return out

    ia, ib = index(a), index(b)
    for k in sorted(set(ia) ^ set(ib)):
        diffs.append(f"run {dict(zip(key, k))} only in the {'first' if k in ia else 'second'} table")
    for k in sorted(set(ia) & set(ib)):
        ra, rb = ia[k], ib[k]
        for c in sorted((cols_a & cols_b) - ignore):
            if ra.get(c, "") != rb.get(c, ""):
                diffs.append(f"run {dict(zip(key, k))}: {c}: {ra.get(c, '')!r} != {rb.get(c, '')!r}")
    return diffs

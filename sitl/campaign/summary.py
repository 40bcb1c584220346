"""A campaign's summaries: per group of runs (the same scenario and settings, every seed) and
per metric the mean, standard deviation and 95 % interval of the mean across seeds; box plots of
the headline metrics per setting; the Monte Carlo NEES pooled per group
(:func:`sitl.bench.seeds.aggregate_nees`, as ``python -m sitl.bench nees`` does).

The interval is Student's t interval of the mean, ``mean +- t(0.975, n-1) s / sqrt(n)`` over the
``n`` finished runs of the group (none for one run). Booleans count as 0/1 (the mean of
``crashed`` is the crash rate). Failed and lost runs are counted per group, never left out of the
report: their metrics are missing, so the figures are over the runs that finished.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.special import stdtrit

from .table import cell, flatten, write_table

__all__ = ["group_label", "metric_stats", "summarise", "HEADLINE", "markdown_summary", "write_summary", "box_plots",
           "pooled_nees"]

#: the metrics summary.md and the box plots show first (a column or a per-link list's columns)
HEADLINE = ("rms_track_true_m", "rms_est_err_m.ekf", "rms_est_err_m.sckf", "constraint_pos_p95_m.after",
            "constraint_vel_p95_m_s.after", "rms_pose_track_true_pos_m", "load_pose_err.ekf.pos_rms_m",
            "load_pose_err.ekf.att_rms_deg", "load_pose_err.camera_free.pos_rms_m", "min_altitude_m", "crashed")
_NOT_PLOTTED = ("crashed",)


def group_label(columns: dict[str, Any]) -> str:
    """A run's group (its key columns without the seed) as one label:
    ``three_link batch firmware.ekf.gate_sigma=4``."""
    parts = [str(columns[c]) for c in ("scenario", "mode") if c in columns]
    parts += [f"{c}={cell(columns[c])}" for c in ("duration_s", "profile", "speed") if c in columns]
    parts += [f"{c[4:]}={columns[c]}" for c in columns if c.startswith("set:")]
    return " ".join(parts)


def _groups(records: Iterable[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for rec in records:
        out.setdefault(group_label(rec.get("columns", {})), []).append(rec)
    return out


def metric_stats(values: list[float]) -> dict[str, float | int | None]:
    """``n``, ``mean``, ``std`` (n-1), ``ci95_lo`` / ``ci95_hi`` (t interval of the mean),
    ``min``, ``max`` of the finite ``values`` (the t quantile by ``scipy.special.stdtrit``: scipy.stats
    is slow to import)."""
    x = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    n = int(x.size)
    if n == 0:
        return {"n": 0, "mean": None, "std": None, "ci95_lo": None, "ci95_hi": None, "min": None, "max": None}
    mean = float(x.mean())
    std = float(x.std(ddof=1)) if n > 1 else None
    half = float(stdtrit(n - 1, 0.975) * std / math.sqrt(n)) if n > 1 else None
    return {"n": n, "mean": mean, "std": std, "ci95_lo": None if half is None else mean - half,
            "ci95_hi": None if half is None else mean + half, "min": float(x.min()), "max": float(x.max())}


def _numeric(value: Any) -> float | None:
    if isinstance(value, bool):
        return float(value)
    if isinstance(value, (int, float)):
        return float(value)
    return None


def summarise(records: list[dict]) -> list[dict[str, Any]]:
    """The long table: a row per group and numeric metric (finished runs only), with the
    group's ``runs``, ``failed`` and ``lost`` counts on every row."""
    out = []
    for label, recs in _groups(records).items():
        ok = [r for r in recs if r.get("status") == "ok"]
        counts = {"runs": len(recs), "failed": sum(r.get("status") == "failed" for r in recs),
                  "lost": sum(r.get("status") == "lost" for r in recs)}
        metrics: dict[str, list[float]] = {}
        for rec in ok:
            flat = {"wall_s": rec.get("wall_s"), **flatten(rec.get("result") or {})}
            for k, v in flat.items():
                x = _numeric(v)
                if x is not None and k not in ("seed",):
                    metrics.setdefault(k, []).append(x)
        for name, values in metrics.items():
            out.append({"group": label, **counts, "metric": name, **metric_stats(values)})
        if not metrics:
            out.append({"group": label, **counts, "metric": "", **metric_stats([])})
    return out


def _headline_columns(names: Iterable[str]) -> list[str]:
    names = list(dict.fromkeys(names))
    out = []
    for h in HEADLINE:
        out += [n for n in names if n == h or re.fullmatch(re.escape(h) + r"\[\d+\]", n)]
    return out


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.4g}"


def markdown_summary(summary: list[dict], title: str) -> str:
    """``summary.md``: every group's run counts, then its headline metrics as mean ± std
    [95 % interval] (all metrics are in ``summary.csv``)."""
    from sitl.bench.report import md_table

    groups = list(dict.fromkeys(r["group"] for r in summary))
    first = {g: next(r for r in summary if r["group"] == g) for g in groups}
    lines = [f"# {title}", "", "Runs per group (finished / failed / lost):", "",
             md_table(("group", "runs", "finished", "failed", "lost"),
                      [(g, first[g]["runs"], first[g]["runs"] - first[g]["failed"] - first[g]["lost"],
                        first[g]["failed"], first[g]["lost"]) for g in groups])]
    heads = _headline_columns(r["metric"] for r in summary)
    if heads:
        by = {(r["group"], r["metric"]): r for r in summary}
        rows = []
        for m in heads:
            cells = []
            for g in groups:
                r = by.get((g, m))
                if r is None or not r["n"]:
                    cells.append("-")
                elif r["ci95_lo"] is None:
                    cells.append(f"{_fmt(r['mean'])} (n=1)")
                else:
                    cells.append(f"{_fmt(r['mean'])} ± {_fmt(r['std'])} [{_fmt(r['ci95_lo'])}, {_fmt(r['ci95_hi'])}]")
            rows.append((m, *cells))
        lines += ["", "Mean ± standard deviation [95 % interval of the mean] over the finished runs' seeds "
                  "(a list's `[i]` is link i+1):", "", md_table(("metric", *groups), rows)]
    return "\n".join(lines) + "\n"


def write_summary(folder: Path, summary: list[dict]) -> Path:
    path = Path(folder) / "summary.csv"
    write_table(path, summary)
    return path


def box_plots(records: list[dict], folder: Path, metrics: Iterable[str] | None = None) -> list[Path]:
    """One PNG per metric in ``folder``: a box per group over its finished runs' seeds
    (default: :data:`HEADLINE` but ``crashed``, a rate; a per-link metric gets a panel per link)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = _groups(r for r in records if r.get("status") == "ok")
    flats = {g: [flatten(r.get("result") or {}) | {"wall_s": r.get("wall_s")} for r in recs]
             for g, recs in groups.items()}
    names = list(dict.fromkeys(k for fl in flats.values() for f in fl for k in f))
    wanted = list(metrics) if metrics is not None else [h for h in HEADLINE if h not in _NOT_PLOTTED]
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for base in wanted:
        cols = [n for n in names if n == base or re.fullmatch(re.escape(base) + r"\[\d+\]", n)]
        if not cols:
            continue
        fig, axes = plt.subplots(1, len(cols), figsize=(max(4.0, 2.2 * len(groups)) * min(len(cols), 3) / 1.5, 4.0),
                                 squeeze=False, sharey=True)
        common, xlabel, ticks = _split_labels(list(groups))
        for ax, col in zip(axes[0], cols):
            data = [[x for f in flats[g] if (x := _numeric(f.get(col))) is not None and math.isfinite(x)]
                    for g in groups]
            ax.boxplot([d or [math.nan] for d in data])  # (a group with no finished run: an empty slot)
            ax.set_xticks(range(1, len(groups) + 1), ticks)
            ax.set_title(col, fontsize=9)
            ax.tick_params(axis="x", labelsize=7)
            ax.set_xlabel(xlabel, fontsize=7)
        fig.suptitle(f"{common} (over seeds)", fontsize=9)
        fig.tight_layout()
        path = folder / (re.sub(r"[^A-Za-z0-9._-]", "_", base) + ".png")
        fig.savefig(path, dpi=90)
        plt.close(fig)
        out.append(path)
    return out


def _split_labels(labels: list[str]) -> tuple[str, str, list[str]]:
    """What the group labels share (the figure's title), the keys whose values tell them apart
    (the x axis's label) and those values (each group's tick)."""
    words = [label.split(" ") for label in labels]
    shared = [w for w in words[0] if all(w in other for other in words)]
    rest = [[w for w in ws if w not in shared] for ws in words]
    keys = [[w.partition("=")[0] for w in ws] for ws in rest]
    if all(rest) and all("=" in w for ws in rest for w in ws) and all(k == keys[0] for k in keys):
        return " ".join(shared), ", ".join(keys[0]), ["\n".join(w.partition("=")[2] for w in ws) for ws in rest]
    return " ".join(shared), "", ["\n".join(ws) or "all" for ws in rest]


def pooled_nees(records: list[dict]) -> dict[str, dict]:
    """Per group with NEES figures, :func:`sitl.bench.seeds.aggregate_nees` over its finished runs."""
    from sitl.bench.seeds import aggregate_nees

    out = {}
    for label, recs in _groups(r for r in records if r.get("status") == "ok").items():
        results = [r["result"] for r in recs if isinstance(r.get("result"), dict) and r["result"].get("nees")]
        if results:
            out[label] = aggregate_nees(results)
    return out

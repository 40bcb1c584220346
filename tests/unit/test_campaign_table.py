"""The campaign's results table and summaries (sitl.campaign.table, sitl.campaign.summary)."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sitl.campaign.summary import group_label, markdown_summary, metric_stats, summarise
from sitl.campaign.table import compare, flatten, read_table, rows, write_table


def _record(seed, status="ok", gate="4", **result):
    return {"key": f"s|batch|g={gate}|seed={seed}", "status": status, "attempts": 1, "error": None if status == "ok"
            else "RuntimeError: no", "wall_s": 1.5 + seed, "worker": "0", "host": "h",
            "columns": {"scenario": "s", "mode": "batch", "set:g": gate, "seed": seed},
            "result": result if status == "ok" else None}


def test_flatten_names_every_scalar_by_its_path():
    tree = {"a": 1, "b": {"c": [0.5, 0.25], "d": True}, "e": [{"f": np.float64(2.0)}], "g": None, "h": "x"}
    assert flatten(tree) == {"a": 1, "b.c[0]": 0.5, "b.c[1]": 0.25, "b.d": True, "e[0].f": 2.0, "g": None, "h": "x"}
    assert type(flatten({"x": np.int64(3)})["x"]) is int


def test_a_row_is_key_columns_then_the_run_then_its_metrics():
    rec = _record(2, crashed=False, rms=[0.1, 0.2])
    rec["result"].update(seed=2, scenario="three_link")
    row = rows([rec])[0]
    assert list(row)[:4] == ["scenario", "mode", "set:g", "seed"]
    assert row["scenario"] == "s"  # the key column, not the metrics' own copy
    assert row["status"] == "ok" and row["rms[1]"] == 0.2 and row["crashed"] is False
    failed = rows([_record(3, status="failed")])[0]
    assert failed["error"] == "RuntimeError: no" and "rms[0]" not in failed


@given(st.lists(st.floats(allow_nan=False), min_size=1, max_size=8))
def test_the_csv_keeps_every_float_to_its_last_digit(tmp_path_factory, values):
    path = tmp_path_factory.mktemp("t") / "results.csv"
    write_table(path, rows([_record(i, x=v) for i, v in enumerate(values)]))
    back = read_table(path)
    assert [float(r["x"]) for r in back] == values
    assert not compare(back, read_table(path))


def test_compare_finds_a_changed_metric_and_a_missing_run_but_not_the_timing(tmp_path):
    a = rows([_record(0, x=0.1, realtime_factor=9.0), _record(1, x=0.2, realtime_factor=9.0)])
    b = rows([_record(0, x=0.1, realtime_factor=3.0), _record(1, x=math.nextafter(0.2, 1.0), realtime_factor=3.0)])
    for r in b:
        r["wall_s"], r["worker"] = 99.0, "tcp://10.0.0.2:4000"
    write_table(tmp_path / "a.csv", a)
    write_table(tmp_path / "b.csv", b)
    diffs = compare(read_table(tmp_path / "a.csv"), read_table(tmp_path / "b.csv"))
    assert len(diffs) == 1 and "x: '0.2' != '0.20000000000000004'" in diffs[0]
    write_table(tmp_path / "c.csv", a[:1])
    assert any("only in the first" in d for d in compare(read_table(tmp_path / "a.csv"), read_table(tmp_path / "c.csv")))


def test_stats_are_the_mean_spread_and_t_interval_of_the_mean():
    out = metric_stats([1.0, 2.0, 3.0, float("nan")])  # a non-finite value is left out
    half = 4.302652729911275 / math.sqrt(3)  # t(0.975, 2) * std 1 / sqrt(3)
    assert out["n"] == 3 and out["mean"] == 2.0 and out["std"] == 1.0
    assert out["ci95_lo"] == pytest.approx(2.0 - half) and out["ci95_hi"] == pytest.approx(2.0 + half)
    one = metric_stats([5.0])
    assert one["mean"] == 5.0 and one["std"] is None and one["ci95_lo"] is None
    assert metric_stats([])["n"] == 0


def test_the_summary_counts_failed_and_lost_runs_per_group():
    recs = [_record(0, x=1.0, crashed=False), _record(1, x=3.0, crashed=True), _record(2, status="failed"),
            _record(0, gate="5", x=10.0, crashed=False), _record(1, gate="5", status="lost")]
    summary = summarise(recs)
    by = {(r["group"], r["metric"]): r for r in summary}
    g4, g5 = group_label(recs[0]["columns"]), group_label(recs[3]["columns"])
    assert g4 == "s batch g=4"
    assert by[(g4, "x")]["mean"] == 2.0 and by[(g4, "x")]["runs"] == 3 and by[(g4, "x")]["failed"] == 1
    assert by[(g4, "crashed")]["mean"] == 0.5  # the crash rate
    assert by[(g5, "x")]["n"] == 1 and by[(g5, "x")]["lost"] == 1
    text = markdown_summary(summary, "t")
    assert "| s batch g=4 | 3 | 2 | 1 | 0 |" in text and "| s batch g=5 | 2 | 1 | 0 | 1 |" in text
    assert "crashed" in text


@pytest.mark.parametrize("labels, title, xlabel, ticks", [
    (["s batch g=4 h=1", "s batch g=5 h=1"], "s batch h=1", "g", ["4", "5"]),
    (["s batch g=4 h=1", "s batch g=5 h=2"], "s batch", "g, h", ["4\n1", "5\n2"]),
    (["a batch", "b batch g=1"], "batch", "", ["a", "b\ng=1"]),
    (["s batch"], "s batch", "", ["all"]),
])
def test_box_plot_labels_keep_what_the_groups_share_in_the_title(labels, title, xlabel, ticks):
    from sitl.campaign.summary import _split_labels

    assert _split_labels(labels) == (title, xlabel, ticks)

"""The benchmarks' Markdown reports (sitl/bench/report.py), cheaply: the header every report
carries, tables built from a result dict (never typed by hand), and the --doc / --no-doc options
of every bench. No bench runs here."""

from __future__ import annotations

import datetime as dt
import re
import subprocess
from pathlib import Path

import pytest

from sitl.bench import report
from sitl.bench.__main__ import DOCS, _write_doc, build_parser
from sitl.bench.scaling import format_scaling, markdown_scaling

from ..paths import ROOT

BENCHES = ("table2", "scaling", "zenoh", "nees", "static", "load_filter", "sitl")

#: a small scaling result in the layout ``scaling.json`` holds (sitl/bench/scaling.py::run_scaling)
FAKE_SCALING = {
    "full": {"3": 0.2231, "7": 0.4052},
    "semi2": {"3": 0.4134, "7": 0.5731},
    "full_dense_reference": {"3": 0.1921},
    "iterations": {"3": {"full": 1.08, "semi2_max_group": 1.0}, "7": {"full": 2.0, "semi2_max_group": 2.0}},
    "protocol": {"seed": 0, "duration_s": 5.0, "transient_s": 2.0, "steps_per_n": 60, "eps": 0.01, "alpha": 0.01,
                 "dense_cap_links": 24},
}


def test_report_has_every_header_field_and_the_result_as_a_table():
    when = dt.datetime(2025, 3, 4, 5, 6, 7, tzinfo=dt.timezone.utc)
    machine = {"platform": "Linux-test", "cpu": "Test CPU 3000", "cores": 2, "python": "3.11.9",
               "packages": {"numpy": "2.0.0", "numba": "0.68.1"}}
    text = report.render_doc(title="Constraint application per step", command="python -m sitl.bench scaling --doc",
                             body=markdown_scaling(FAKE_SCALING), console=format_scaling(FAKE_SCALING), date=when,
                             commit="abc1234+dirty", machine=machine, elapsed_s=12.34,
                             outputs=["runs/scaling-x/scaling.json"], load=((0.5, 0.25, 0.125), (1.5, 1.0, 0.75)))
    lines = text.splitlines()
    assert lines[0] == "# Constraint application per step"
    assert "do not edit by hand" in text
    assert "- command: `python -m sitl.bench scaling --doc`" in lines
    assert "- date (UTC): 2025-03-04 05:06:07" in lines
    assert "- git commit: `abc1234+dirty`" in lines
    assert "- platform: Linux-test" in lines
    assert "- CPU: Test CPU 3000, 2 cores" in lines
    assert "- Python: 3.11.9" in lines
    assert "- packages: numpy 2.0.0, numba 0.68.1" in lines
    assert "- wall time of the run: 12.3 s" in lines
    assert "- outputs: `runs/scaling-x/scaling.json`" in lines
    assert ("- load average (1, 5, 15 min) at the start / end of the run: 0.50, 0.25, 0.12 / 1.50, 1.00, 0.75 "
            "(other work on the machine slows the timed figures)") in lines
    # the figures: a Markdown table whose cells come from the dict
    header = lines.index("| n links | full SCKF [ms] | semi, groups of 2 [ms] | dense reference [ms] | iterations full "
                         "| iterations semi |")
    assert re.fullmatch(r"\| :--- (\| ---: ){5}\|", lines[header + 1])
    assert lines[header + 2] == "| 3 | 0.223 | 0.413 | 0.192 | 1.08 | 1.00 |"
    assert lines[header + 3] == "| 7 | 0.405 | 0.573 | (capped) | 2.00 | 2.00 |"
    # then what the command printed, verbatim
    assert "## Console output" in text and format_scaling(FAKE_SCALING) in text


def test_md_table_escapes_pipes_and_checks_its_shape():
    assert report.md_table(("a", "b"), [("x|y", 1)]).splitlines() == ["| a | b |", "| :--- | ---: |", "| x\\|y | 1 |"]
    with pytest.raises(ValueError):
        report.md_table(("a", "b"), [(1, 2, 3)])


def test_git_commit_of_this_checkout_and_outside_one(tmp_path):
    commit = report.git_commit(ROOT)
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    if head:
        assert commit.split("+")[0] == head and commit in (head, head + "+dirty")
    assert report.git_commit(tmp_path) == "unknown"


def test_machine_info_and_cpu_model(tmp_path):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nvendor_id\t: X\nmodel name\t: Fancy CPU @ 3 GHz\n")
    assert report.cpu_model(cpuinfo) == "Fancy CPU @ 3 GHz"
    info = report.machine_info(("numpy", "no-such-package-here"))
    assert info["cores"] and info["python"] and info["platform"] and info["cpu"]
    assert info["packages"]["no-such-package-here"] == "not installed"
    assert re.match(r"\d+\.\d+", info["packages"]["numpy"])


@pytest.mark.parametrize("bench", BENCHES)
def test_doc_options_parse(bench, tmp_path):
    parser = build_parser()
    base = [bench]
    args = parser.parse_args(base)
    assert args.doc is None and not args.no_doc
    assert report.doc_path(args, tmp_path, bench) == tmp_path / f"{bench}.md"  # the run folder by default
    args = parser.parse_args([*base, "--doc"])
    assert report.doc_path(args, tmp_path, bench) == Path("docs/bench") / f"{bench}.md"
    args = parser.parse_args([*base, "--doc", "elsewhere/x.md"])
    assert report.doc_path(args, tmp_path, bench) == Path("elsewhere/x.md")
    args = parser.parse_args([*base, "--no-doc"])
    assert args.no_doc and report.doc_path(args, tmp_path, bench) is None
    with pytest.raises(SystemExit):
        parser.parse_args([*base, "--doc", "x.md", "--no-doc"])
    assert bench in DOCS


def test_write_doc_records_the_command_as_typed(tmp_path):
    args = build_parser().parse_args(["scaling", "--seed", "3", "--doc", str(tmp_path / "d" / "scaling.md")])
    args.argv = ["scaling", "--seed", "3", "--doc", str(tmp_path / "d" / "scaling.md")]
    _write_doc(args, tmp_path / "run", markdown_scaling(FAKE_SCALING), format_scaling(FAKE_SCALING), ["x.json"])
    text = (tmp_path / "d" / "scaling.md").read_text()
    assert "- load average" not in text  # (args.load_start is set by main, not here)
    assert f"- command: `python -m sitl.bench scaling --seed 3 --doc {tmp_path / 'd' / 'scaling.md'}`" in text
    assert "| 7 | 0.405 | 0.573 | (capped) | 2.00 | 2.00 |" in text
    assert not (tmp_path / "run").exists()  # --doc PATH: not in the run folder
    args = build_parser().parse_args(["scaling", "--no-doc"])
    _write_doc(args, tmp_path / "run2", "body", "console", [])
    assert not (tmp_path / "run2").exists()


def test_environment_that_changes_a_bench_is_recorded(monkeypatch):
    monkeypatch.setenv("SKELETON_JIT", "0")
    info = report.machine_info(())
    assert info["environment"]["SKELETON_JIT"] == "0"
    text = report.render_doc(title="t", command="c", body="b", commit="x", machine=info)
    assert "`SKELETON_JIT=0`" in text


def test_a_short_bench_run_writes_its_report_from_its_json(tmp_path):
    """End to end on the cheapest bench: the report in the run folder records the command and
    shows the JSON's own numbers."""
    import json

    from sitl.bench.__main__ import main

    argv = ["table2", "--duration", "0.3", "--seeds", "1", "--ekf", "paper", "--out", str(tmp_path / "run"), "--quiet"]
    assert main(argv) == 0
    text = (tmp_path / "run" / "table2.md").read_text()
    result = json.loads((tmp_path / "run" / "table2.json").read_text())
    assert f"- command: `python -m sitl.bench {' '.join(argv)}`" in text
    assert "- load average (1, 5, 15 min) at the start / end of the run: " in text
    ekf = result["by_ekf"]["paper"]["ekf_only"]
    assert f"| EKF only | - | {ekf['pos_err_m']:.4f} | {ekf['quat_err']:.4f} |" in text
    assert main([*argv[:-3], "--out", str(tmp_path / "run2"), "--no-doc", "--quiet"]) == 0
    assert not (tmp_path / "run2" / "table2.md").exists() and (tmp_path / "run2" / "table2.json").exists()


def test_the_controllers_table_gives_each_controllers_tracking_and_real_time_factor():
    """What a controller costs per tick has its figure in the report: the flight's real-time factor
    beside its tracking (``-`` when unmeasured)."""
    from sitl.bench.controllers import format_controllers, markdown_controllers

    flight = {"rms_pos_true_m": 0.0445, "rms_pos_est_m": 0.0326, "rms_att_true_deg": 0.42, "max_pos_true_m": 0.0753,
              "window_s": [14.0, 39.98], "crashed": False}
    result = {"scenario": "single_odar_figure8", "seed": 3, "duration_s": 40.0,
              "controllers": {"impedance": {**flight, "realtime_factor": 5.73},
                              "se3_pid": {**flight, "crashed": True, "realtime_factor": None}}}
    table = markdown_controllers(result)
    assert "| real-time factor |" in table.splitlines()[2]
    assert "| impedance | 4.45 | 3.26 | 0.42 | 7.53 | no | 5.7 |" in table
    assert "| se3_pid | 4.45 | 3.26 | 0.42 | 7.53 | yes | - |" in table
    assert format_controllers(result).splitlines()[1].split()[-3:] == ["crashed", "real-time", "factor"]

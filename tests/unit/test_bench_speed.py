"""The plumbing of ``python -m sitl.bench sitl`` (sitl/bench/speed.py), cheaply: the MuJoCo
ceiling on a short horizon, a child's CPU/RSS accounting and metrics reading (with a stand-in for
the flight), the /proc sampling and the fleet processes' roles, the table, and the CLI's errors.
The real figures are the command's (README)."""

from __future__ import annotations

import json
import os
import sys
import textwrap
from pathlib import Path

import pytest

from sitl.bench import procfs, speed
from sitl.bench.__main__ import main as bench_main


def test_mujoco_ceiling_runs_the_scenarios_model():
    c = speed.mujoco_ceiling("three_link", 0.05)
    assert c["sim_s"] == pytest.approx(0.05)
    assert c["realtime_factor"] > 0 and c["cpu_s_per_sim_s"] > 0


def test_firmware_tick_times_both_paths():
    tick = speed.firmware_tick(60, repeat=3)
    assert set(tick) == {"fused_us", "step_by_step_us", "fused_us_runs", "step_by_step_us_runs"}
    for path in ("fused_us", "step_by_step_us"):
        assert len(tick[f"{path}_runs"]) == 3 and all(v > 0 for v in tick[f"{path}_runs"])
        assert tick[path] == min(tick[f"{path}_runs"])  # the least: a busy host only adds
    with pytest.raises(ValueError, match="n_ticks"):
        speed.firmware_tick(0)
    with pytest.raises(ValueError, match="repeat"):
        speed.firmware_tick(10, repeat=0)


def test_run_batch_reads_the_child_and_its_metrics(tmp_path):
    """A stand-in for ``python -m sitl fly``: burns some CPU, writes metrics.json where --out says."""
    fake = tmp_path / "fake_python.py"
    fake.write_text(textwrap.dedent("""
        import json, pathlib, sys, time
        out = pathlib.Path(sys.argv[sys.argv.index("--out") + 1]); out.mkdir(parents=True)
        t = time.process_time()
        while time.process_time() - t < 0.2:
            pass
        blob = bytearray(64 << 20)  # 64 MB resident
        (out / "metrics.json").write_text(json.dumps({"duration_s": 4.0, "realtime_factor": 2.5, "crashed": False}))
    """))
    wrapper = tmp_path / "python"
    wrapper.write_text(f"#!/bin/sh\nshift 2\nexec {sys.executable} {fake} \"$@\"\n")  # drops "-m sitl"
    wrapper.chmod(0o755)
    r = speed.run_batch("three_link", 4.0, tmp_path, python=str(wrapper))
    assert r["exit_code"] == 0 and r["sim_s"] == 4.0 and r["realtime_factor"] == 2.5
    assert 0.2 / 4.0 <= r["cpu_s_per_sim_s"] < 2.0
    assert r["peak_rss_mb"] > 64


def test_fleet_flight_arguments_are_the_launch_clis(tmp_path):
    from sitl.__main__ import build_parser

    args = build_parser().parse_args(speed.fleet_args("seven_link", 20.0, tmp_path / "f"))
    assert args.command == "launch" and args.speed == 0 and args.no_plots and args.duration == 20.0
    assert args.sim_link == "tcp"
    assert build_parser().parse_args(speed.fleet_args("seven_link", 20.0, tmp_path / "f", "unix")).sim_link == "unix"
    assert args.instance_offset == 0  # fifteen links: PX4 instances from 11, their ports past the GCS's 14550
    assert build_parser().parse_args(speed.fleet_args("fifteen_link", 20.0, tmp_path / "f")).instance_offset == 11
    # beside another fleet (--instance-offset K): every fleet shifted, each still clear of the GCS port
    offsets = {name: build_parser().parse_args(speed.fleet_args(name, 20.0, tmp_path / "f", "tcp", 4)).instance_offset
               for name in ("three_link", "seven_link", "fifteen_link")}
    assert offsets == {"three_link": 4, "seven_link": 15, "fifteen_link": 15}


def test_a_failed_flight_says_why_and_is_no_speed_miss(tmp_path):
    """A child that exits with an error (a port in use, a bad config) is reported with its error
    line, and its target as failed, not missed."""
    fake = tmp_path / "fake_python.py"
    fake.write_text("import sys\nprint('error: ports in use by another process: TCP 4560')\nsys.exit(3)\n")
    wrapper = tmp_path / "python"
    wrapper.write_text(f"#!/bin/sh\nshift 2\nexec {sys.executable} {fake} \"$@\"\n")
    wrapper.chmod(0o755)
    r = speed.run_batch("three_link", 4.0, tmp_path, python=str(wrapper))
    assert r["exit_code"] == 3 and r["error"] == "error: ports in use by another process: TCP 4560"
    r.update(ratio_to_ceiling=None, target_rtf=10.0, target_met=False)
    result = {"compiled": True, "warm_up_s": 0.5, "load_average_at_end": (1.0, 1.0, 1.0), "mujoco_ceiling": {},
              "runs": [r]}
    text = speed.format_speed(result)
    assert "(exit 3)" in text and "failed" in text and "MISSED" not in text
    assert "  error: ports in use by another process: TCP 4560" in text.splitlines()
    assert "failed" in speed.markdown_speed(result) and "**missed**" not in speed.markdown_speed(result)


def _fleet(scenario: str, n_vehicles: int, n_companions: int, rtf: float) -> dict:
    procs = {"harness": {"cpu_s_per_sim_s": 0.5, "loop_cpu_s_per_sim_s": 0.25, "peak_rss_mb": 300.0}}
    procs.update({f"vehicle {i + 1}": {"cpu_s_per_sim_s": 0.12, "loop_cpu_s_per_sim_s": 0.06, "peak_rss_mb": 200.0}
                  for i in range(n_vehicles)})
    procs.update({f"companion g{g + 1}": {"cpu_s_per_sim_s": 0.2, "loop_cpu_s_per_sim_s": 0.1, "peak_rss_mb": 90.0}
                  for g in range(n_companions)})
    return {"mode": "fleet", "scenario": scenario, "sim_link": "unix", "scheduling": "batch", "exit_code": 0,
            "realtime_factor": rtf, "ratio_to_ceiling": rtf / 50.0, "cpu_s_per_sim_s": 1.0, "processes": procs}


def test_the_fleet_scaling_table_sums_the_cpu_by_kind_of_process():
    result = {"compiled": True, "warm_up_s": 0.5, "load_average_at_end": (1.0, 1.0, 1.0), "cpu_count": 2,
              "mujoco_ceiling": {}, "runs": [_fleet("three_link", 3, 1, 4.0), _fleet("fifteen_link", 15, 5, 0.8)]}
    three, fifteen = speed.fleet_scaling(result)
    assert (three["links"], fifteen["links"]) == (3, 15) and fifteen["cpu"] == "in loop"
    assert fifteen["vehicles"] == pytest.approx(0.9) and fifteen["per_vehicle"] == pytest.approx(0.06)
    assert fifteen["companions"] == pytest.approx(0.5) and fifteen["all"] == pytest.approx(0.25 + 0.9 + 0.5)
    # 1.65 CPU s per simulated s at 0.8x: 1.32 of the 2 cores busy; every core busy at 2 / 1.65 = 1.21x
    assert fifteen["cores_busy"] == pytest.approx(1.65 * 0.8) and fifteen["cpu_bound_rtf"] == pytest.approx(2 / 1.65)
    text, md = speed.format_speed(result), speed.markdown_speed(result)
    assert "fleet scaling" in text and "## Fleet scaling" in md and "0.900 (0.060)" in md
    assert "| 1.32 | 1.21 |" in md and "of the machine's 2" in md
    result["runs"][1]["processes"]["harness"]["loop_cpu_s_per_sim_s"] = None  # (over the processes' lives)
    lives = speed.fleet_scaling(result)[1]
    assert lives["cpu"] == "over their lives" and lives["cores_busy"] is None and lives["cpu_bound_rtf"] is None
    vehicles = [int(x.split()[1]) for x in text.splitlines() if x.strip().startswith("vehicle")]
    assert vehicles == [*range(1, 4), *range(1, 16)]  # in their natural order: vehicle 2 before vehicle 10


def test_proc_sampling_and_roles():
    cmd, cpu, hwm = procfs.sample(os.getpid())
    assert "python" in cmd and cpu > 0 and hwm > 0
    assert procfs.sample(2**22 + 12345) is None  # no such process
    assert procfs.role("python -m link_firmware_sim --config x --instance 2 --out y") == "vehicle 3"
    assert procfs.role("python -m companion --config c --out d --group 2") == "companion g2"
    assert procfs.role("python -m companion --config c --out d") == "companion"
    assert procfs.role("python -m pytest") is None


def test_format_and_cli_errors(tmp_path, capsys):
    result = {"compiled": True, "warm_up_s": 0.5, "load_average_at_end": (1.0, 1.0, 1.0),
              "firmware_tick_us": {"fused_us": 21.5, "step_by_step_us": 60.25},
              "mujoco_ceiling": {"three_link": {"realtime_factor": 40.0, "cpu_s_per_sim_s": 0.02}},
              "runs": [{"mode": "fleet", "scenario": "three_link", "sim_link": "unix", "scheduling": "batch",
                        "exit_code": 0, "realtime_factor": 2.0,
                        "ratio_to_ceiling": 0.05, "cpu_s_per_sim_s": 1.5,
                        "loop_cpu_s_per_sim_s": 0.75,
                        "processes": {"harness": {"cpu_s_per_sim_s": 0.5, "loop_cpu_s_per_sim_s": 0.25,
                                                  "peak_rss_mb": 300.0}}}]}
    text = speed.format_speed(result)
    assert "fleet three_link (unix)" in text and "0.050" in text and "harness" in text
    assert "fleets' scheduling policy: batch" in text
    assert "in loop" in text and "0.750" in text and "0.250" in text
    assert "21.5 us one-kernel" in text and "60.2 us step by step" in text
    assert "MISSED" not in text and "target" not in text.splitlines()[-1]  # (judged by run_speed: below)
    assert bench_main(["sitl", "--batch", "no_such_scenario", "--fleet", "", "--out", str(tmp_path / "x"),
                       "--quiet", "--ceiling-duration", "0.01"]) == 2
    assert "no_such_scenario" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:  # (argparse: a duration is a finite number > 0)
        bench_main(["sitl", "--duration", "0", "--out", str(tmp_path / "y")])
    assert refused.value.code == 2 and "a duration is a finite number" in capsys.readouterr().err
    json.dumps(result)


def test_median_of_repeated_runs_and_its_report():
    runs = [{"realtime_factor": x, "cpu_s_per_sim_s": c, "scenario": "three_link", "mode": "batch", "exit_code": 0}
            for x, c in ((8.0, 0.30), (6.0, 0.40), (9.5, 0.28), (None, 0.5))]
    m = speed.median_of(runs)
    assert m["realtime_factor"] == 8.0 and m["cpu_s_per_sim_s"] == 0.30  # the median run, whole
    assert m["realtime_factor_runs"] == [8.0, 6.0, 9.5, None]
    assert m["cpu_s_per_sim_s_runs"] == [0.30, 0.40, 0.28, 0.5]
    assert speed.median_of(runs[:2])["realtime_factor"] == 6.0  # the lower middle of an even count
    assert "realtime_factor_runs" not in speed.median_of(runs[:1])
    assert speed.median_of([{"realtime_factor": None}]) == {"realtime_factor": None}
    result = {"compiled": True, "warm_up_s": 0.5, "load_average_at_end": (1.0, 1.0, 1.0), "repeat": 4,
              "mujoco_ceiling": {"three_link": {"realtime_factor": 40.0, "cpu_s_per_sim_s": 0.02}},
              "runs": [dict(m, ratio_to_ceiling=0.2, peak_rss_mb=300.0)]}
    text = speed.format_speed(result)
    assert "median of 4 interleaved runs" in text and "[8.00 6.00 9.50 -]" in text
    with pytest.raises(ValueError, match="repeat"):
        speed.run_speed(Path("."), 1.0, 1.0, (), (), repeat=0)
    with pytest.raises(ValueError, match="sim links shm"):
        speed.run_speed(Path("."), 1.0, 1.0, (), ("three_link",), sim_links=("shm",))


def test_the_targets_are_judged_and_reported():
    """The targets beside each figure and in one closing line: a flight under its target, or
    one that failed, is MISSED; a scenario without a target is not judged."""
    runs = [{"mode": "batch", "scenario": "three_link", "exit_code": 0, "realtime_factor": 10.5},
            {"mode": "batch", "scenario": "seven_link", "exit_code": 0, "realtime_factor": 4.9},
            {"mode": "batch", "scenario": "seven_link_cpg", "exit_code": 0, "realtime_factor": 4.0},
            {"mode": "fleet", "scenario": "seven_link", "sim_link": "unix", "exit_code": 0, "realtime_factor": 1.5},
            {"mode": "fleet", "scenario": "seven_link", "sim_link": "tcp", "exit_code": 0, "realtime_factor": 1.1},
            {"mode": "fleet", "scenario": "three_link", "sim_link": "unix", "exit_code": 1, "realtime_factor": 3.5},
            {"mode": "fleet", "scenario": "three_link", "sim_link": "tcp", "exit_code": 1, "realtime_factor": None}]
    for r in runs:
        speed._judge(r)
        r.update(ratio_to_ceiling=None if r["realtime_factor"] is None else 0.1, cpu_s_per_sim_s=0.3)
    assert [r["target_rtf"] for r in runs] == [10.0, 5.0, None, 1.5, 1.5, 3.0, 3.0]
    assert [r["target_met"] for r in runs] == [True, False, None, True, False, False, False]
    tick = {"fused_us": 31.0, "step_by_step_us": 60.0, "target_us": speed.TICK_TARGET_US, "target_met": False}
    result = {"compiled": True, "warm_up_s": 0.5, "load_average_at_end": (1.0, 1.0, 1.0), "firmware_tick_us": tick,
              "mujoco_ceiling": {"three_link": {"realtime_factor": 130.0, "cpu_s_per_sim_s": 0.01},
                                 "seven_link": {"realtime_factor": 57.0, "cpu_s_per_sim_s": 0.02}},
              "runs": runs}
    lines = speed.format_speed(result).splitlines()
    assert any(line.startswith("firmware tick") and line.endswith("(target <= 30 us: MISSED)") for line in lines)
    row = {line.split("  ")[0]: line for line in lines}
    assert ">= 10x met" in row["batch three_link"] and ">= 5x MISSED" in row["batch seven_link"]
    assert "met" not in row["batch seven_link_cpg"] and "MISSED" not in row["batch seven_link_cpg"]
    assert ">= 1.5x met" in row["fleet seven_link (unix)"] and ">= 1.5x MISSED" in row["fleet seven_link (tcp)"]
    assert lines[-1] == ("targets met: batch three_link >= 10x, fleet seven_link (unix) >= 1.5x; missed: firmware "
                         "tick <= 30 us, batch seven_link >= 5x, fleet seven_link (tcp) >= 1.5x, fleet three_link "
                         "(unix) >= 3x, fleet three_link (tcp) >= 3x (MuJoCo alone, the machine's phase: three_link "
                         "130x, seven_link 57x)")
    json.dumps(result)


def test_batch_parts_account_for_the_whole_flight():
    """The breakdown of a short batch flight: every part took time, the parts add up to the
    flight's wall time (the loop is the rest, not negative), the quiet ticks ran in the batch, and
    the report's row puts MuJoCo alone beside them."""
    from sitl.bench.batch_parts import PARTS, batch_parts, markdown_batch_parts

    p = batch_parts(speed.scenario_file("three_link"), 0.4, warm_s=0.2)
    ms = p["ms_per_sim_s"]
    assert list(ms) == list(PARTS) and all(ms[k] > 0.0 for k in PARTS), ms
    assert sum(ms.values()) == pytest.approx(p["total_ms_per_sim_s"])
    assert p["realtime_factor"] == pytest.approx(1e3 / p["total_ms_per_sim_s"])
    assert p["batch_counts"]["ticks"] > 100 and 0.0 < p["batch_kernel_ms_per_sim_s"] < ms["firmware"]
    text = markdown_batch_parts({"three_link": p}, {"three_link": {"realtime_factor": 200.0}})
    assert "| three_link |" in text and "| 5.0 |" in text and "firmware" in text

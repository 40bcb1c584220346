"""The pure parts of ``python -m sitl.bench soak`` (sitl/bench/soak.py) on synthetic series: the
windows after the warm-up, the window means, the growth fit per simulated hour, the simulated
time of each sample, the process keys (the role mapping shared with the speed bench), and the
command's options. No fleet flies here."""

from __future__ import annotations

import os

import numpy as np
import pytest

from sitl.bench import procfs, soak, speed
from sitl.bench.__main__ import build_parser


def test_windows_skip_the_warm_up_then_take_a_tenth_at_each_end():
    w = soak.windows(3600.0)
    assert w["fit"] == (60.0, 3600.0)  # 60 s < 10 % of an hour
    assert w["first"] == pytest.approx((60.0, 414.0)) and w["last"] == pytest.approx((3246.0, 3600.0))
    w = soak.windows(300.0)  # a short flight: 10 % (30 s) is the smaller warm-up
    assert w["fit"] == (30.0, 300.0) and w["first"] == pytest.approx((30.0, 57.0))
    # latency: ten minutes at each end of a long flight, 10 % of a short one
    assert soak.latency_windows(3600.0) == {"first": (60.0, 660.0), "last": (3000.0, 3600.0)}
    assert soak.latency_windows(600.0)["first"] == pytest.approx((60.0, 114.0))


def test_growth_fit_and_window_means_on_a_linear_series():
    t = np.arange(0.0, 3601.0, 15.0)
    y = 100.0 + 64.0 * t / 3600.0  # +64 MB per simulated hour
    y[t < 60] = 500.0  # a warm-up spike the figures must leave out
    y[::7] = np.nan  # samples where the process was not read
    res = soak.analyse(t, {"companion": y}, {"companion": np.full_like(t, 11.0)}, 2.0 + t / 360.0, t_end=3600.0)
    c = res["processes"]["companion"]
    assert c["rss_mb_per_sim_h"] == pytest.approx(64.0)
    assert c["rss_mb_first"] == pytest.approx(100.0 + 64.0 * (60 + 414) / 2 / 3600, abs=0.5)
    assert c["rss_mb_last"] == pytest.approx(100.0 + 64.0 * (3246 + 3600) / 2 / 3600, abs=0.5)
    assert c["growth_pct"] == pytest.approx(100.0 * (c["rss_mb_last"] - c["rss_mb_first"]) / c["rss_mb_first"])
    assert c["fds_first"] == c["fds_last"] == 11.0 and c["fds_per_sim_h"] == 0.0
    assert res["run_folder"]["mb_per_sim_h"] == pytest.approx(10.0)
    # an empty window: the sample nearest its middle; nothing at all: None
    assert soak.window_mean([0.0, 10.0], [1.0, 2.0], 8.0, 9.0) == 2.0
    assert soak.window_mean([np.nan], [1.0], 0.0, 1.0) is None
    assert soak.growth_per_hour([5.0, 5.0], [1.0, 2.0]) is None


def test_latency_percentiles_per_window():
    t = np.linspace(0.0, 3600.0, 36001)
    lat = np.column_stack([t, np.where(t < 1800, 0.002, 0.010)])  # 2 ms, then 10 ms
    out = soak.latency_stats(lat, 3600.0)
    assert out["first"]["p50"] == pytest.approx(2.0) and out["last"]["p99"] == pytest.approx(10.0)
    assert soak.latency_stats(np.zeros((0, 2)), 600.0) is None


def test_sample_times_from_progress_else_the_lockstep_markers():
    wall = np.array([0.0, 5.0, 10.0, 15.0, 20.0])
    t, src = soak.sim_times(wall, np.array([np.nan, 10.0, 30.0, 50.0, np.nan]), {})
    assert src == "progress" and t[2] == 30.0
    marks = {"start_wall": 5.0, "end_wall": 15.0, "start_t": 0.0, "end_t": 100.0}
    t, src = soak.sim_times(wall, np.full(5, np.nan), marks)
    assert src == "lockstep markers"
    np.testing.assert_allclose(t, [np.nan, 0.0, 50.0, 100.0, np.nan])
    assert soak.sim_times(wall, np.full(5, np.nan), {})[1] == "none"


def test_process_keys_reuse_the_fleet_roles():
    assert speed.procfs is procfs  # one sampler, shared
    cmds = {10: "python -m sitl launch", 11: "python -m link_firmware_sim --instance 0", 12: "python -m companion --c x",
            13: "python -m sitl.fleet.wire a", 14: "python -m sitl.fleet.wire b", 15: "sh -c true",
            16: "python -m link_firmware_sim --instance 0"}
    keys = soak.process_keys({pid: procfs.role(c) for pid, c in cmds.items()}, harness_pid=10)
    assert keys == {10: "harness", 11: "vehicle 1", 12: "companion", 13: "wire", 14: "wire #2", 16: "vehicle 1 #2"}
    rss, fds = procfs.memory(os.getpid())
    assert rss > 1000 and fds >= 3
    assert procfs.memory(2**22 + 12345) is None


def test_disk_usage_and_the_options(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "f.bin").write_bytes(b"x" * 100_000)
    assert procfs.disk_usage(tmp_path) >= 100_000 and procfs.disk_usage(tmp_path / "nope") == 0
    args = build_parser().parse_args(["soak"])
    assert (args.config, args.duration, args.sample_s, args.doc) == ("three_link", 3600.0, 5.0, None)
    args = build_parser().parse_args(["soak", "--duration", "600", "--sample-s", "2", "--doc", "--json", "x.json"])
    assert (args.duration, args.sample_s, args.json, args.doc) == (600.0, 2.0, "x.json", "docs/bench/soak.md")
    assert soak.resolve_config("three_link").name == "three_link.toml"

"""Scenarios over many seeds (sitl.bench.seeds): the Monte Carlo NEES and the static protocol's
aggregation, and the CLI flying real seeded runs."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from sitl.bench.seeds import aggregate_nees, aggregate_static, format_nees, format_static, independent_reduction

from ..paths import ROOT



def _nees_run(seed, mean, k_eff, samples=100):
    blocks = {b: [mean] * 2 for b in ("pos", "vel", "att")}
    return {"seed": seed, "scenario": "x", "nees": {
        "ekf": blocks, "corrected": blocks, "samples": samples,
        "effective_samples": {w: {b: [k_eff] * 2 for b in blocks} for w in ("ekf", "corrected")}}}


def test_monte_carlo_nees_pools_the_effective_samples_of_the_seeds():
    runs = [_nees_run(s, m, 2.0) for s, m in enumerate([2.0, 4.0, 3.3, 2.7])]
    out = aggregate_nees(runs)
    row = out["ekf"]["pos"]
    assert row["mean"] == pytest.approx([3.0, 3.0])
    assert row["effective_samples"] == [8.0, 8.0]
    lo, hi = row["bounds95"][0]
    assert lo < 3.0 < hi and hi - lo > 2.0 and all(row["inside95"])  # 8 samples: a wide band
    many = aggregate_nees([_nees_run(s, 4.0, 500.0) for s in range(10)])  # sharp band, 4 is out
    assert not any(many["corrected"]["att"]["inside95"])
    assert 3.1 < many["bounds95_independent"][1] < 3.2  # 1000 steps
    assert "OUT" in format_nees(many) and "OUT" not in format_nees(out)
    with pytest.raises(ValueError, match="no run has NEES"):
        aggregate_nees([{"seed": 0}])


def test_static_aggregation_mean_spread_and_reduction():
    def run(seed, scale):
        ekf = np.full((7, 3), 0.7 * scale)
        semi = np.full((7, 3), 0.35 * scale)
        return {"seed": seed, "scenario": "s", "static": {
            "std_m": {"ekf": ekf.tolist(), "local": (0.8 * ekf).tolist(), "semi_distributed": semi.tolist(),
                      "truth": np.zeros((7, 3)).tolist()},
            "rms_err_m": {"ekf": ekf.tolist(), "local": (0.8 * ekf).tolist(), "semi_distributed": semi.tolist()}}}

    out = aggregate_static([run(0, 1.0), run(1, 3.0)])
    assert out["std_m"]["ekf"]["mean"][3] == pytest.approx([1.4] * 3)
    assert out["std_m"]["ekf"]["spread"][3][0] == pytest.approx(np.std([0.7, 2.1], ddof=1))
    assert out["reduction_rms"]["chain"] == pytest.approx([2.0] * 3)
    assert out["independent_reduction"] == pytest.approx(math.sqrt(7))
    text = format_static(out)
    assert "thesis 0.558 / 0.542 / 0.098" in text and "sqrt(7) = 2.65" in text
    assert independent_reduction(3) == pytest.approx(math.sqrt(3))


def test_static_protocol_cli_flies_each_seed_into_its_folder_and_repeats(tmp_path):
    """Two short seeds of the resting seven-link chain in two processes: one folder per seed
    with a runnable scenario and its own metrics, figures for every link, seeds that differ."""
    def bench(out, seeds, first=0):
        cmd = [sys.executable, "-m", "sitl.bench", "static", "--seeds", str(seeds), "--seed", str(first),
               "--duration", "6.5", "--jobs", "2", "--quiet", "--out", str(out)]
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stderr[-2000:]
        return res.stdout, json.loads((out / "static.json").read_text())

    text, out = bench(tmp_path / "a", 2)
    assert out["seeds"] == [0, 1] and out["profile"] == "m8" and out["n_links"] == 7
    for seed in (0, 1):
        assert (tmp_path / "a" / f"seed-{seed}" / "scenario.toml").is_file()
        assert (tmp_path / "a" / f"seed-{seed}" / "run.log").is_file()  # the flight's log, not the console
    ekf = np.array(out["rms_err_m"]["ekf"]["mean"])
    assert ekf.shape == (7, 3) and np.all(np.isfinite(ekf)) and np.all(ekf > 0)
    assert np.all(np.array(out["rms_err_m"]["ekf"]["spread"]) > 0)  # the seeds differ
    assert "link 4 std" in text and "semi_distributed" in text
    single = json.loads((tmp_path / "a" / "seed-1" / "metrics.json").read_text())
    assert single["seed"] == 1 and np.array(single["static"]["rms_err_m"]["ekf"]).shape == (7, 3)
    res = subprocess.run([sys.executable, "-m", "sitl.bench", "static", "--config", "configs/sitl/chain/three_link.toml",
                          "--seeds", "1", "--out", str(tmp_path / "c")], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 2 and "resting chain" in res.stderr

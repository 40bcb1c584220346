import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from companion.estimation.sckf import CAParams
from sitl.bench.ekf_chain import ChainRun, rate_divisor, simulate_ekf_chain
from sitl.bench.scaling import run_scaling
from sitl.bench.table2 import evaluate_group_size, run_table2
from sitl.synthetic import ChainMotion


def test_rates_must_be_whole_multiples_of_the_base_tick():
    assert rate_divisor(100.0, 20.0, "sckf") == 5
    with pytest.raises(ValueError, match="not a whole divisor"):
        rate_divisor(100.0, 30.0, "sckf")
    with pytest.raises(ValueError, match="sckf"):
        ChainRun(sckf_rate_hz=33.0)


def test_table2_short_run_layout_and_sckf_beats_ekf(tmp_path):
    path = tmp_path / "t2.json"
    proc = subprocess.run(
        [sys.executable, "-m", "sitl.bench", "table2", "--duration", "3", "--json", str(path), "--out",
         str(tmp_path / "run"), "--quiet"],
        capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert "EKF only" in proc.stdout
    result = json.loads(path.read_text())
    assert set(result["ekf_only"]) >= {"pos_err_m", "quat_err"}
    assert set(result["groups"]) == {"2", "3", "4", "6", "12"}
    for row in result["groups"].values():
        assert set(row) >= {"time_s", "pos_err_m", "quat_err"}
        assert row["time_s"] > 0
        assert row["pos_err_m"] < result["ekf_only"]["pos_err_m"]
    assert result["protocol"]["sckf_steps"] == 60
    replay_in = np.load(tmp_path / "run" / "ekf_stream.npz")
    assert replay_in["P"].shape == (60, 12, 9, 9)


def _short_run(n=6, duration=2.0):
    return ChainRun(motion=replace(ChainMotion(), n_links=n), duration_s=duration)


def test_same_seed_same_numbers():
    run = _short_run()
    a, sa = run_table2(seed=5, run=run, group_sizes=(2, 3, 6))
    b, sb = run_table2(seed=5, run=run, group_sizes=(2, 3, 6))
    for key in ("p", "q", "P"):
        np.testing.assert_array_equal(getattr(sa, key), getattr(sb, key))
    assert a["ekf_only"] == b["ekf_only"]
    for g in a["groups"]:
        for field in ("pos_err_m", "quat_err", "mean_iterations_per_group", "residual_after_mean"):
            assert a["groups"][g][field] == b["groups"][g][field]
    c, _ = run_table2(seed=6, run=run, group_sizes=(2,))
    assert c["ekf_only"]["pos_err_m"] != a["ekf_only"]["pos_err_m"]


def test_group_size_evaluation_reduces_constraint_error():
    stream = simulate_ekf_chain(_short_run(n=8), seed=1)
    row = evaluate_group_size(stream, 4, CAParams(eps=0.01))
    # Two groups of 4: each local residual <= eps, the one group joint closed exactly.
    assert row["residual_after_max"] <= np.sqrt(2) * 0.01 + 1e-9
    assert row["groups"] == 2


def test_scaling_reports_all_variants():
    result = run_scaling(seed=0, link_counts=(3, 5), duration_s=1.0, transient_s=0.5)
    for key in ("full", "semi2", "full_dense_reference"):
        assert set(result[key]) == {"3", "5"}
        assert all(v > 0 for v in result[key].values())

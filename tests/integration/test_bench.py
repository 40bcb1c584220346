import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from companion.estimation.sckf import CAParams
from companion.estimation.so3 import quat_from_rotvec, quat_mul
from link_firmware_sim.estimators import EkfConfig
from sitl.bench.ekf_chain import (
    ChainRun,
    EkfStream,
    consistent_ekf_config,
    drift_seen,
    ekf_config,
    honest_noise,
    simulate_ekf_chain,
)
from sitl.bench.scaling import run_scaling
from sitl.bench.table2 import (
    aggregate_seeds,
    combine_configs,
    evaluate_group_size,
    format_table2_configs,
    nees_summary,
    run_table2,
    run_table2_configs,
)
from sitl.plant.schedule import rate_divisor
from sitl.synthetic import ChainMotion, SensorModel


def test_rates_must_be_whole_multiples_of_the_base_tick():
    assert rate_divisor(100.0, 20.0, "sckf") == 5
    with pytest.raises(ValueError, match="not a whole divisor"):
        rate_divisor(100.0, 30.0, "sckf")
    with pytest.raises(ValueError, match="sckf"):
        ChainRun(sckf_rate_hz=33.0)


NEES_FIELDS = {"nees", "nees_std", "nees_effective_samples", "nees_bounds95", "nees_inside95"}


def test_table2_short_run_layout_and_sckf_beats_ekf(tmp_path):
    path = tmp_path / "t2.json"
    proc = subprocess.run(
        [sys.executable, "-m", "sitl.bench", "table2", "--duration", "1.5", "--seeds", "2", "--json", str(path), "--out",
         str(tmp_path / "run"), "--quiet"],
        capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert "EKF only" in proc.stdout
    assert "EKF tuning: paper" in proc.stdout and "EKF tuning: consistent" in proc.stdout
    assert "NEES per 3-dof block" in proc.stdout
    result = json.loads(path.read_text())
    assert result["ekf_configs"] == ["paper", "consistent"]
    assert result["protocol"]["sckf_steps"] == 30 and result["protocol"]["seeds"] == [0, 1]
    for name, agg in result["by_ekf"].items():
        assert agg["protocol"]["ekf_config"] == name
        assert agg["protocol"]["ekf"]["att_var_rad2"] == ekf_config(name).att_var_rad2
        assert set(agg["ekf_only"]) >= {"pos_err_m", "quat_err"} | NEES_FIELDS
        assert set(agg["groups"]) == {"2", "3", "4", "6", "12"}
        for row in [agg["ekf_only"], *agg["groups"].values()]:
            assert set(row["nees"]) == {"pos", "vel", "att"}
            for block, (lo, hi) in row["nees_bounds95"].items():
                assert 0 < lo < 3 < hi
                assert row["nees_effective_samples"][block] >= 1
                assert row["nees_inside95"][block] == (lo <= row["nees"][block] <= hi)
        for row in agg["groups"].values():
            assert set(row) >= {"time_s", "pos_err_m", "quat_err"}
            assert row["time_s"] > 0
            assert row["pos_err_m"] < agg["ekf_only"]["pos_err_m"]
    for name in ("ekf_stream.npz", "ekf_stream_consistent.npz"):
        replay_in = np.load(tmp_path / "run" / name)
        assert replay_in["P"].shape == (30, 12, 9, 9)
    p_paper = np.load(tmp_path / "run" / "ekf_stream.npz")["P"]
    p_cons = np.load(tmp_path / "run" / "ekf_stream_consistent.npz")["P"]
    assert not np.allclose(p_paper, p_cons)


def test_table2_single_tuning_option(tmp_path):
    path = tmp_path / "t2.json"
    proc = subprocess.run(
        [sys.executable, "-m", "sitl.bench", "table2", "--duration", "0.5", "--seeds", "1", "--ekf", "consistent", "--json",
         str(path), "--out", str(tmp_path / "run"), "--quiet"],
        capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(path.read_text())
    assert result["ekf_configs"] == ["consistent"] and list(result["by_ekf"]) == ["consistent"]
    assert "EKF tuning: paper" not in proc.stdout
    assert (tmp_path / "run" / "ekf_stream_consistent.npz").exists()
    assert not (tmp_path / "run" / "ekf_stream.npz").exists()


def test_drift_seen_limits():
    var, f1, f2 = 0.04, 0.02, 0.1
    assert drift_seen(var, f1, f2, 1e-6) == pytest.approx(var, rel=1e-6)  # short memory: follows the drift
    tau = 1e4  # long memory: the drift is averaged out as 1 / (2 pi tau)^2 f1 f2
    assert drift_seen(var, f1, f2, tau) == pytest.approx(var / ((2 * np.pi * tau) ** 2 * f1 * f2), rel=1e-3)
    # A single frequency: the first-order low-pass gain.
    assert drift_seen(var, 0.05, 0.05, 3.0) == pytest.approx(var / (1 + (2 * np.pi * 0.05 * 3.0) ** 2))


def test_honest_noise_claims_what_the_filter_errs():
    white, drift, rate, tau = 0.1, 0.03, 10.0, 2.0
    R, q = honest_noise(white, drift, rate, tau)
    n = tau * rate
    assert np.sqrt(R / (q * rate)) == pytest.approx(tau)  # the memory it was built for
    assert R / n == pytest.approx(white / (2 * n) + drift)  # claimed = white averaged + drift left


def test_consistent_config_follows_the_sensor_model():
    cfg = consistent_ekf_config()
    # Carries the drift: far above the white noise alone (0.1 m^2, 0.04 rad^2).
    assert 0.4 < cfg.gps_pos_var_m2 < 0.7 and 0.1 < cfg.att_var_rad2 < 0.25
    assert cfg.noise.att_rad2_s < 1e-4 < cfg.noise.pos_m2_s < 0.1
    assert cfg.gps_vel_var_m2_s2 == SensorModel().gps_vel_var_m2_s2  # velocity has no drift
    no_drift = consistent_ekf_config(SensorModel(pos_drift_amp_m=0.0, att_drift_amp_rad=0.0))
    assert no_drift.gps_pos_var_m2 == pytest.approx(0.05) and no_drift.att_var_rad2 == pytest.approx(0.02)
    assert ekf_config("paper") == EkfConfig()
    with pytest.raises(ValueError, match="unknown EKF config"):
        ekf_config("tuned")


def test_nees_summary_is_three_for_errors_drawn_from_the_covariance():
    rng = np.random.default_rng(3)
    K, n = 300, 4
    A = rng.normal(size=(n, 9, 9))
    P = np.broadcast_to(A @ np.swapaxes(A, 1, 2) * 0.01 + 0.01 * np.eye(9), (K, n, 9, 9)).copy()
    err = np.einsum("knij,knj->kni", np.linalg.cholesky(P), rng.normal(size=(K, n, 9)))
    q = quat_from_rotvec(rng.normal(size=(K, n, 3)) * 0.3)
    q_true = quat_mul(quat_from_rotvec(err[..., 6:9]), q)  # truth = Exp(dtheta) (x) estimate
    zeros = np.zeros((K, n, 3))
    stream = EkfStream(t=np.arange(K) * 0.05, p=zeros, v=zeros, q=q, w=zeros, P=P, d=np.zeros((n, 3)),
                       p_true=err[..., 0:3], v_true=err[..., 3:6], q_true=q_true)
    out = nees_summary(stream, stream.p, stream.v, stream.q, stream.P)
    for block in ("pos", "vel", "att"):
        lo, hi = out["nees_bounds95"][block]
        assert lo <= out["nees"][block] <= hi
        assert out["nees_effective_samples"][block] > 0.7 * K * n  # white errors: nearly every sample counts
    # Claiming half the variance doubles the NEES, outside the bounds.
    over = nees_summary(stream, stream.p, stream.v, stream.q, 0.5 * stream.P)
    assert over["nees"]["pos"] == pytest.approx(2 * out["nees"]["pos"])
    assert over["nees"]["pos"] > over["nees_bounds95"]["pos"][1]


def test_consistent_tuning_is_consistent_where_the_paper_tuning_is_over_confident():
    """Short seeded runs: the paper's tuning (drift unmodelled) claims too little position error;
    the consistent one averages a NEES near 3 in every block, and is more accurate in attitude."""
    run = _short_run(n=6, duration=5.0)
    per_seed = {"paper": [], "consistent": []}
    for seed in (0, 1):
        for name, (result, _) in run_table2_configs(seed, run, group_sizes=(6,)).items():
            per_seed[name].append(result)
    agg = {name: aggregate_seeds(res) for name, res in per_seed.items()}
    paper, cons = agg["paper"]["ekf_only"], agg["consistent"]["ekf_only"]
    assert paper["nees"]["pos"] > 4.5
    for block in ("pos", "vel", "att"):
        assert 1.5 < cons["nees"][block] < 4.5, (block, cons["nees"])
    assert cons["quat_err"] < 0.8 * paper["quat_err"]
    text = format_table2_configs(combine_configs(agg))
    assert "paper" in text and "consistent" in text and "NEES" in text


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
        for field in ("pos_err_m", "quat_err", "mean_iterations_per_group", "residual_after_mean", "nees"):
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


def test_the_companion_bench_times_both_paths_in_their_own_processes(tmp_path, compiled_kernels):
    """``python -m sitl.bench companion`` (short): the numpy path's child runs without numba's
    kernels and the compiled path's with them; each reports every step and target set it timed,
    the cycle's figures and the margin to the 50 ms budget, in the JSON and the report."""
    out = tmp_path / "bench"
    proc = subprocess.run([sys.executable, "-m", "sitl.bench", "companion", "--config", "configs/sitl/chain/three_link.toml",
                           "--duration", "8", "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((out / "companion.json").read_text())
    numpy_path, compiled = result["paths"]["numpy"], result["paths"]["compiled"]
    assert not numpy_path["compiled"] and compiled["compiled"]
    for r in (numpy_path, compiled):
        assert r["n_links"] == 3 and r["budget_ms"] == pytest.approx(50.0) and not r["crashed"]
        assert r["step_ms"]["count"] >= 40 and r["targets_ms"]["count"] >= r["step_ms"]["count"]  # 20 Hz steps, faster targets
        assert 0 < r["step_ms"]["p50"] <= r["step_ms"]["max"] and 0 < r["targets_ms"]["p50"] <= r["targets_ms"]["max"]
        assert r["cycle_worst_ms"] >= r["cycle_mean_ms"] > 0 and r["margin"] == pytest.approx(50.0 / r["cycle_worst_ms"])
    assert "numpy" in proc.stdout and "margin" in (out / "companion.md").read_text()
    short = subprocess.run([sys.executable, "-m", "sitl.bench", "companion", "--config", "configs/sitl/chain/three_link.toml",
                            "--duration", "3", "--out", str(tmp_path / "short")], capture_output=True, text=True, timeout=60)
    assert short.returncode == 2 and "take-off" in short.stderr and "Traceback" not in short.stderr

"""A finished run by time (sitl.view.timeline): the rows a frame shows, the series of the panel,
hostile logs and run folders."""

import logging
import shutil

import numpy as np
import pytest

from sitl.view.timeline import RunUnreadable, Timeline, open_run

from ..paths import SITL_CONFIGS

T0 = 10.0  # the log does not start at 0
K, N, G = 50, 3, 2  # log rows (50 Hz), links, companion groups


def _unit_quats(rng, *shape):
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def make_log(k: int = K, n: int = N, seed: int = 0) -> dict[str, np.ndarray]:
    """A log.npz's arrays: rows at 50 Hz from T0, companion steps at 20 Hz from T0 + 0.03 s (every
    other step exactly at a log sample's time). Row k's truth is about k, step j's correction j."""
    rng = np.random.default_rng(seed)
    t = T0 + np.arange(k) / 50.0
    # steps at T0 + 0.03 + 0.05 j: j even t[1 + 5m] + 0.01, j odd exactly t[4 + 5m]
    t_sckf = np.sort(np.concatenate((t[1::5] + 0.01, t[4::5])))
    s = len(t_sckf)
    log = {"t": t,
           "p_true": np.arange(k, dtype=float)[:, None, None] + rng.uniform(0, 0.1, (k, n, 3)),
           "q_true": _unit_quats(rng, k, n),
           "p_ekf": rng.normal(size=(k, n, 3)), "q_ekf": _unit_quats(rng, k, n),
           "p_target": rng.normal(size=(k, n, 3)), "q_target": _unit_quats(rng, k, n),
           "link_state": rng.integers(0, 128, (k, n)).astype(np.uint8),
           "correction_latency_ms": rng.uniform(0, 50, (k, n)),
           "t_sckf": t_sckf,
           "p_ekf_sckf": rng.normal(size=(s, n, 3)),
           "p_corr_sckf": np.arange(s, dtype=float)[:, None, None] + rng.uniform(0, 0.1, (s, n, 3)),
           "q_corr_sckf": _unit_quats(rng, s, n),
           "con_pos_before": rng.uniform(0, 0.05, (s, n - 1)),
           "con_pos_after": rng.uniform(0, 0.005, (s, n - 1)),
           "global_applied": rng.random((s, G)) < 0.5,
           "iterations": rng.integers(1, 5, s)}
    log["correction_latency_ms"][3] = np.nan
    return log


def expected_rows(log, t_s):
    """Brute force: the newest log row at or before ``t_s`` (the first before the start) and the
    newest step at or before that row's time (``None``: none)."""
    t, ts = log["t"], log["t_sckf"]
    k = max([i for i in range(len(t)) if t[i] <= t_s], default=0)
    j = max([i for i in range(len(ts)) if ts[i] <= t[k]], default=None)
    return k, j


def check_frame(f, log, k, j):
    assert f.t_s == log["t"][k]
    np.testing.assert_array_equal(f.truth.p_w_m, log["p_true"][k])
    np.testing.assert_array_equal(f.truth.q_wxyz, log["q_true"][k])
    np.testing.assert_array_equal(f.ekf.p_w_m, log["p_ekf"][k])
    np.testing.assert_array_equal(f.target.q_wxyz, log["q_target"][k])
    np.testing.assert_array_equal(f.link_state, log["link_state"][k])
    if j is None:
        assert f.step_t_s is None and f.corrected is None and f.correction_from_w_m is None
        assert "constraint_before_mm" not in f.figures
    else:
        assert f.step_t_s == log["t_sckf"][j]
        np.testing.assert_array_equal(f.corrected.p_w_m, log["p_corr_sckf"][j])
        np.testing.assert_array_equal(f.correction_from_w_m, log["p_ekf_sckf"][j])
        np.testing.assert_array_equal(f.correction_to_w_m, log["p_corr_sckf"][j])
        assert f.figures["constraint_before_mm"] == pytest.approx(1e3 * log["con_pos_before"][j].max())
        assert f.figures["global_step"] == pytest.approx(log["global_applied"][j].mean())


@pytest.fixture
def log():
    return make_log()


def test_the_synthetic_steps_are_at_20_hz_and_some_at_log_samples(log):
    np.testing.assert_allclose(np.diff(log["t_sckf"]), 0.05, atol=1e-12)
    assert log["t_sckf"][1] == log["t"][4]  # exactly: the at-or-before case is exercised


def test_frame_exactly_at_each_sample(log):
    tl = Timeline(log)
    assert (tl.n, tl.start_s, tl.end_s) == (N, log["t"][0], log["t"][-1])
    for k, t in enumerate(log["t"]):
        kk, j = expected_rows(log, t)
        assert kk == k
        check_frame(tl.frame(t), log, k, j)


def test_frame_between_samples_is_the_row_before(log):
    tl = Timeline(log)
    for k, t in enumerate(log["t"][:-1]):
        check_frame(tl.frame(t + 0.015), log, k, expected_rows(log, t)[1])


@pytest.mark.parametrize("t_s, k, j", [
    (T0 - 5.0, 0, None),  # before the start: the first row
    (-np.inf, 0, None),
    (T0, 0, None),  # the first step is at T0 + 0.03
    (T0 + 0.035, 1, None),  # after the first step, but the row shown (T0 + 0.02) is before it
    (T0 + 0.04, 2, 0),
    (T0 + 0.08, 4, 1),  # a step exactly at the row's time
    (T0 + 0.0999, 4, 1),
    (T0 + 0.98, K - 1, 19),  # the last row, its step exactly at it
    (T0 + 1e6, K - 1, 19),  # after the end: the last row
    (np.inf, K - 1, 19),
])
def test_frame_at_the_edges(log, t_s, k, j):
    assert expected_rows(log, t_s) == (k, j)
    check_frame(Timeline(log).frame(t_s), log, k, j)


def test_frame_at_random_times_matches_brute_force(log):
    tl = Timeline(log)
    for t_s in np.random.default_rng(1).uniform(T0 - 0.2, T0 + 1.2, 200):
        check_frame(tl.frame(t_s), log, *expected_rows(log, t_s))


def test_a_log_without_steps_has_no_step_rows(log):
    for key in ("t_sckf", "p_ekf_sckf", "p_corr_sckf", "q_corr_sckf", "con_pos_before", "con_pos_after",
                "global_applied", "iterations"):
        del log[key]
    tl = Timeline(log)
    f = tl.frame(T0 + 0.5)
    assert f.step_t_s is None and f.corrected is None
    assert set(tl.series()) == {"tracking_cm", "latency_ms"}


def test_an_empty_step_log_is_no_step_log(log):
    log["t_sckf"] = np.zeros(0)
    tl = Timeline(log)
    assert tl.frame(T0 + 0.5).step_t_s is None
    assert "global_step" not in tl.series()


def test_series_times_and_values(log):
    series = Timeline(log).series()
    assert set(series) == {"tracking_cm", "latency_ms", "constraint_before_mm", "constraint_after_mm", "global_step"}
    for name in ("tracking_cm", "latency_ms"):
        times, values = series[name]
        np.testing.assert_array_equal(times, log["t"])
        assert values.shape == (K,)
    for name in ("constraint_before_mm", "constraint_after_mm", "global_step"):
        times, values = series[name]
        np.testing.assert_array_equal(times, log["t_sckf"])
        assert values.shape == (len(log["t_sckf"]),)
    np.testing.assert_allclose(series["tracking_cm"][1],
                               100 * np.linalg.norm(log["p_true"] - log["p_target"], axis=-1).max(axis=1))
    np.testing.assert_allclose(series["latency_ms"][1][3], np.nan, equal_nan=True)
    np.testing.assert_allclose(series["latency_ms"][1][4], log["correction_latency_ms"][4].max())
    np.testing.assert_allclose(series["constraint_after_mm"][1], 1e3 * log["con_pos_after"].max(axis=1))
    np.testing.assert_allclose(series["global_step"][1], log["global_applied"].mean(axis=1))


def test_load_rows_by_time(log):
    load_t = T0 + 0.1 + np.arange(10) / 10.0
    load = {"load_t": load_t, "load_p_true": np.arange(10.0)[:, None] * np.ones(3),
            "load_q_true": np.tile([1.0, 0, 0, 0], (10, 1))}
    tl = Timeline(log, load)
    assert tl.frame(T0 + 0.08).load is None  # before the load's first row
    f = tl.frame(T0 + 0.35)  # row at T0 + 0.34: the load's row at T0 + 0.3
    np.testing.assert_array_equal(f.load.p_w_m, [2.0, 2.0, 2.0])
    assert Timeline(log, {"load_t": np.zeros(0)}).frame(T0 + 0.5).load is None


def _drop(key):
    def mutate(log):
        del log[key]
    return mutate


def _set(key, value):
    def mutate(log):
        log[key] = value(log) if callable(value) else value
    return mutate


def _t_with_nan(log):
    t = log["t"].copy()
    t[7] = np.nan
    return t


def _t_going_back(log):
    t = log["t"].copy()
    t[7], t[8] = t[8], t[7]
    return t


def _empty_truth(log):
    log["t"], log["p_true"], log["q_true"] = np.zeros(0), np.zeros((0, N, 3)), np.zeros((0, N, 4))


@pytest.mark.parametrize("mutate, match", [
    (_drop("p_true"), "p_true"),
    (_drop("q_true"), "q_true"),
    (_drop("t"), r"\(t, p_true"),
    (_set("p_true", np.zeros((K, N, 2))), "p_true"),
    (_set("p_true", np.zeros((K - 1, N, 3))), "p_true"),
    (_set("p_true", np.zeros((K, 3))), "p_true"),
    (_set("q_true", np.zeros((K, N + 1, 4))), "q_true"),
    (_set("q_true", np.zeros((K, N, 3))), "q_true"),
    (_set("t", _t_with_nan), r"^t: .*finite"),
    (_set("t", _t_going_back), r"^t: .*go back"),
    (_set("t", lambda log: np.full(K, np.inf)), r"^t: "),
    (_set("t", lambda log: log["t"][:, None]), r"^t: "),
    (_empty_truth, r"^t: .*non-empty"),
    (_set("t_sckf", lambda log: log["t_sckf"][::-1].copy()), r"^t_sckf: "),
    (_set("t_sckf", lambda log: np.where(np.arange(len(log["t_sckf"])) == 2, np.nan, log["t_sckf"])), r"^t_sckf: "),
], ids=["no p_true", "no q_true", "no t", "p_true xy", "p_true rows", "p_true 2-D", "q_true links",
        "q_true width", "t NaN", "t back", "t inf", "t 2-D", "t empty", "t_sckf back", "t_sckf NaN"])
def test_hostile_logs_are_unreadable(log, mutate, match):
    mutate(log)
    with pytest.raises(RunUnreadable, match=match):
        Timeline(log)


def test_hostile_load_times_are_unreadable(log):
    with pytest.raises(RunUnreadable, match="load_t"):
        Timeline(log, {"load_t": np.array([1.0, 0.5]), "load_p_true": np.zeros((2, 3))})


def test_run_unreadable_is_a_value_error():
    assert issubclass(RunUnreadable, ValueError)


# ---- run folders ----------------------------------------------------------------------------


def _save(run_dir, log):
    run_dir.mkdir(parents=True, exist_ok=True)
    np.savez(run_dir / "log.npz", **log)


def test_open_run_without_a_log(tmp_path):
    with pytest.raises(RunUnreadable, match="no log.npz"):
        open_run(tmp_path)
    (tmp_path / "log.npz").mkdir()  # not a file either
    with pytest.raises(RunUnreadable, match="no log.npz"):
        open_run(tmp_path)


def test_open_run_with_random_bytes(tmp_path):
    (tmp_path / "log.npz").write_bytes(np.random.default_rng(0).bytes(2000))
    with pytest.raises(RunUnreadable, match="log.npz"):
        open_run(tmp_path)


@pytest.mark.parametrize("cut", [0.5, 0.95])
def test_open_run_with_a_truncated_npz(tmp_path, log, cut):
    _save(tmp_path, log)
    data = (tmp_path / "log.npz").read_bytes()
    (tmp_path / "log.npz").write_bytes(data[:int(cut * len(data))])  # a copy cut short, a killed save
    with pytest.raises(RunUnreadable, match="log.npz"):
        open_run(tmp_path)


def test_open_run_with_a_log_lacking_the_truth(tmp_path, log):
    del log["q_true"]
    _save(tmp_path, log)
    with pytest.raises(RunUnreadable, match=r"log\.npz: .*q_true"):
        open_run(tmp_path)


def test_open_run_with_its_scenario(tmp_path, log):
    _save(tmp_path, log)
    shutil.copy(SITL_CONFIGS / "chain" / "three_link.toml", tmp_path / "scenario.toml")
    timeline, spec = open_run(tmp_path)
    assert timeline.n == 3 and len(timeline.t) == K
    assert spec.n == 3 and spec.joined
    assert spec.rotor_positions_b_m.shape == (8, 3)
    assert spec.rotor_directions_b.shape == (8, 3)
    check_frame(timeline.frame(T0 + 0.5), log, *expected_rows(log, T0 + 0.5))


def test_open_run_with_a_load(tmp_path, log):
    _save(tmp_path, log)
    np.savez(tmp_path / "load.npz", load_t=log["t"][::5], load_p_true=np.ones((10, 3)),
             load_q_true=np.tile([1.0, 0, 0, 0], (10, 1)))
    timeline, _ = open_run(tmp_path)
    np.testing.assert_array_equal(timeline.frame(T0 + 0.5).load.p_w_m, np.ones(3))


def _assert_plain_chain(spec, n):
    assert spec.n == n
    assert spec.rotor_positions_b_m is None and spec.rotor_directions_b is None
    assert spec.joined == (n > 1)


def test_open_run_with_a_scenario_of_another_count_falls_back(tmp_path, log, caplog):
    _save(tmp_path, log)
    shutil.copy(SITL_CONFIGS / "chain" / "seven_link.toml", tmp_path / "scenario.toml")
    with caplog.at_level(logging.WARNING):
        timeline, spec = open_run(tmp_path)
    assert timeline.n == 3
    _assert_plain_chain(spec, 3)
    assert "7 links" in caplog.text


@pytest.mark.parametrize("text", [b"this is [not toml", b"\xff\xfe\x00garbage", b"[skeleton]\nn_links = 'three'\n",
                                  b""])
def test_open_run_with_a_garbage_scenario_falls_back(tmp_path, log, text, caplog):
    _save(tmp_path, log)
    (tmp_path / "scenario.toml").write_bytes(text)
    with caplog.at_level(logging.WARNING):
        timeline, spec = open_run(tmp_path)
    assert timeline.n == 3
    _assert_plain_chain(spec, 3)
    assert "default geometry" in caplog.text


@pytest.mark.parametrize("n", [1, 2])
def test_open_run_without_a_scenario(tmp_path, n):
    log = make_log(n=2)
    _save(tmp_path, {"t": log["t"], "p_true": log["p_true"][:, :n], "q_true": log["q_true"][:, :n]})
    timeline, spec = open_run(tmp_path)
    assert timeline.n == n
    _assert_plain_chain(spec, n)


def test_a_replay_shows_the_targets_in_the_truths_frame():
    """A run flown from home (``home_offset_w_m`` in its log): every frame's targets and the
    tracking series are those of the targets less that offset."""
    log = make_log()
    home = np.array([0.3, -0.2, 1.5])
    log["home_offset_w_m"] = home
    tl = Timeline(log)
    for k, t in enumerate(log["t"]):
        np.testing.assert_allclose(tl.frame(t).target.p_w_m, log["p_target"][k] - home, atol=1e-12)
    times, tracking = tl.series()["tracking_cm"]
    want = 100.0 * np.linalg.norm(log["p_true"] - (log["p_target"] - home), axis=-1).max(axis=1)
    np.testing.assert_allclose(tracking, want, atol=1e-9)

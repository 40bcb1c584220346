"""The view's frame of one log row (sitl.view.frame): the figures of rows with and without a time
axis agree, their units, and what a frame holds when the rows lack a part."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sitl.view.frame import FIGURES, Poses, ViewFrame, figures, frame

# a NaN must never make numpy warn (all-NaN rows, links without a target)
pytestmark = pytest.mark.filterwarnings("error")

ROW_FIGURES = ("tracking_cm", "latency_ms")
STEP_FIGURES = ("constraint_before_mm", "constraint_after_mm", "global_step")


def _unit_quats(rng, *shape):
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _with_nans(rng, a: np.ndarray, link_axis: int) -> np.ndarray:
    """``a`` with NaN entries, NaN links and whole NaN time rows."""
    a = a.copy()
    a[rng.random(a.shape) < 0.1] = np.nan
    mask = rng.random(a.shape[:link_axis + 1]) < 0.25  # whole links (all their components)
    a[mask] = np.nan
    a[rng.random(a.shape[0]) < 0.3] = np.nan  # whole rows
    return a


def random_logs(seed: int, K: int, S: int, n: int, g: int):
    rng = np.random.default_rng(seed)
    rows = {"p_true": _with_nans(rng, rng.normal(size=(K, n, 3)), 1),
            "q_true": _unit_quats(rng, K, n),
            "p_target": _with_nans(rng, rng.normal(size=(K, n, 3)), 1),
            "correction_latency_ms": _with_nans(rng, rng.uniform(0, 80, (K, n)), 1)}
    steps = {"con_pos_before": _with_nans(rng, rng.uniform(0, 0.05, (S, n - 1)), 1),
             "con_pos_after": _with_nans(rng, rng.uniform(0, 0.01, (S, n - 1)), 1),
             "global_applied": rng.random((S, g)) < 0.5}
    return rows, steps


def _largest_finite(values) -> float:
    finite = [float(v) for v in np.ravel(values) if math.isfinite(v)]
    return max(finite) if finite else math.nan


@given(seed=st.integers(0, 2**32 - 1), K=st.integers(1, 6), S=st.integers(1, 5), n=st.integers(1, 5),
       g=st.integers(0, 3))
def test_figures_of_whole_arrays_equal_the_figures_of_each_row(seed, K, S, n, g):
    rows, steps = random_logs(seed, K, S, n, g)
    whole = figures(rows, steps)
    assert set(whole) == set(FIGURES)
    for name in ROW_FIGURES:
        assert np.shape(whole[name]) == (K,)
    for name in STEP_FIGURES:
        assert np.shape(whole[name]) == (S,)
    for k in range(K):
        one = figures({key: a[k] for key, a in rows.items()})
        assert set(one) == set(ROW_FIGURES)
        for name in ROW_FIGURES:
            assert np.ndim(one[name]) == 0
            np.testing.assert_allclose(whole[name][k], one[name], rtol=1e-12, equal_nan=True)
        # an independent oracle: the largest finite value over the links, NaN when there is none
        err = [np.sqrt(np.sum((rows["p_true"][k, i] - rows["p_target"][k, i]) ** 2)) for i in range(n)]
        np.testing.assert_allclose(one["tracking_cm"], 100.0 * _largest_finite(err), rtol=1e-12, equal_nan=True)
        np.testing.assert_allclose(one["latency_ms"], _largest_finite(rows["correction_latency_ms"][k]),
                                   equal_nan=True)
    for s in range(S):
        one = figures({}, {key: a[s] for key, a in steps.items()})
        assert set(one) == set(STEP_FIGURES)
        for name in STEP_FIGURES:
            assert np.ndim(one[name]) == 0
            np.testing.assert_allclose(whole[name][s], one[name], rtol=1e-12, equal_nan=True)
        np.testing.assert_allclose(one["constraint_before_mm"], 1e3 * _largest_finite(steps["con_pos_before"][s]),
                                   rtol=1e-12, equal_nan=True)
        np.testing.assert_allclose(one["constraint_after_mm"], 1e3 * _largest_finite(steps["con_pos_after"][s]),
                                   rtol=1e-12, equal_nan=True)
        flags = steps["global_applied"][s]
        np.testing.assert_allclose(one["global_step"], flags.mean() if g else np.nan, equal_nan=True)


def test_units_of_the_figures():
    row = {"p_true": np.zeros((3, 3)),
           "p_target": np.array([[0.01, 0.0, 0.0], [0.03, 0.04, 0.0], [np.nan, 0.0, 0.0]]),
           "correction_latency_ms": np.array([12.0, np.nan, 40.5])}
    step = {"con_pos_before": np.array([0.002, 0.0125]), "con_pos_after": np.array([np.nan, 0.0004]),
            "global_applied": np.array([True, False, False, True])}
    f = figures(row, step)
    assert f["tracking_cm"] == pytest.approx(5.0)  # 100 x 0.05 m, the NaN target left out
    assert f["latency_ms"] == pytest.approx(40.5)
    assert f["constraint_before_mm"] == pytest.approx(12.5)
    assert f["constraint_after_mm"] == pytest.approx(0.4)
    assert f["global_step"] == pytest.approx(0.5)


@pytest.mark.parametrize("row, step, present", [
    ({}, None, set()),
    ({"p_true": np.zeros((2, 3))}, None, set()),  # no target: no tracking error
    ({"p_true": np.zeros((2, 3)), "p_target": np.ones((2, 3))}, None, {"tracking_cm"}),
    ({"correction_latency_ms": np.ones(2)}, {}, {"latency_ms"}),
    ({}, {"con_pos_after": np.ones(1)}, {"constraint_after_mm"}),
    ({}, {"global_applied": np.ones(2, bool), "con_pos_before": np.ones(1)}, {"global_step", "constraint_before_mm"}),
])
def test_a_figure_whose_keys_are_missing_is_left_out(row, step, present):
    assert set(figures(row, step)) == present


def test_all_nan_rows_give_nan():
    K, n = 4, 3
    rows = {"p_true": np.full((K, n, 3), np.nan), "p_target": np.zeros((K, n, 3)),
            "correction_latency_ms": np.full((K, n), np.nan)}
    steps = {"con_pos_before": np.full((K, n - 1), np.nan), "con_pos_after": np.full((K, n - 1), np.nan),
             "global_applied": np.zeros((K, 0), bool)}
    for f in (figures(rows, steps), figures({k: a[0] for k, a in rows.items()}, {k: a[0] for k, a in steps.items()})):
        for name in FIGURES:
            assert np.isnan(f[name]).all(), name


def _row(n=3, **extra):
    row = {"p_true": np.arange(3 * n, dtype=float).reshape(n, 3), "q_true": np.tile([1.0, 0, 0, 0], (n, 1))}
    row.update(extra)
    return row


@pytest.mark.parametrize("missing", ["p_true", "q_true"])
def test_frame_needs_the_truth(missing):
    row = _row()
    del row[missing]
    with pytest.raises(KeyError):
        frame(0.0, row)


def test_frame_of_the_truth_alone():
    f = frame(np.float64(1.5), _row())
    assert isinstance(f, ViewFrame)
    assert f.t_s == 1.5 and type(f.t_s) is float
    np.testing.assert_array_equal(f.truth.p_w_m, np.arange(9.0).reshape(3, 3))
    assert f.truth.known.tolist() == [True, True, True]
    assert f.ekf is None and f.target is None and f.corrected is None and f.load is None
    assert f.step_t_s is None and f.correction_from_w_m is None and f.correction_to_w_m is None
    assert f.link_state is None
    assert f.figures == {}


@pytest.mark.parametrize("step", [None, {}])
def test_no_step_row_no_correction(step):
    f = frame(0.0, _row(p_ekf=np.zeros((3, 3)), q_ekf=np.tile([1.0, 0, 0, 0], (3, 1))), step)
    assert f.ekf is not None
    assert f.corrected is None and f.step_t_s is None and f.correction_from_w_m is None


def test_frame_of_every_part():
    n = 3
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    row = _row(p_ekf=np.ones((n, 3)), q_ekf=q, p_target=np.zeros((n, 3)), q_target=q,
               link_state=np.array([3, 64, 19], dtype=np.uint8), correction_latency_ms=np.array([1.0, 2.0, 3.0]))
    step = {"t_sckf": np.float64(0.95), "p_ekf_sckf": np.full((n, 3), 2.0), "p_corr_sckf": np.full((n, 3), 2.5),
            "q_corr_sckf": q, "con_pos_before": np.array([0.001, 0.002]), "global_applied": np.array([True])}
    load = {"load_p_true": np.array([0.0, 0.0, 1.0]), "load_q_true": np.array([1.0, 0, 0, 0])}
    f = frame(1.0, row, step, load)
    np.testing.assert_array_equal(f.ekf.p_w_m, np.ones((n, 3)))
    np.testing.assert_array_equal(f.target.p_w_m, np.zeros((n, 3)))
    np.testing.assert_array_equal(f.corrected.p_w_m, np.full((n, 3), 2.5))
    np.testing.assert_array_equal(f.correction_from_w_m, np.full((n, 3), 2.0))
    np.testing.assert_array_equal(f.correction_to_w_m, np.full((n, 3), 2.5))
    assert f.step_t_s == 0.95 and type(f.step_t_s) is float
    assert f.link_state.tolist() == [3, 64, 19]
    np.testing.assert_array_equal(f.load.p_w_m, [0.0, 0.0, 1.0])
    assert f.figures == pytest.approx({"tracking_cm": 100 * np.linalg.norm([6.0, 7.0, 8.0]), "latency_ms": 3.0,
                                       "constraint_before_mm": 2.0, "global_step": 1.0})
    assert all(type(v) is float for v in f.figures.values())


def test_step_without_the_estimate_it_used_has_no_correction_arrow():
    q = np.tile([1.0, 0, 0, 0], (2, 1))
    f = frame(0.0, _row(2), {"p_corr_sckf": np.zeros((2, 3)), "q_corr_sckf": q})
    assert f.corrected is not None
    assert f.correction_from_w_m is None and f.correction_to_w_m is None and f.step_t_s is None


def test_poses_known_is_false_for_a_row_with_a_nan():
    p = np.zeros((4, 3))
    q = np.tile([1.0, 0, 0, 0], (4, 1))
    p[1, 2] = np.nan
    q[2, 0] = np.nan
    p[3] = np.inf
    assert Poses(p, q).known.tolist() == [True, False, False, False]
    f = frame(0.0, {"p_true": p, "q_true": q, "p_ekf": np.full((4, 3), np.nan), "q_ekf": q})
    assert f.truth.known.tolist() == [True, False, False, False]
    assert not f.ekf.known.any()


@pytest.mark.parametrize("home", [None, (0.3, -0.2, 1.5)])
def test_the_targets_are_shown_and_judged_in_the_truths_frame(home):
    """The companion flies the trajectory from its home, in the links' frame: a chain that flies it
    exactly shows its targets on the truth and no tracking error, with or without a home."""
    rng = np.random.default_rng(3)
    truth = rng.normal(size=(3, 3))
    row = {"p_true": truth, "q_true": _unit_quats(rng, 3), "q_target": _unit_quats(rng, 3),
           "p_target": truth + (0.0 if home is None else np.asarray(home))}
    if home is not None:
        row["home_offset_w_m"] = np.asarray(home)
    f = frame(1.0, row)
    np.testing.assert_allclose(f.target.p_w_m, truth, atol=1e-12)
    assert f.figures["tracking_cm"] == pytest.approx(0.0, abs=1e-9)

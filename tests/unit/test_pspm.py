"""PSPM in E(3) and SO(3) (thesis sec. 2.3.4): reservoirs never negative, caps, projection, agreement."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat
from link_firmware_sim.controllers.pspm import (
    HapticGains,
    PspmGains,
    PspmModulator,
    haptic_feedback,
    project_to_ellipsoid,
    pspm_init,
    pspm_observe,
    pspm_update,
    so3_log,
)

finite = st.floats(-3.0, 3.0)
vec3 = st.lists(finite, min_size=3, max_size=3).map(np.array)
posk = st.lists(st.floats(0.1, 50.0), min_size=3, max_size=3).map(np.array)


@settings(max_examples=60, deadline=None)
@given(vec3, posk, st.floats(0.0, 10.0))
def test_projection_is_feasible_and_closest(b, k, budget):
    y = project_to_ellipsoid(b, k, budget)
    assert 0.5 * np.sum(k * y * y) <= budget + 1e-9
    if 0.5 * np.sum(k * b * b) <= budget:
        np.testing.assert_array_equal(y, b)
    else:  # no feasible point of a random sample is closer
        rng = np.random.default_rng(0)
        cand = rng.normal(size=(200, 3)) * np.abs(b).max()
        ok = 0.5 * np.sum(k * cand * cand, axis=1) <= budget
        if ok.any():
            assert np.linalg.norm(y - b) <= np.linalg.norm(cand[ok] - b, axis=1).min() + 1e-6


step = st.tuples(vec3, vec3.map(lambda v: v * 0.5), vec3.map(lambda v: v * 0.3), vec3.map(lambda v: v * 2.0),
                 st.integers(1, 8))


@settings(max_examples=30, deadline=None)
@given(st.lists(step, min_size=1, max_size=15), st.floats(0.0, 2.0), st.floats(0.0, 1.0))
def test_reservoirs_never_negative_nor_above_their_caps(steps, e0_t, e0_r):
    """Random operator samples (jumps included) and random slave motion between them."""
    gains = PspmGains(e0_t_j=e0_t, e0_r_j=e0_r)
    state = pspm_init(np.zeros(3), np.array([1.0, 0, 0, 0]), gains, 0.0)
    t, dt = 0.0, 0.002
    p, q = np.zeros(3), np.array([1.0, 0, 0, 0])
    for p_d, rv_d, dp, w, ticks in steps:
        for _ in range(ticks):
            t += dt
            p = p + dp * dt * 10
            state = pspm_observe(state, gains, p, w, dt)
        q = quat_from_rotvec(so3_log(quat_to_rotmat(q)) + 0.1 * w * dt)
        new = pspm_update(state, gains, p_d, quat_from_rotvec(rv_d), p, q, t)
        assert 0.0 <= new.energy_t_j <= gains.e_max_t_j
        assert 0.0 <= new.energy_r_j <= gains.e_max_r_j
        # the bookkeeping: E(k) = E(k-1) + D - dP, unless capped
        raw = state.energy_t_j + new.last["d_t_j"] - new.last["dP_t_j"]
        assert new.energy_t_j == pytest.approx(min(raw, gains.e_max_t_j), abs=1e-9)
        raw_r = state.energy_r_j + new.last["d_r_j"] - new.last["dP_r_j"]
        assert new.energy_r_j == pytest.approx(min(raw_r, gains.e_max_r_j), abs=1e-9)
        state = new


def test_enough_energy_passes_the_operator_unchanged_and_none_holds_the_pose():
    gains = PspmGains(e0_t_j=2.0, e0_r_j=1.0)
    q_d = quat_from_rotvec(np.array([0.0, 0.1, 0.0]))
    s = pspm_update(pspm_init(np.zeros(3), np.array([1.0, 0, 0, 0]), gains, 0.0), gains, np.array([0.1, 0, 0]), q_d,
                    np.zeros(3), np.array([1.0, 0, 0, 0]), 0.01)
    np.testing.assert_allclose(s.p_bar_w_m, [0.1, 0, 0])
    np.testing.assert_allclose(so3_log(quat_to_rotmat(s.q_bar_wxyz)), [0, 0.1, 0], atol=1e-12)
    # empty reservoirs, slave at rest: a 1 m jump is withheld entirely
    empty = PspmGains()
    s = pspm_update(pspm_init(np.zeros(3), np.array([1.0, 0, 0, 0]), empty, 0.0), empty, np.array([1.0, 0, 0]), q_d,
                    np.zeros(3), np.array([1.0, 0, 0, 0]), 0.01)
    np.testing.assert_allclose(s.p_bar_w_m, 0.0, atol=1e-12)
    assert s.energy_t_j == 0.0


def test_modulator_class_agrees_with_functions():
    gains = PspmGains(e0_t_j=0.5)
    rng = np.random.default_rng(2)
    mod = PspmModulator(gains)
    state = None
    t = 0.0
    for _ in range(10):
        p, q, w = rng.normal(size=3), quat_from_rotvec(rng.normal(size=3)), rng.normal(size=3)
        t += 0.008
        mod.observe(p, q, w, t, 0.008)
        state = pspm_init(p, q, gains, t) if state is None else state
        state = pspm_observe(state, gains, p, w, 0.008)
        p_d, q_d = rng.normal(size=3), quat_from_rotvec(rng.normal(size=3))
        mod.update(p_d, q_d, p, q, t)
        state = pspm_update(state, gains, p_d, q_d, p, q, t)
        np.testing.assert_array_equal(mod.state.p_bar_w_m, state.p_bar_w_m)
        assert mod.state.energy_r_j == state.energy_r_j


def test_haptic_feedback_pulls_the_operator_back_to_the_modulated_pose():
    q = np.array([1.0, 0, 0, 0])
    f, tau = haptic_feedback(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0]), q, np.zeros(3), q, np.zeros(3),
                             np.zeros(3), HapticGains())
    assert f[0] < 0 and np.allclose(f[1:], 0) and np.allclose(tau, 0)
    with pytest.raises(ValueError, match="kp_n_m"):
        PspmGains(kp_n_m=(1.0, 0.0, 1.0))

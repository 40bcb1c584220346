"""Eq. 4.2, the pivotboard's decaying-acceleration model (companion.motion.decaying_acceleration):
the model, and its fit recovering known parameters from noisy samples."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.motion.decaying_acceleration import DAModel, fit_decaying_acceleration


def test_the_model_is_eq_4_2():
    m = DAModel(0.5, 0.8, 0.3)
    t = np.linspace(0.0, 5.0, 11)
    v = m.velocity(t, 0.1)
    np.testing.assert_allclose(np.gradient(v, t, edge_order=2), m.acceleration(v), atol=2e-2)  # v_dot = -d (v - v_s)
    assert v[0] == pytest.approx(0.1) and m.velocity(1e3, 0.1) == pytest.approx(0.5)
    np.testing.assert_allclose(m.angular_velocity(v), 0.3 * v)


@settings(max_examples=30, deadline=None)
@given(v_s=st.floats(-0.5, 0.5).filter(lambda x: abs(x) > 0.05), d=st.floats(0.1, 5.0), c=st.floats(-2.0, 2.0),
       v0=st.floats(-0.2, 0.2), seed=st.integers(0, 2**16))
def test_the_fit_recovers_the_parameters_of_a_noisy_run(v_s, d, c, v0, seed):
    rng = np.random.default_rng(seed)
    true = DAModel(v_s, d, c)
    t = 1.0 + np.arange(0.0, 4.0 / d + 5.0, 0.1)
    v = true.velocity(t, v0, t0_s=t[0])
    noise = 1e-3
    fit = fit_decaying_acceleration(t, v + rng.normal(0, noise, v.size), true.angular_velocity(v) + rng.normal(0, noise, v.size))
    assert fit.model.v_s_m_s == pytest.approx(v_s, abs=5e-3)
    assert fit.model.c_rad_per_m == pytest.approx(c, abs=0.05)
    if abs(v0 - v_s) > 0.05:  # a visible transient: its rate is observable
        assert fit.model.d_per_s == pytest.approx(d, rel=0.15)
    assert fit.v_rms_m_s < 2 * noise and fit.omega_rms_rad_s < 2 * noise + 0.01


@pytest.mark.parametrize("t, v, w, reason", [
    ([0, 1, 2], [0, 1, 2], [0, 0, 0], "four samples"),
    ([0, 1, 2, 3], [0, 0, 0, 0], [0, 0, 0, 0], "never leaves zero"),
    ([0, 1, 2, 3], [0, np.nan, 1, 1], [0, 0, 0, 0], "finite"),
])
def test_the_fit_refuses_what_fits_nothing(t, v, w, reason):
    with pytest.raises(ValueError, match=reason):
        fit_decaying_acceleration(t, v, w)


@pytest.fixture(scope="module")
def da_inverse():
    """An inverse model trained on a known feasible set of DA parameters: ``v_s = 0.1 A^2``,
    ``d = 0.3 + 0.2 A``, ``c = B`` for ``(A, B)`` on a grid (the board's shape, simplified)."""
    from companion.motion.inverse import train_inverse_model

    A, B = np.meshgrid(np.linspace(0.2, 1.0, 9), np.linspace(-0.8, 0.8, 9), indexing="ij")
    A, B = A.ravel(), B.ravel()
    xi = np.column_stack((0.1 * A ** 2, 0.3 + 0.2 * A, B))
    return train_inverse_model(np.column_stack((A, B)), xi, seed=0, hidden=12, steady=None, bottleneck=2)


@pytest.mark.parametrize("A, B, v", [(0.4, 0.3, 0.012), (0.7, -0.5, 0.02), (0.9, 0.0, 0.06), (0.5, 0.6, 0.03)])
def test_the_line_search_finds_the_parameters_of_a_motion_the_set_can_make(da_inverse, A, B, v):
    """Sec. 4.5.3, Fig. 4-11: a motion ``(v, v_dot, omega)`` made by a feasible ``(v_s, d, c)`` is
    mapped back to it (the hyperbola ``v_s = v + v_dot / d`` crosses the feasible surface there),
    and the model gives back the inputs."""
    from companion.motion.decaying_acceleration import feasible_da

    v_s, d, c = 0.1 * A ** 2, 0.3 + 0.2 * A, B
    xi = feasible_da(da_inverse, v, d * (v_s - v), c * v)
    assert np.all(np.abs(xi - [v_s, d, c]) <= [0.002, 0.02, 0.02]), (xi, [v_s, d, c])
    np.testing.assert_allclose(da_inverse(xi)[0], [A, B], atol=0.05)


def test_the_line_search_takes_the_curvature_at_a_floor_speed_and_refuses_what_is_not_finite(da_inverse):
    from companion.motion.decaying_acceleration import feasible_da

    assert feasible_da(da_inverse, 0.0, 0.01, 0.002, v_min_m_s=0.01)[2] == pytest.approx(0.2)
    for bad in ((np.nan, 0.0, 0.0), (0.1, np.inf, 0.0), (0.1, 0.0, -np.inf)):
        with pytest.raises(ValueError, match="finite"):
            feasible_da(da_inverse, *bad)

"""Eel-like CPG (thesis sec. 4.3.1): phase locking, amplitude/bias convergence, smooth steps and
gait transitions, body rates against finite differences, functional API vs class."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat
from companion.motion.cpg import (
    Cpg,
    CpgParams,
    CpgState,
    cpg_derivative,
    cpg_initial_state,
    cpg_output,
    cpg_step,
    so3_exp,
    so3_right_jacobian,
)

DT = 0.002


def _run(params, state, A, B, seconds, dt=DT):
    for _ in range(int(round(seconds / dt))):
        state = cpg_step(state, params, A, B, dt)
    return state


def _wrap(x):
    return (x + math.pi) % (2 * math.pi) - math.pi


@pytest.mark.parametrize("n", [3, 5, 7, 12])
def test_oscillators_lock_to_the_commanded_phase_lags(n):
    params = CpgParams(n, k_phi=4.0)
    rng = np.random.default_rng(n)
    state = cpg_initial_state(params, phi0=rng.uniform(-math.pi, math.pi, n))
    state = _run(params, state, [0.3, 0.0], [0.0, 0.0], 40.0, dt=0.01)
    lag = params.shaping[2]
    np.testing.assert_allclose(_wrap(np.diff(state.phi) + lag), 0.0, atol=1e-3)
    # locked: every oscillator runs at the common frequency 2 pi f
    later = cpg_step(state, params, [0.3, 0.0], [0.0, 0.0], DT)
    np.testing.assert_allclose((later.phi - state.phi) / DT, 2 * math.pi * params.frequency_hz, rtol=1e-3)


@pytest.mark.parametrize("n", [2, 3, 7, 12])
def test_phase_coupling_over_the_pair_list_is_the_dense_sum(n):
    """The derivative sums sin(phi_j - phi_i - phi_ij) over the coupled pairs only: the same numbers
    as the sum over the whole (n, n) coupling matrix with the uncoupled entries zeroed, bit for bit
    (a batch of random phases). The cached shaping and coupling are read-only."""
    params = CpgParams(n)
    rng = np.random.default_rng(n)
    phi = rng.uniform(-10.0, 10.0, (5, n))
    z = np.zeros((5, n, 2))
    d = cpg_derivative(CpgState(z, z, z, z, phi), params, [0.3, 0.1], [0.0, 0.2])
    coupled = ~np.isnan(params.coupling)
    diff = phi[..., None, :] - phi[..., :, None] - np.where(coupled, params.coupling, 0.0)
    dense = np.sum(np.where(coupled, np.sin(diff), 0.0), axis=-1)
    np.testing.assert_array_equal(d.phi, 2 * math.pi * params.frequency_hz + params.k_phi * dense)
    assert params.shaping[0] is params.shaping[0]  # computed once per instance
    pairs = params.coupled_pairs
    for a in (*params.shaping[:2], params.coupling, pairs.i, pairs.j, pairs.phi_ij, pairs.incidence):
        with pytest.raises(ValueError):
            a[...] = 0


def test_amplitude_and_bias_converge_to_the_shaped_commands():
    params = CpgParams(7)
    sigma_a, sigma_b, _ = params.shaping
    state = _run(params, cpg_initial_state(params), [0.4, 0.1], [0.2, -0.05], 15.0)
    np.testing.assert_allclose(state.a, sigma_a[:, None] * [0.4, 0.1], atol=1e-4)
    np.testing.assert_allclose(state.b, sigma_b[:, None] * [0.2, -0.05], atol=1e-4)
    assert sigma_a[0] < sigma_a[-1] == pytest.approx(1.0)  # eel: the tail swings most
    np.testing.assert_allclose(sigma_b, np.linspace(-1, 1, 7))  # the bias bends into an arc


def _trace(params, state, schedule, seconds):
    """Attitude axis-angles and body rates sampled every step, with ``schedule(t) -> (A, B)``."""
    ws, oms = [], []
    for k in range(int(round(seconds / DT))):
        A, B = schedule(k * DT)
        state = cpg_step(state, params, A, B, DT)
        w, _, om = cpg_output(state, params, A, B)
        ws.append(w)
        oms.append(om)
    return np.array(ws), np.array(oms)


@pytest.mark.parametrize("step", ["A", "B", "gait"])
def test_a_step_in_A_or_B_gives_targets_without_jumps(step):
    """Steps of the commands change the attitude and rate only continuously (second-order filters)."""
    params = CpgParams(7)
    state = _run(params, cpg_initial_state(params), [0.3, 0.0], [0.0, 0.0], 10.0)
    after = {"A": ([0.6, 0.0], [0.0, 0.0]), "B": ([0.3, 0.0], [0.3, 0.0]), "gait": ([0.0, 0.3], [0.0, 0.0])}[step]
    seconds = 8.0 if step == "gait" else 3.0  # the gait: until the horizontal amplitude has died out
    ws, oms = _trace(params, state, lambda t: ([0.3, 0.0], [0.0, 0.0]) if t < 1.0 else after, seconds)
    dw = np.linalg.norm(np.diff(ws, axis=0), axis=-1).max(axis=1)
    dom = np.linalg.norm(np.diff(oms, axis=0), axis=-1).max(axis=1)
    k = int(round(1.0 / DT))
    before_w, before_om = dw[:k - 1].max(), dom[:k - 1].max()
    # no jump at the step: per-sample changes stay of the size they had before
    assert dw[k - 2:k + 3].max() <= 1.5 * before_w
    assert dom[k - 2:k + 3].max() <= 1.5 * before_om
    assert dw.max() < 0.01  # rad per 2 ms, everywhere
    if step == "gait":  # horizontal undulation handed over to vertical
        assert np.abs(ws[-1][:, 2]).max() < 0.02 and np.abs(ws[-500:][:, :, 1]).max() > 0.2


def test_body_rates_are_the_derivative_of_the_attitudes():
    params = CpgParams(5)
    state = _run(params, cpg_initial_state(params), [0.5, 0.3], [0.2, 0.1], 3.0)  # still converging
    A, B = [0.5, 0.3], [0.2, 0.1]
    h = 1e-4
    _, R0, om = cpg_output(state, params, A, B)
    _, Rp, _ = cpg_output(cpg_step(state, params, A, B, h), params, A, B)
    _, Rm, _ = cpg_output(cpg_step(state, params, A, B, -h), params, A, B)
    W = np.einsum("nji,njk->nik", R0, (Rp - Rm) / (2 * h))
    np.testing.assert_allclose(np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=1), om, atol=1e-6)


def test_so3_exp_and_right_jacobian():
    rng = np.random.default_rng(3)
    w = rng.normal(size=(20, 3))
    w[0] = 0.0
    w[1] = 1e-9
    np.testing.assert_allclose(so3_exp(w), quat_to_rotmat(quat_from_rotvec(w)), atol=1e-12)
    v = rng.normal(size=(20, 3))
    h = 1e-6
    dR = (so3_exp(w + h * v) - so3_exp(w - h * v)) / (2 * h)
    W = np.einsum("nji,njk->nik", so3_exp(w), dR)
    np.testing.assert_allclose(np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=1),
                               np.einsum("nij,nj->ni", so3_right_jacobian(w), v), atol=1e-7)


def test_class_and_functions_agree():
    params = CpgParams(4, frequency_hz=0.8)
    cpg = Cpg(params)
    state = cpg_initial_state(params)
    for k in range(500):
        A, B = [0.2 + 0.001 * k, 0.0], [0.0, 0.05]
        cpg.step(A, B, DT)
        state = cpg_step(state, params, A, B, DT)
    np.testing.assert_array_equal(cpg.state.vector(), state.vector())
    for x, y in zip(cpg.output(), cpg_output(state, params, A, B)):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("kwargs, reason", [
    ({"n_links": 1}, "n_links"),
    ({"n_links": 3, "frequency_hz": 0.0}, "frequency_hz"),
    ({"n_links": 3, "sigma_a": (1.0, 1.0)}, "sigma_a has 2 weights for 3 links"),
    ({"n_links": 3, "lag_rad": math.nan}, "lag_rad"),
])
def test_bad_parameters_are_rejected(kwargs, reason):
    with pytest.raises(ValueError, match=reason):
        CpgParams(**kwargs)

"""The snake's and the pivotboard's CPGs (thesis secs. 4.3.2, 4.3.3; companion.motion.ground_cpgs)
and the oscillator core they share with the flying skeleton's (companion.motion.oscillators): the
integration against scipy's solve_ivp, convergence to the limit cycle the equations lock to, the
pivotboard's switch to zero phase difference on deceleration, and the phase maps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from companion.motion.ground_cpgs import (PivotCpgParams, PivotCpgState, SnakeCpgParams, SnakeCpgState,
                                          pivot_derivative, pivot_joint_angles, pivot_phase_target, pivot_step,
                                          snake_derivative, snake_joint_angles, snake_step)
from companion.motion.oscillators import PhaseMap, chain_coupling, filter_acceleration

DT = 0.01  # the thesis's 100 Hz
#: a phase map of (A, B) that is not constant: the lock must follow it
HV_MAP = PhaseMap(((0.0, 1.0), (-0.5, 0.5)), (0.2, 0.6, 1.0, 1.4))


def wrap(x):
    return (np.asarray(x) + math.pi) % (2 * math.pi) - math.pi


@pytest.mark.parametrize("A, B", [(0.5, 0.0), (0.8, 0.3), (0.2, -0.4)])
def test_the_snake_cpg_integrates_as_solve_ivp_does(A, B):
    params = SnakeCpgParams(phase_hv=HV_MAP)
    rng = np.random.default_rng(1)
    x0 = SnakeCpgState.at_rest(params, rng.uniform(-3, 3, params.n), rng.uniform(-3, 3, params.n))
    x = x0
    for _ in range(300):
        x = snake_step(x, params, A, B, DT)
    ref = solve_ivp(lambda t, y: snake_derivative(SnakeCpgState.from_vector(y), params, A, B).vector(), (0.0, 3.0),
                    x0.vector(), method="DOP853", rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(x.vector(), ref.y[:, -1], atol=1e-7)


@pytest.mark.parametrize("A, B, v_dot_d", [(0.3, 0.1, 0.2), (0.5, -0.2, -0.1)])
def test_the_pivotboard_cpg_integrates_as_solve_ivp_does(A, B, v_dot_d):
    params = PivotCpgParams()
    x0 = PivotCpgState.at_rest((0.4, -1.1))
    x = x0
    for _ in range(300):
        x = pivot_step(x, params, A, B, v_dot_d, DT)
    ref = solve_ivp(lambda t, y: pivot_derivative(PivotCpgState.from_vector(y), params, A, B, v_dot_d).vector(),
                    (0.0, 3.0), x0.vector(), method="DOP853", rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(x.vector(), ref.y[:, -1], atol=1e-7)


@pytest.mark.parametrize("seed", range(3))
def test_the_snake_locks_to_its_travelling_wave_and_the_vertical_at_twice_the_frequency(seed):
    """From phases up to 0.8 rad off the locked wave (and from rest, with phi_hv(A, B) moved by the
    inputs): the horizontal neighbours lock to the lag, the vertical ones to twice it, every
    vertical oscillator to twice its horizontal one plus phi_hv(A, B); the amplitude and bias
    reach sigma A and sigma B; the joints then follow the steady-state wave."""
    rng = np.random.default_rng(seed)
    params = SnakeCpgParams(phase_hv=HV_MAP, sigma_a=tuple(rng.uniform(0.5, 1.0, 7)))
    A, B = 0.6, 0.2
    locked = SnakeCpgState.at_rest(params)
    x = SnakeCpgState.at_rest(params, locked.phi_h + rng.uniform(-0.8, 0.8, 7), locked.phi_v + rng.uniform(-0.8, 0.8, 7))
    for _ in range(1500):
        x = snake_step(x, params, A, B, DT)
    np.testing.assert_allclose(wrap(np.diff(x.phi_h) + params.lag), 0.0, atol=1e-4)
    np.testing.assert_allclose(wrap(np.diff(x.phi_v) + 2 * params.lag), 0.0, atol=1e-4)
    np.testing.assert_allclose(wrap(x.phi_v - 2 * x.phi_h - HV_MAP(A, B)), 0.0, atol=1e-4)
    sigma_a, sigma_b, A_v = params.shaping
    np.testing.assert_allclose(x.a, sigma_a * A, atol=1e-6)
    np.testing.assert_allclose(x.b, sigma_b * B, atol=1e-6)
    d = snake_derivative(x, params, A, B)
    np.testing.assert_allclose(d.phi_h, 2 * math.pi * params.frequency_hz, atol=1e-4)  # the coupling is at rest
    np.testing.assert_allclose(d.phi_v, 4 * math.pi * params.frequency_hz, atol=1e-4)
    theta_h, theta_v = snake_joint_angles(x, params)
    np.testing.assert_allclose(theta_h, sigma_a * A * np.cos(x.phi_h) + sigma_b * B, atol=1e-6)
    np.testing.assert_allclose(theta_v, -A_v * np.sin(2 * x.phi_h + HV_MAP(A, B)), atol=1e-3)


def test_from_arbitrary_phases_the_snake_can_lock_twisted():
    """The equations as the thesis gives them have more than one stable locked state: from these
    random phases the chains lock with the tail's vertical oscillator 1.36 rad off its target
    (what SnakeCpgState.at_rest avoids by starting on the wave)."""
    rng = np.random.default_rng(0)
    params = SnakeCpgParams(phase_hv=HV_MAP, sigma_a=tuple(rng.uniform(0.5, 1.0, 7)))
    x = SnakeCpgState.at_rest(params, rng.uniform(-math.pi, math.pi, 7), rng.uniform(-math.pi, math.pi, 7))
    for _ in range(3000):
        x = snake_step(x, params, 0.6, 0.2, DT)
    d = snake_derivative(x, params, 0.6, 0.2)
    np.testing.assert_allclose(np.diff(d.phi_h), 0.0, atol=1e-6)  # locked: one frequency for all
    assert abs(wrap(x.phi_v - 2 * x.phi_h - HV_MAP(0.6, 0.2))[-1]) > 1.0


def test_the_pivotboard_locks_to_its_phase_and_to_zero_when_decelerating_with_continuous_joints():
    """Accelerating, the plates' phase difference locks to phi(A, B, v_dot_d); a switch to
    deceleration takes it to zero at rate 2w. Only the phase rates switch: the joint angles move
    by no more than their rate allows in any step across the switch."""
    params = PivotCpgParams(phase=PhaseMap(((0.0, 1.0), (0.0,), (0.0, 1.0)), (0.3, 0.5, 0.7, 0.9)))
    A, B = 0.4, 0.15
    x = PivotCpgState.at_rest((1.0, -2.0))
    for _ in range(1000):
        x = pivot_step(x, params, A, B, 0.5, DT)
    assert pivot_phase_target(params, A, B, 0.5) == pytest.approx(0.3 + 0.4 * 0.4 + 0.5 * 0.2)
    assert wrap(x.phi[1] - x.phi[0] - pivot_phase_target(params, A, B, 0.5)) == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(x.a, [A, A], atol=1e-6)
    np.testing.assert_allclose(x.b, [B, 0.0], atol=1e-6)  # the bias on the right plate only
    theta = [pivot_joint_angles(x)]
    for _ in range(300):
        x = pivot_step(x, params, A, B, -0.3, DT)
        theta.append(pivot_joint_angles(x))
    assert pivot_phase_target(params, A, B, -0.3) == 0.0
    assert wrap(x.phi[1] - x.phi[0]) == pytest.approx(0.0, abs=1e-4)
    steps = np.abs(np.diff(np.array(theta), axis=0))
    rate_bound = A * (2 * math.pi * params.frequency_hz + params.w) * DT
    assert steps.max() <= rate_bound


@given(st.floats(-1.0, 1.0), st.floats(0.5, 20.0))
@settings(max_examples=40, deadline=None)
def test_the_filters_reach_a_step_target_without_overshoot(target, k):
    """The critically damped amplitude and bias filters, from rest, approach a step target
    monotonically and never pass it."""
    x, v = 0.0, 0.0
    path = []
    for _ in range(int(16.0 / k / 0.001)):
        a = filter_acceleration(x, v, target, k)
        v += 0.001 * a
        x += 0.001 * v
        path.append(x)
    path = np.array(path)
    assert np.all(np.sign(target) * path <= abs(target) + 1e-9)
    assert np.all(np.sign(target) * np.diff(path) >= -1e-12)
    assert abs(path[-1] - target) < 0.02 * abs(target) + 1e-9


def test_the_phase_maps_interpolate_clamp_and_refuse_bad_grids():
    m = PhaseMap(((0.0, 1.0, 3.0), (-1.0, 1.0)), (0.0, 1.0, 2.0, 3.0, 4.0, 5.0))
    assert m(1.0, 1.0) == 3.0 and m(0.0, -1.0) == 0.0  # grid points
    assert m(2.0, 0.0) == pytest.approx(0.5 * (2.5 + 4.5))  # bilinear
    assert m(9.0, 7.0) == 5.0 and m(-5.0, -5.0) == 0.0  # clamped to the edges
    assert PhaseMap.constant(0.7, 3)(1.0, -2.0, 5.0) == 0.7
    for axes, values in ((((0.0, 0.0),), (1.0, 2.0)), (((1.0, 0.0),), (1.0, 2.0)), (((0.0, 1.0),), (1.0,)),
                         (((0.0, float("nan")),), (1.0, 2.0)), (((0.0, 1.0),), (1.0, float("inf"))), ((), ())):
        with pytest.raises(ValueError):
            PhaseMap(axes, values)
    with pytest.raises(ValueError, match="takes 2 inputs"):
        m(1.0)


def test_bad_constants_are_refused_and_the_chain_coupling_runs_head_to_tail():
    for kwargs in (dict(n=1), dict(k_a=0.0), dict(w_hv=-1.0), dict(sigma_a=(1.0, 2.0)), dict(A_v_rad=()),
                   dict(phase_hv=PhaseMap.constant(0.0, 3))):
        with pytest.raises(ValueError):
            SnakeCpgParams(**kwargs)
    with pytest.raises(ValueError):
        PivotCpgParams(phase=PhaseMap.constant(0.0, 2))
    c = chain_coupling(4, 0.5)
    assert list(zip(c.i.tolist(), c.j.tolist(), c.phi_ij.tolist())) == [
        (0, 1, -0.5), (1, 0, 0.5), (1, 2, -0.5), (2, 1, 0.5), (2, 3, -0.5), (3, 2, 0.5)]
    locked = -0.5 * np.arange(4)
    np.testing.assert_allclose(c.sum_sin(locked), 0.0, atol=1e-15)

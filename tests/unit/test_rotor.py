import math

import numpy as np
import pytest

from companion.skeleton.rotors import RotorParams
from sitl.plant.rotor import RotorBank

DT = 0.001


def _run(bank, command, seconds):
    bank.set_command(np.atleast_1d(command))
    out = []
    for _ in range(int(round(seconds / DT))):
        out.append(bank.step(DT).copy())
    return np.array(out)


def test_first_order_tracking_matches_exponential():
    p = RotorParams(time_constant_s=0.05)
    bank = RotorBank(1, p)
    thrust = _run(bank, 2.0, 0.1)[:, 0]
    t = DT * np.arange(1, thrust.size + 1)
    np.testing.assert_allclose(thrust, 2.0 * (1 - np.exp(-t / 0.05)), rtol=1e-9)


def test_commands_are_clipped_to_the_thrust_limit():
    bank = RotorBank(2, RotorParams(thrust_max_n=8.0))
    thrust = _run(bank, [20.0, -20.0], 1.0)
    assert np.all(np.abs(thrust) <= 8.0 + 1e-12)
    np.testing.assert_allclose(thrust[-1], [8.0, -8.0], rtol=1e-6)


@pytest.mark.parametrize("compiled", [False, True])
def test_time_at_the_limit_is_counted_per_link(compiled):
    """limit_s: per link of 8 rotors, the time with one of them commanded at +-thrust_max_n (a
    command scaled onto the limit, to float32 rounding, counts; 1 ppm below it does not)."""
    bank = RotorBank(16, RotorParams(thrust_max_n=8.0), compiled=compiled, rotors_per_link=8)
    cmd = np.full(16, 3.0)
    _run(bank, cmd, 0.2)
    cmd[3] = -8.0 * (1.0 - 1e-7)  # link 1 at the limit (a float32 1.0 on the wire decodes to this)
    _run(bank, cmd, 0.3)
    cmd[3], cmd[12] = 3.0, 20.0  # link 2 beyond it (clipped)
    _run(bank, cmd, 0.1)
    cmd[12] = 8.0 * (1.0 - 1e-5)
    _run(bank, cmd, 0.4)
    np.testing.assert_allclose(bank.limit_s, [0.3, 0.1], atol=1e-9)
    cmd[12], cmd[0] = -8.0, np.nan  # a NaN command (clipped as NaN) counts nothing, as np.max gives
    _run(bank, cmd, 0.1)
    np.testing.assert_allclose(bank.limit_s, [0.3, 0.1], atol=1e-9)
    with pytest.raises(ValueError, match="links of 8"):
        RotorBank(12, RotorParams(), rotors_per_link=8)


def test_reversal_first_decays_to_zero_then_spins_up():
    """Thesis sec. 2.4.2: a reversing rotor goes to zero thrust first (ESC singularity)."""
    p = RotorParams(time_constant_s=0.05, esc_epsilon_n=0.05)
    bank = RotorBank(1, p)
    _run(bank, 3.0, 0.5)
    thrust = _run(bank, -3.0, 1.0)[:, 0]
    assert bank.zero_crossings[0] == 1
    k_zero = int(np.argmax(np.abs(thrust) <= p.esc_epsilon_n))
    # Until it reaches the dead band it only decays (never pushed through zero) ...
    assert np.all(thrust[:k_zero] > 0) and np.all(np.diff(thrust[:k_zero]) < 0)
    # ... at the thesis rate k (no faster than the plain first-order response) ...
    assert k_zero * DT == pytest.approx(0.05 * math.log(3.0 / 0.05), abs=0.003)
    # ... then spins up the other way.
    assert thrust[-1] == pytest.approx(-3.0, rel=1e-3)


def test_restart_dwell_holds_a_reversing_rotor_at_zero():
    p = RotorParams(time_constant_s=0.05, esc_epsilon_n=0.05, restart_dwell_s=0.2)
    bank = RotorBank(1, p)
    bank.prime(np.array([-0.8]))
    thrust = _run(bank, 1.3, 1.5)[:, 0]
    k_zero = int(np.argmax(np.abs(thrust) <= p.esc_epsilon_n))
    held = thrust[k_zero : k_zero + 190]
    assert np.all(np.abs(held) <= p.esc_epsilon_n)  # restart dwell
    assert thrust[-1] == pytest.approx(1.3, rel=1e-3)  # and the restart completes
    assert bank.zero_crossings[0] == 1


@pytest.mark.parametrize("dwell", [0.0, 0.001, 0.05, 0.2])
def test_restart_completes_for_any_dwell(dwell):
    """Regression: a countdown landing a rounding error below zero must not restart the wait."""
    bank = RotorBank(1, RotorParams(restart_dwell_s=dwell))
    bank.prime(np.array([-0.8]))
    thrust = _run(bank, 1.3, 1.0 + dwell)[:, 0]
    assert thrust[-1] == pytest.approx(1.3, rel=1e-2)


def test_minimum_thrust_stops_the_motor():
    p = RotorParams(min_thrust_n=0.3, restart_dwell_s=0.1)
    bank = RotorBank(1, p)
    _run(bank, 1.0, 0.5)
    thrust = _run(bank, 0.2, 0.5)[:, 0]  # below the sustainable minimum
    assert abs(thrust[-1]) <= p.esc_epsilon_n
    thrust = _run(bank, 1.0, 0.09)[:, 0]  # asked to spin again: restart dwell first
    assert np.all(np.abs(thrust) <= p.esc_epsilon_n)
    thrust = _run(bank, 1.0, 0.5)[:, 0]
    assert thrust[-1] == pytest.approx(1.0, rel=1e-2)


def test_thesis_law_is_the_default():
    assert RotorParams().min_thrust_n == 0.0 and RotorParams().restart_dwell_s == 0.0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"thrust_max_n": 0.0}, "thrust_max_n"),
        ({"time_constant_s": -1.0}, "time_constant_s"),
        ({"esc_epsilon_n": 10.0}, "esc_epsilon_n"),
        ({"min_thrust_n": 9.0}, "min_thrust_n"),
        ({"restart_dwell_s": -0.1}, "restart_dwell_s"),
    ],
)
def test_params_are_validated(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RotorParams(**kwargs)


@pytest.mark.parametrize("seed", range(5))
def test_steady_fast_path_equals_the_full_state_machine(seed):
    """The steady-state shortcut gives bit-identical thrusts and crossing counts."""
    rng = np.random.default_rng(seed)
    p = RotorParams(min_thrust_n=0.35, restart_dwell_s=0.05)
    fast, full = RotorBank(8, p), RotorBank(8, p)
    full.set_command = lambda c, bank=full: (RotorBank.set_command(bank, c), setattr(bank, "_steady", False))
    command = rng.uniform(-4, 4, size=8)
    for k in range(4000):
        if k % 2 == 0:
            command = command + rng.normal(scale=0.4, size=8)
            fast.set_command(command)
            full.set_command(command)
        np.testing.assert_array_equal(fast.step(DT), full.step(DT))
    np.testing.assert_array_equal(fast.zero_crossings, full.zero_crossings)
    assert fast.zero_crossings.sum() > 0  # the sequence really exercised reversals


def test_warm_up_loads_every_kernel_the_bank_steps_by():
    """A run's first physics tick must not load (or compile) a kernel: ``warm_up`` leaves each of the
    bank's kernels with a compiled signature (without numba it does nothing)."""
    from companion.kernels.jit import ENABLED
    from sitl.kernels import rotor as kernels
    from sitl.plant import rotor

    rotor.warm_up()
    if not ENABLED:
        pytest.skip("numba not installed: the numpy path has nothing to load")
    for kernel in (kernels.step_kernel, kernels.set_command_kernel, kernels.relax_kernel):
        assert kernel.signatures, kernel.__name__

"""The stale gyro's stand-in (link_firmware_sim.estimators.stale_rate): Euler's equation under the
commanded torque, corrected by noisy attitude references, against a rigid body integrated here."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import quat_from_rotvec, quat_mul, quat_to_rotvec
from link_firmware_sim.estimators.stale_rate import StaleGyroRate

J = np.array([0.06, 0.35, 0.38])  # about a 1 m, 1.8 kg link's principal inertia [kg m^2]
TAU_S = 0.05
REF_VAR = np.array([0.003, 0.003, 0.015])  # the EKF's attitude reference variances
DT = 0.002


class RigidBody:
    """The truth: a body of inertia ``J`` under the rotors' torque (first-order lag) and an
    external angular acceleration ``a(t)``."""

    def __init__(self, w0, tau0):
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.w = np.array(w0, dtype=float)
        self.tau = np.array(tau0, dtype=float)

    def step(self, tau_cmd, a, dt):
        self.tau = self.tau + dt / (TAU_S + dt) * (tau_cmd - self.tau)
        wdot = (self.tau - np.cross(self.w, J * self.w)) / J + a
        self.q = quat_mul(self.q, quat_from_rotvec((self.w + 0.5 * dt * wdot) * dt))
        self.w = self.w + dt * wdot


def fly(seed, a_offset, w0, seconds=3.0):
    """The observer and, for comparison, the references' rate by differences (low-passed over
    50 ms, what stood in before) on one stale stretch; their rate errors [rad/s] per tick."""
    rng = np.random.default_rng(seed)
    tau0 = np.array([0.2, -1.5, 0.4])  # what the rotors held against the cables
    a_hold = -tau0 / J
    body = RigidBody(w0, tau0)
    obs = StaleGyroRate(J, TAU_S, REF_VAR)
    obs.start(body.q, tau0)
    q_prev, lp = None, np.zeros(3)
    err_obs, err_diff = [], []
    for k in range(int(seconds / DT)):
        t = k * DT
        tau_cmd = tau0 + np.array([0.05, 0.3, 0.1]) * np.sin(2 * np.pi * 0.7 * t)
        body.step(tau_cmd, a_hold + a_offset * min(1.0, t), DT)
        rate = obs.predict(tau_cmd, DT)
        if k % 10 == 9:  # a 50 Hz attitude reference: 1 deg tilt and 3 deg heading noise
            noise = rng.normal(size=3) * np.radians([1.0, 1.0, 3.0])
            ref = quat_mul(body.q, quat_from_rotvec(noise))
            obs.update(ref)
            if q_prev is not None:
                raw = quat_to_rotvec(quat_mul(np.array([q_prev[0], *-q_prev[1:]]), ref)) / (10 * DT)
                lp = lp + (10 * DT) / (0.05 + 10 * DT) * (raw - lp)
            q_prev = ref
            rate = obs.rate_b_rad_s
        if t >= 1.0:
            err_obs.append(rate - body.w)
            err_diff.append(lp - body.w)
    return np.array(err_obs), np.array(err_diff), obs, a_hold


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("a_offset, w0", [((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
                                          ((0.3, -0.5, 0.2), (0.2, -0.3, 0.1)),
                                          ((-0.8, 0.8, -0.4), (-0.4, 0.5, 0.0))])
def test_the_rate_follows_the_body_far_closer_than_the_references_differences(seed, a_offset, w0):
    """After a second, whatever the rate at the start (unknown to the observer) and a change in
    the cables' pull of up to 0.8 rad/s^2: the rate within a few degrees per second, about three
    times closer than the references' differences or better, and the cables' share ``a`` learnt."""
    err_obs, err_diff, obs, a_hold = fly(seed, np.array(a_offset), w0)
    rms_obs = np.sqrt(np.mean(err_obs ** 2, axis=0))
    rms_diff = np.sqrt(np.mean(err_diff ** 2, axis=0))
    assert np.all(rms_obs < np.radians([5.0, 5.0, 8.0])), np.degrees(rms_obs)
    assert np.all(rms_obs < 0.35 * rms_diff), (np.degrees(rms_obs), np.degrees(rms_diff))
    np.testing.assert_allclose(obs.accel_b_rad_s2, a_hold + np.array(a_offset), atol=0.6)


def test_start_takes_the_torque_the_rotors_held_as_the_cables_pull_and_the_rate_as_unknown():
    obs = StaleGyroRate(J, TAU_S, REF_VAR)
    assert not obs.running
    obs.start(np.array([1.0, 0, 0, 0]), [0.3, -0.7, 0.1])
    assert obs.running and obs.updates == 0
    np.testing.assert_array_equal(obs.rate_b_rad_s, np.zeros(3))
    np.testing.assert_allclose(obs.accel_b_rad_s2, -np.array([0.3, -0.7, 0.1]) / J)
    np.testing.assert_allclose(obs.P[:, 0, 0], REF_VAR)
    obs.stop()
    assert not obs.running


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_without_references_it_integrates_eulers_equation(axis):
    """About one principal axis from rest, no gyroscopic term: the rate grows as (tau/J + a) t once
    the rotors' lag has settled, and the attitude turns by its integral."""
    obs = StaleGyroRate(J, 0.0, REF_VAR)
    obs.start(np.array([1.0, 0, 0, 0]), np.zeros(3))
    tau = np.zeros(3)
    tau[axis] = 0.02
    n = 500
    for _ in range(n):
        obs.predict(tau, DT)
    t = n * DT
    assert obs.rate_b_rad_s[axis] == pytest.approx(tau[axis] / J[axis] * t, rel=1e-9)
    angle = quat_to_rotvec(obs.q_wxyz)[axis]
    assert angle == pytest.approx(0.5 * tau[axis] / J[axis] * t * t, rel=5e-3)


@settings(max_examples=50, deadline=None)
@given(rv=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
       tau=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
       ticks=st.integers(1, 40))
def test_a_reference_equal_to_its_attitude_corrects_nothing_and_shrinks_the_uncertainty(rv, tau, ticks):
    obs = StaleGyroRate(J, TAU_S, REF_VAR)
    obs.start(quat_from_rotvec(np.array(rv)), np.array(tau))
    for _ in range(ticks):
        obs.predict(np.array(tau) * 0.5, DT)
    q, w, a, P = obs.q_wxyz.copy(), obs.rate_b_rad_s.copy(), obs.accel_b_rad_s2.copy(), obs.P.copy()
    obs.update(q)
    np.testing.assert_allclose(obs.rate_b_rad_s, w, atol=1e-9)
    np.testing.assert_allclose(obs.accel_b_rad_s2, a, atol=1e-9)
    assert abs(abs(float(obs.q_wxyz @ q)) - 1.0) < 1e-12
    diag_before, diag_after = np.diagonal(P, axis1=1, axis2=2), np.diagonal(obs.P, axis1=1, axis2=2)
    assert np.all(diag_after <= diag_before + 1e-15) and np.all(diag_after[:, 0] < diag_before[:, 0])
    assert np.all(np.linalg.eigvalsh(0.5 * (obs.P + obs.P.transpose(0, 2, 1))) > -1e-12)


@pytest.mark.parametrize("kwargs, fragment", [
    (dict(inertia_kgm2=[0.1, 0.0, 0.1]), "inertia_kgm2"),
    (dict(actuator_time_constant_s=-0.01), "actuator_time_constant_s"),
    (dict(actuator_time_constant_s=float("nan")), "actuator_time_constant_s"),
    (dict(ref_var_rad2=[0.003, 0.0, 0.01]), "ref_var_rad2"),
])
def test_bad_parameters_are_refused(kwargs, fragment):
    args = dict(inertia_kgm2=J, actuator_time_constant_s=TAU_S, ref_var_rad2=REF_VAR) | kwargs
    with pytest.raises(ValueError, match=fragment):
        StaleGyroRate(**args)

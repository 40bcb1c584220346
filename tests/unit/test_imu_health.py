"""A stuck gyro (link_firmware_sim.estimators.imu_health) and the firmware without it: stale after
0.2 s of one repeated sample, alive at the first that differs; in flight the EKF then holds the
attitude on its reference and the controller damps with the rate of the attitude estimate."""

from __future__ import annotations

import numpy as np
import pytest

from companion.messages import PoseTarget
from link_firmware_sim.estimators.imu_health import STALE_S, StaleSensor

from .test_gps_health import GRAVITY_UP, _hovering_firmware


def _fly_still(fw, q, rng, gyro, gps_std_m: float, ticks: int = 750, first: int = 1) -> None:
    """``ticks`` 500 Hz ticks from tick ``first`` of a still link at attitude ``q``: ``gyro()``
    each tick, the attitude reference every 10, a GPS fix (``gps_std_m`` of noise) every 50, and
    the stuck-sensor watch every 10, as a shell does on its log rows."""
    for k in range(first, first + ticks):
        t = k / 500
        if k % 10 == 0:
            fw.on_attitude(t, q)
        if k % 50 == 0:
            fw.on_gps(t, rng.normal(0, gps_std_m, 3), np.zeros(3))
        fw.on_imu(t, gyro(), GRAVITY_UP + rng.normal(0, 1e-4, 3))
        if k % 10 == 0:
            fw.watch_imu(t)


@pytest.mark.parametrize("step_s", [0.002, 0.02])  # every tick, or a sample per compiled loop's return
def test_a_repeated_sample_is_stale_after_stale_s_and_alive_at_the_next_change(step_s):
    s = StaleSensor("Gyro")
    rng = np.random.default_rng(0)
    t, events = 0.0, []
    for _ in range(50):
        events += s.on_sample(t, rng.normal(0, 0.01, 3))
        t += step_s
    stuck = np.array([0.01, -0.02, 0.03])
    t_stuck = t
    while t < t_stuck + STALE_S + 0.1:
        events += s.on_sample(t, stuck)
        if t < t_stuck + STALE_S - 1e-9:
            assert not s.stale
        t += step_s
    assert s.stale and [e.kind for e in events] == ["fault"] and events[0].text == "Gyro stale: no change for 0.2 s"
    events = s.on_sample(t, stuck + 1e-9)
    assert not s.stale and [e.kind for e in events] == ["recovered"]
    report = s.report(t)
    assert report["episodes"] == 1 and report["stale_s"] == pytest.approx(t - t_stuck - STALE_S, abs=step_s)


def test_stop_ends_an_episode_quietly():
    s = StaleSensor("Gyro")
    for k in range(200):
        s.on_sample(k * 0.002, np.zeros(3))
    assert s.stale
    s.stop(0.5)
    assert not s.stale and s.on_sample(0.6, np.zeros(3)) == [] and s.report(0.6)["stale_s"] > 0.0
    with pytest.raises(ValueError):
        StaleSensor("Gyro", stale_s=0.0)


@pytest.mark.parametrize("stale", [False, True])
def test_in_flight_a_stuck_gyro_is_not_integrated(stale):
    """An armed, still link whose gyro reads a constant 0.5 rad/s about z (stuck; ``stale``) or
    whose samples vary by a hair around it (``not stale``: a live gyro, believed): the stale
    gyro's rate is never integrated once it is found stale (watched every 20 ms, as a shell does),
    so the attitude stays on the reference; the believed one turns the estimate. The controller
    damps with the stale gyro's stand-in (its model rate, corrected by the references), near zero
    here."""
    fw, q = _hovering_firmware()
    assert fw.arm(0.0)
    fw.set_target(0.0, PoseTarget.hold(np.zeros(3), q))
    rng = np.random.default_rng(1)
    rate = np.array([0.0, 0.0, 0.5])
    _fly_still(fw, q, rng, lambda: rate if stale else rate + rng.normal(0, 1e-6, 3), gps_std_m=0.05)
    yaw_err = np.degrees(2 * np.arccos(min(1.0, abs(float(fw.ekf.q_wxyz @ q)))))
    assert fw.imu_health.gyro.stale == stale
    if stale:
        assert yaw_err < 3.0 and [e.text for e in fw.events if e.kind == "fault"] == ["Gyro stale: no change for 0.2 s"]
        assert np.linalg.norm(fw.imu_health.rate.rate_b_rad_s) < 0.2 and fw.imu_health.rate.updates > 0
    else:
        assert yaw_err > 5.0
    fw.disarm()
    assert not fw.imu_health.gyro.stale


@pytest.mark.parametrize("stale", [False, True])
def test_the_attitude_integral_holds_while_the_gyro_is_stale(stale):
    """A link held 10 deg off its target in yaw (its attitude reference says so): eq. 1's attitude
    integral winds on the error with a live gyro; with a stale one it holds its value (anti-windup
    while the damping is the model's rate), the position integral going on."""
    from companion.estimation.so3 import quat_from_euler_zyx

    fw, q = _hovering_firmware()
    assert fw.arm(0.0)
    target = quat_from_euler_zyx(np.radians(10.0), 0.0, 0.0)
    fw.set_target(0.0, PoseTarget.hold(np.array([0.3, 0.0, 0.0]), target))
    rng = np.random.default_rng(2)
    gyro = lambda: np.zeros(3) if stale else rng.normal(0, 1e-4, 3)  # noqa: E731
    _fly_still(fw, q, rng, gyro, gps_std_m=0.01, ticks=250)
    assert fw.imu_health.gyro.stale == stale
    before = fw.integrals
    _fly_still(fw, q, rng, gyro, gps_std_m=0.01, ticks=500, first=251)
    after = fw.integrals
    assert np.linalg.norm(after.pos - before.pos) > 1e-3
    if stale:
        np.testing.assert_array_equal(after.att, before.att)
    else:
        assert np.linalg.norm(after.att - before.att) > 1e-3


@pytest.mark.parametrize("stale", [False, True])
def test_in_flight_a_stuck_accelerometer_is_replaced_by_the_commanded_thrust(stale):
    """An armed, still link without GPS whose accelerometer reads 0.5 m/s^2 off its true specific
    force: stuck on that value (``stale``), it is found stale and the commanded thrust's specific
    force stands in (the velocity stays near zero, SYS-status-worthy event reported); varying by a
    hair around it (a live sensor, believed), the velocity estimate runs off at 0.5 m/s^2."""
    fw, q = _hovering_firmware()
    assert fw.arm(0.0)
    fw.set_target(0.0, PoseTarget.hold(np.zeros(3), q))
    rng = np.random.default_rng(2)
    off = GRAVITY_UP + np.array([0.5, 0.0, 0.0])
    for k in range(1, 1001):
        t = k / 500
        if k % 10 == 0:
            fw.on_attitude(t, q)
        if k <= 100:  # 0.2 s live, then the reading goes off (and, stale, stays bit for bit)
            fw.on_imu(t, rng.normal(0, 1e-4, 3), GRAVITY_UP + rng.normal(0, 1e-4, 3))
        else:
            fw.on_imu(t, rng.normal(0, 1e-4, 3), off if stale else off + rng.normal(0, 1e-6, 3))
        if k % 10 == 0:
            fw.watch_imu(t)
    speed = float(np.linalg.norm(fw.ekf.v_w_m_s))
    assert fw.imu_health.accel.stale == stale and not fw.imu_health.gyro.stale
    if stale:
        assert speed < 0.2 and "Accel stale: no change for 0.2 s" in [e.text for e in fw.events if e.kind == "fault"]
    else:
        assert speed > 0.6


def test_each_stale_stretch_starts_the_gyros_stand_in_afresh():
    """A gyro stuck, alive again (its stand-in stopped at the watch that saw it change, whichever
    path the next ticks take), stuck again: the second stretch starts from the attitude estimate
    and the commanded torque of then, not from where the first one left off."""
    fw, q = _hovering_firmware()
    assert fw.arm(0.0)
    fw.set_target(0.0, PoseTarget.hold(np.zeros(3), q))
    rng = np.random.default_rng(3)
    stuck = np.array([0.0, 0.0, 0.01])
    _fly_still(fw, q, rng, lambda: stuck, gps_std_m=0.01, ticks=400)
    rate = fw.imu_health.rate
    assert fw.imu_health.gyro.stale and rate.running and rate.updates > 5
    first_updates = rate.updates
    _fly_still(fw, q, rng, lambda: rng.normal(0, 1e-3, 3), gps_std_m=0.01, ticks=50, first=401)
    assert not fw.imu_health.gyro.stale and not rate.running
    _fly_still(fw, q, rng, lambda: stuck, gps_std_m=0.01, ticks=150, first=451)
    assert fw.imu_health.gyro.stale and rate.running and 0 < rate.updates < first_updates

"""Injected failures (link_firmware_sim.vehicle.failures): the command's params, the failures per
unit and instance, the samples and rotor commands they change, clearing them."""

import math

import numpy as np
import pytest

from companion.mavlink.dialect import load_dialect
from link_firmware_sim.vehicle import failures as f
from link_firmware_sim.vehicle.failures import FailureInjector, parse_failure

D = load_dialect()
P = np.array([1.0, 2.0, 3.0])
V = np.array([0.5, 0.0, -0.1])


def test_numbers_are_common_xml_s():
    assert (f.GYRO, f.ACCEL, f.GPS, f.MOTOR) == (D.FAILURE_UNIT_SENSOR_GYRO, D.FAILURE_UNIT_SENSOR_ACCEL,
                                                 D.FAILURE_UNIT_SENSOR_GPS, D.FAILURE_UNIT_SYSTEM_MOTOR)
    assert (f.OK, f.OFF, f.STUCK, f.GARBAGE, f.WRONG) == (D.FAILURE_TYPE_OK, D.FAILURE_TYPE_OFF, D.FAILURE_TYPE_STUCK,
                                                          D.FAILURE_TYPE_GARBAGE, D.FAILURE_TYPE_WRONG)


def test_parse_rounds_like_px4_and_refuses_what_is_not_a_small_number():
    assert parse_failure(4.0, 1.0, 0.0) == (4, 1, 0)
    assert parse_failure(100.6, 0.9999, 2.2) == (101, 1, 2)
    for bad in ((math.nan, 1, 0), (4, math.inf, 0), (4, 1, -math.inf), (-1, 1, 0), (4, 1, 256), (1e30, 0, 0)):
        with pytest.raises(ValueError):
            parse_failure(*bad)


@pytest.mark.parametrize("unit, ftype, instance, supported", [
    (f.GPS, f.OK, 0, True), (f.GPS, f.OFF, 0, True), (f.GPS, f.STUCK, 1, True), (f.GPS, f.WRONG, 0, True),
    (f.GPS, f.GARBAGE, 0, False), (f.GPS, f.OFF, 2, False),
    (f.GYRO, f.STUCK, 0, True), (f.GYRO, f.GARBAGE, 1, True), (f.GYRO, f.OFF, 0, False), (f.GYRO, f.STUCK, 2, False),
    (f.ACCEL, f.STUCK, 1, True), (f.ACCEL, f.GARBAGE, 0, True), (f.ACCEL, f.WRONG, 0, False),
    (f.MOTOR, f.OFF, 3, True), (f.MOTOR, f.OFF, 0, True), (f.MOTOR, f.OFF, 9, False), (f.MOTOR, f.STUCK, 1, False),
    (D.FAILURE_UNIT_SENSOR_BARO, f.OFF, 0, False), (D.FAILURE_UNIT_SYSTEM_BATTERY, f.OFF, 0, False), (250, 1, 0, False),
    (f.GPS, 200, 0, False),
])
def test_what_is_supported(unit, ftype, instance, supported):
    inj = FailureInjector()
    what = inj.inject(unit, ftype, instance)
    assert (what is not None) == supported
    if not supported:
        assert inj.active == {} and inj.injected == 0


@pytest.mark.parametrize("instance", [0, 1])
def test_gps_off_drops_fixes_until_ok(instance):
    inj = FailureInjector()
    assert inj.gps(P, V) == (P, V)
    assert inj.inject(f.GPS, f.OFF, instance) == "gps off"
    assert inj.gps(P, V) is None and inj.changed["gps"] == 1
    assert inj.report()["active"] == ["gps 1 off"]
    assert inj.inject(f.GPS, f.OK, instance) == "gps ok"
    assert inj.gps(P, V) == (P, V) and inj.active == {}


def test_gps_stuck_repeats_the_last_fix_before_the_failure():
    inj = FailureInjector()
    inj.gps(P, V)
    inj.inject(f.GPS, f.STUCK, 0)
    for k in range(3):
        p, v = inj.gps(P + k + 1.0, V * 2)
        np.testing.assert_array_equal(p, P)
        np.testing.assert_array_equal(v, V)
    inj.inject(f.GPS, f.OK, 0)
    np.testing.assert_array_equal(inj.gps(P + 5.0, V)[0], P + 5.0)


def test_gps_stuck_before_any_fix_holds_the_first_one():
    inj = FailureInjector()
    inj.inject(f.GPS, f.STUCK, 1)
    np.testing.assert_array_equal(inj.gps(P, V)[0], P)
    np.testing.assert_array_equal(inj.gps(P + 1.0, V)[0], P)


def test_gps_wrong_offsets_the_position_only():
    inj = FailureInjector()
    inj.inject(f.GPS, f.WRONG, 0)
    p, v = inj.gps(P, V)
    np.testing.assert_allclose(p - P, f.GPS_WRONG_OFFSET_ENU_M)
    assert np.linalg.norm(p - P) == pytest.approx(50.0)
    np.testing.assert_array_equal(v, V)


def test_imu_stuck_and_garbage_and_clearing():
    inj = FailureInjector(seed=1)
    assert not inj.imu_or_motor
    inj.inject(f.GYRO, f.STUCK, 0)
    assert inj.imu_or_motor
    g0, a0 = np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.0, 9.8])
    g, a = inj.imu(g0, a0)
    np.testing.assert_array_equal(g, g0)
    g, a = inj.imu(g0 + 1.0, a0 + 1.0)
    np.testing.assert_array_equal(g, g0)  # held
    np.testing.assert_array_equal(a, a0 + 1.0)  # the accelerometer is fine
    inj.inject(f.ACCEL, f.GARBAGE, 1)
    accels = np.array([inj.imu(g0, a0)[1] for _ in range(400)])
    assert np.std(accels - a0) == pytest.approx(f.ACCEL_GARBAGE_STD_M_S2, rel=0.15)
    inj.inject(f.GYRO, f.OK, 0)
    inj.inject(f.ACCEL, f.OK, 0)
    assert not inj.imu_or_motor
    g, a = inj.imu(g0, a0)
    assert g is g0 and a is a0


@pytest.mark.parametrize("instance, zeroed", [(3, [2]), (0, list(range(8)))])
def test_motor_off_zeroes_its_thrust(instance, zeroed):
    inj = FailureInjector()
    thrust = np.full(8, 4.0)
    assert inj.thrust(thrust) is thrust
    assert inj.inject(f.MOTOR, f.OFF, instance) == ("motor off" if instance == 0 else f"motor {instance} off")
    out = inj.thrust(thrust)
    assert list(np.flatnonzero(out == 0.0)) == zeroed
    np.testing.assert_array_equal(thrust, 4.0)  # the firmware's array untouched
    inj.inject(f.MOTOR, f.OK, 0)
    assert inj.thrust(thrust) is thrust


def test_ok_on_one_instance_clears_only_that_one():
    inj = FailureInjector()
    inj.inject(f.MOTOR, f.OFF, 0)
    inj.inject(f.MOTOR, f.OK, 2)
    assert inj.failure(f.MOTOR, 2) == f.OK and inj.failure(f.MOTOR, 1) == f.OFF
    assert len(inj.active) == 7

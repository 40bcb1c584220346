"""The optional barometer and magnetometer: their sensor models (sitl.plant.sensors), their HIL_SENSOR
fields (link_firmware_sim.vehicle.hil) and their fusion in the link EKF (link_firmware_sim.estimators)."""

import math

import numpy as np
import pytest

from companion.estimation.so3 import attitude_error, quat_from_euler_zyx, quat_normalize, quat_to_rotmat, retract
from link_firmware_sim.estimators.ekf import (
    E_BARO,
    E_PZ,
    E_TH,
    E_V,
    NE,
    NE_BARO,
    NX,
    X_BARO,
    X_Q,
    EkfConfig,
    EkfNoise,
    ekf_add_baro_offset,
    ekf_init,
    ekf_predict,
    ekf_update_baro,
    ekf_update_mag_heading,
    mag_heading_jacobian,
)
from link_firmware_sim.estimators import LinkEkf
from link_firmware_sim.geo import MAG_DECLINATION_RAD, MAG_FIELD_NED_GAUSS, pressure_altitude_m, pressure_hpa_at
from link_firmware_sim.vehicle.hil import (
    HIL_SENSOR_BARO,
    HIL_SENSOR_IMU,
    HIL_SENSOR_MAG,
    decode_hil_baro_mag,
    decode_hil_sensor,
    encode_hil_sensor,
)
from sitl.scenario import SensorConfig
from sitl.plant.sensors import MAG_FIELD_ENU_GAUSS, PROFILES, LinkSensors

from ..mavlink_wire import over_mavlink


# -- sensor models ------------------------------------------------------------------------


def test_baro_drift_has_its_std_and_time_constant():
    b = PROFILES["m8_baro_mag"].baro
    n, rate = 300, 2.0
    s = LinkSensors(PROFILES["m8_baro_mag"], n, np.random.default_rng(3))
    p = np.tile([0.0, 0.0, 5.0], (n, 1))  # above the ground effect
    err = np.array([s.baro(k / rate, p) - 5.0 for k in range(int(600 * rate))])  # (time, links)
    total = math.hypot(b.drift_std_m, b.height_std_m)
    assert np.std(err) == pytest.approx(total, rel=0.1)
    lag = int(b.drift_time_constant_s * rate)
    rho = np.mean(err[:-lag] * err[lag:]) / np.mean(err * err)
    assert rho == pytest.approx(math.exp(-1.0) * b.drift_std_m ** 2 / total ** 2, abs=0.08)
    # the white part: consecutive samples differ by sqrt(2) of it (the drift barely moves in 0.5 s)
    assert np.std(np.diff(err, axis=0)) == pytest.approx(math.sqrt(2) * b.height_std_m, rel=0.15)


def test_baro_ground_effect_reads_low_near_the_ground_with_the_rotors_blowing():
    b = PROFILES["m8_baro_mag"].baro
    n = 2000

    def mean_error(height_m, downwash):
        s = LinkSensors(PROFILES["m8_baro_mag"], n, np.random.default_rng(5))
        p = np.tile([0.0, 0.0, height_m], (n, 1))
        return float(np.mean(s.baro(0.0, p, np.full(n, downwash)) - height_m))

    low = mean_error(0.2, 1.0) - mean_error(0.2, 0.0)  # same seed: the same noise, only the effect differs
    assert low == pytest.approx(-b.ground_effect_m * (1.0 - 0.2 / b.ground_effect_height_m), abs=1e-9)
    assert low < 0.0  # over-pressure under the rotors: the barometer reads low
    assert mean_error(0.2, 0.5) - mean_error(0.2, 0.0) == pytest.approx(0.5 * low, abs=1e-9)
    assert mean_error(2.0, 1.0) - mean_error(2.0, 0.0) == 0.0  # above its height: none


def test_mag_is_the_earth_field_plus_a_constant_disturbance_per_link_in_the_body_frame():
    m = PROFILES["m8_baro_mag"].mag
    n = 400
    s = LinkSensors(PROFILES["m8_baro_mag"], n, np.random.default_rng(7))
    q = quat_normalize(np.random.default_rng(8).normal(size=(n, 4)))
    R = quat_to_rotmat(q)
    samples = np.array([np.einsum("nij,nj->ni", R, s.mag(q)) for _ in range(50)])  # back in the world
    per_link = samples.mean(axis=0) - MAG_FIELD_ENU_GAUSS  # the disturbance (white averaged out)
    assert np.std(per_link) == pytest.approx(m.disturbance_std_gauss, rel=0.1)
    assert np.std(samples - samples.mean(axis=0)) == pytest.approx(m.field_std_gauss, rel=0.05)
    np.testing.assert_allclose(MAG_FIELD_ENU_GAUSS, [MAG_FIELD_NED_GAUSS[1], MAG_FIELD_NED_GAUSS[0],
                                                     -MAG_FIELD_NED_GAUSS[2]])


def test_baro_and_mag_leave_every_other_draw_as_it_was():
    """The same seed gives the same GNSS, IMU and attitude errors with and without the barometer
    and magnetometer (a clean comparison), and the profiles without them spawn nothing."""
    a = LinkSensors(PROFILES["m8"], 3, np.random.default_rng(11))
    b = LinkSensors(PROFILES["m8_baro_mag"], 3, np.random.default_rng(11))
    p, q = np.zeros((3, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    for k in range(20):
        t = 0.1 * k
        b.baro(t, p)
        b.mag(q)
        for x, y in zip(a.gps(t, p, p), b.gps(t, p, p)):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(a.attitude(t, q), b.attitude(t, q))
        np.testing.assert_array_equal(a.imu(p, p, 0.1)[1], b.imu(p, p, 0.1)[1])
    rng = np.random.default_rng(0)
    outdoor = LinkSensors(PROFILES["outdoor"], 3, rng)
    assert not outdoor.has_baro and not outdoor.has_mag and outdoor._aux_rng is None
    assert rng.bit_generator.seed_seq.n_children_spawned == 0
    with pytest.raises(RuntimeError, match="no barometer"):
        outdoor.baro(0.0, p)


def test_scenario_tables_fit_override_and_name_bad_keys():
    assert SensorConfig(profile="m8").suite().baro is None
    assert SensorConfig(profile="m8_baro_mag").suite().mag == PROFILES["m8_baro_mag"].mag
    fitted = SensorConfig(profile="outdoor", baro={"height_std_m": 0.2}, mag={}).suite()
    assert fitted.baro.height_std_m == 0.2 and fitted.gps == PROFILES["outdoor"].gps
    assert fitted.mag == PROFILES["m8_baro_mag"].mag  # an empty table: the defaults
    with pytest.raises(ValueError, match="mag: unknown field 'hard_iron'"):
        SensorConfig(profile="m8_baro_mag", mag={"hard_iron": 0.1})
    with pytest.raises(ValueError, match="baro: drift_time_constant_s must be positive"):
        SensorConfig(profile="m8_baro_mag", baro={"drift_time_constant_s": 0.0})


# -- HIL_SENSOR ----------------------------------------------------------------------------


def test_standard_atmosphere_round_trip():
    assert pressure_hpa_at(0.0) == pytest.approx(1013.25)
    assert pressure_hpa_at(488.0) == pytest.approx(956.0, abs=0.05)  # ~0.11 hPa per metre here
    assert pressure_hpa_at(487.0) - pressure_hpa_at(488.0) == pytest.approx(0.113, abs=0.002)
    for h in (-200.0, 0.0, 488.0, 3000.0):
        assert pressure_altitude_m(pressure_hpa_at(h)) == pytest.approx(h, abs=1e-6)


def test_hil_sensor_carries_baro_and_mag_only_when_simulated():
    acc, gyr = np.array([0.1, -0.2, 9.8]), np.array([0.01, 0.02, -0.03])
    plain = over_mavlink(encode_hil_sensor(1.0, acc, gyr))
    assert plain.fields_updated == HIL_SENSOR_IMU
    assert decode_hil_baro_mag(plain).baro_alt_m is None and decode_hil_baro_mag(plain).mag_flu_gauss is None
    mag = np.array([0.2, -0.05, -0.41])  # FLU
    msg = over_mavlink(encode_hil_sensor(1.0, acc, gyr, mag_flu_gauss=mag, baro_alt_m=490.345))
    assert msg.fields_updated == HIL_SENSOR_IMU | HIL_SENSOR_MAG | HIL_SENSOR_BARO
    np.testing.assert_allclose([msg.xmag, msg.ymag, msg.zmag], [0.2, 0.05, 0.41], rtol=1e-6)  # body FRD
    assert msg.abs_pressure == pytest.approx(pressure_hpa_at(490.345), rel=1e-7)  # hPa
    assert msg.pressure_alt == pytest.approx(490.345, abs=1e-4)
    out = decode_hil_baro_mag(msg)
    assert out.rejected == ()
    assert out.baro_alt_m == pytest.approx(490.345, abs=0.01)  # float32 pressure: ~1 mm
    np.testing.assert_allclose(out.mag_flu_gauss, mag, rtol=1e-6)
    t, g, a = decode_hil_sensor(msg)
    np.testing.assert_allclose(a, acc, rtol=1e-6)


@pytest.mark.parametrize("field, value, sensor", [
    ("abs_pressure", math.nan, "baro"), ("abs_pressure", 5000.0, "baro"), ("abs_pressure", 0.0, "baro"),
    ("xmag", math.nan, "mag"), ("zmag", math.inf, "mag"), ("ymag", 12.0, "mag"),
])
def test_invalid_baro_or_mag_is_dropped_not_raised(field, value, sensor):
    msg = encode_hil_sensor(2.0, np.zeros(3), np.zeros(3), mag_flu_gauss=np.array([0.2, 0.0, -0.4]), baro_alt_m=500.0)
    setattr(msg, field, value)
    out = decode_hil_baro_mag(over_mavlink(msg))
    assert out.rejected == (sensor,)
    assert (out.baro_alt_m is None) == (sensor == "baro") and (out.mag_flu_gauss is None) == (sensor == "mag")
    decode_hil_sensor(over_mavlink(msg))  # the IMU part is still good


# -- EKF -------------------------------------------------------------------------------------


def test_mag_heading_jacobian_matches_finite_differences():
    rng = np.random.default_rng(2)
    for _ in range(20):
        q = quat_normalize(rng.normal(size=4))
        mb = rng.normal(size=3)

        def phi(dtheta):
            m = quat_to_rotmat(retract(q, dtheta)) @ mb
            return math.atan2(m[1], m[0])

        h = 1e-6
        fd = [(phi(h * e) - phi(-h * e)) / (2 * h) for e in np.eye(3)]
        np.testing.assert_allclose(mag_heading_jacobian(q, mb), fd, rtol=1e-5, atol=1e-6)


def test_mag_heading_update_corrects_the_yaw_and_ignores_a_vertical_field():
    q_true = quat_from_euler_zyx(0.7, 0.2, -0.1)
    earth_enu = np.array([MAG_FIELD_NED_GAUSS[1], MAG_FIELD_NED_GAUSS[0], -MAG_FIELD_NED_GAUSS[2]])
    mb = quat_to_rotmat(q_true).T @ earth_enu  # what the magnetometer reads (no noise)
    x, P = ekf_init(np.zeros(3), np.zeros(3), quat_from_euler_zyx(0.75, 0.2, -0.1), EkfConfig())
    P[E_TH, E_TH] = np.diag([1e-6, 1e-6, 0.05])  # tilt known (gravity), heading not
    x2, P2, info = ekf_update_mag_heading(x, P, mb, MAG_DECLINATION_RAD, 1e-4)
    assert info.accepted and info.innovation[0] == pytest.approx(-0.05, abs=1e-9)  # estimate 0.05 rad to the left
    err_before = np.linalg.norm(attitude_error(q_true, x[X_Q]))
    err_after = np.linalg.norm(attitude_error(q_true, x2[X_Q]))
    assert err_before == pytest.approx(0.05, abs=1e-6)
    assert err_after < 0.01 * err_before and P2[E_TH, E_TH][2, 2] < 0.01 * P[E_TH, E_TH][2, 2]
    # with the tilt as uncertain as the heading, the field's 63 deg inclination turns part of the
    # heading residual into tilt (the Jacobian's tilt terms): the heading moves less
    P[E_TH, E_TH] = 0.05 * np.eye(3)
    x3, _, _ = ekf_update_mag_heading(x, P, mb, MAG_DECLINATION_RAD, 1e-4)
    assert np.linalg.norm(attitude_error(q_true, x3[X_Q])) > 5 * err_after
    vertical_b = quat_to_rotmat(x[X_Q]).T @ [0.0, 0.0, -0.5]
    x4, P4, info = ekf_update_mag_heading(x, P, vertical_b, MAG_DECLINATION_RAD, 1e-4)
    assert not info.accepted and x4 is x and P4 is P  # a vertical field has no heading: skipped


_HOVER = (np.zeros(3), np.array([0.0, 0.0, 9.80665]))  # a level link at rest: gyro, accelerometer
_NOISE = EkfNoise(pos_m2_s=1e-3, vel_m2_s3=1e-2, att_rad2_s=1e-5, baro_bias_m2_s=1e-4)


def test_baro_offset_gives_relative_height_only():
    """Referenced against the EKF's height, the barometer cannot make the absolute height better
    known than it was (its offset's error is minus the height's), but it stops the height's
    uncertainty from growing: it measures the changes."""
    x, P = ekf_init(np.zeros(3), np.zeros(3), [1.0, 0.0, 0.0, 0.0], EkfConfig(init_pos_var_m2=0.5, init_vel_var_m2_s2=0.1))
    x, P = ekf_add_baro_offset(x, P, 500.0, 0.01)
    assert len(x) == NX + 1 and P.shape == (NE_BARO, NE_BARO)
    assert x[X_BARO][0] == pytest.approx(500.0)
    assert P[E_BARO, E_PZ][0, 0] == pytest.approx(-0.5) and P[E_BARO, E_BARO][0, 0] == pytest.approx(0.51)
    x_free, P_free = x.copy(), P.copy()
    _, _, info = ekf_update_baro(x, P, 500.3, 0.01)
    assert info.accepted  # at once, z + b is known to the sample's noise: nothing to learn about z
    for _ in range(250):  # 5 s: the barometer at 50 Hz says the height does not change
        x, P = ekf_predict(x, P, *_HOVER, 0.02, _NOISE)
        x_free, P_free = ekf_predict(x_free, P_free, *_HOVER, 0.02, _NOISE)
        x, P, info = ekf_update_baro(x, P, 500.0, 0.01)
        assert info.accepted
    assert P[2, 2] > 0.5  # the absolute height: as uncertain as at the reference (plus the walk)
    assert P[2, 2] < 0.6 < P_free[2, 2]  # ... where without the barometer it grows (0.5 + 5 s of 0.1 m^2/s^2)
    assert P[E_V, E_V][2, 2] < 0.01 < P_free[E_V, E_V][2, 2]  # the vertical velocity: learned
    np.testing.assert_array_equal(P, P.T)
    assert np.all(np.linalg.eigvalsh(P) > -1e-12)
    # a barometer 0.3 m higher than the reference now moves the height (and the velocity) up
    x2, _, _ = ekf_update_baro(x, P, 500.3, 0.01)
    assert x2[2] > x[2] + 0.01


def test_baro_ground_effect_deadzone():
    x, P = ekf_init(np.zeros(3), np.zeros(3), [1.0, 0.0, 0.0, 0.0], EkfConfig())
    x, P = ekf_add_baro_offset(x, P, 100.0, 0.01)
    for _ in range(50):  # 1 s without a barometer: the height's changes are uncertain again
        x, P = ekf_predict(x, P, *_HOVER, 0.02, _NOISE)
    low = 100.0 - 0.4  # reads 0.4 m low: inside a 1 m deadzone nothing moves, outside the height drops
    x_ge, _, info = ekf_update_baro(x, P, low, 0.01, deadzone_m=1.0)
    assert info.accepted and info.innovation[0] == 0.0 and x_ge[2] == pytest.approx(x[2])
    x_free, _, info = ekf_update_baro(x, P, low, 0.01, gate_sigma=50.0)
    assert info.innovation[0] == pytest.approx(-0.4) and x_free[2] < x[2]
    _, _, info = ekf_update_baro(x, P, 100.0 - 1.5, 0.01, deadzone_m=1.0, gate_sigma=50.0)
    assert info.innovation[0] == pytest.approx(-0.5)
    x_high, _, _ = ekf_update_baro(x, P, 100.4, 0.01, deadzone_m=1.0, gate_sigma=50.0)
    assert x_high[2] > x[2]  # reading high is not ground effect


def test_link_ekf_methods_agree_with_the_functions():
    cfg = EkfConfig(baro_var_m2=0.02, mag_heading_var_rad2=0.03, baro_ground_effect_deadzone_m=0.7)
    rng = np.random.default_rng(9)
    q = quat_normalize(rng.normal(size=4))
    ekf = LinkEkf(rng.normal(size=3), rng.normal(size=3), q, cfg, compiled=False)  # the numpy specification
    x, P = ekf.x.copy(), ekf.P.copy()
    assert ekf.update_baro(50.0).accepted and ekf.baro_referenced  # the reference
    x, P = ekf_add_baro_offset(x, P, 50.0, cfg.baro_var_m2)
    np.testing.assert_array_equal(ekf.x, x)
    np.testing.assert_array_equal(ekf.P, P)
    for h, ge in ((50.3, False), (49.6, True)):
        ekf.update_baro(h, ground_effect=ge)
        x, P, _ = ekf_update_baro(x, P, h, cfg.baro_var_m2, cfg.gate_sigma, 0.7 if ge else 0.0)
        np.testing.assert_array_equal(ekf.x, x)
        np.testing.assert_array_equal(ekf.P, P)
    mb = np.array([0.1, 0.15, -0.4])
    ekf.update_mag(mb)
    x, P, _ = ekf_update_mag_heading(x, P, mb, cfg.mag_declination_rad, cfg.mag_heading_var_rad2, cfg.gate_sigma)
    np.testing.assert_array_equal(ekf.x, x)
    np.testing.assert_array_equal(ekf.P, P)
    assert ekf.accepted["baro"] == 3 and ekf.accepted["mag"] + ekf.rejected["mag"] == 1
    ekf.predict(np.zeros(3), [0.0, 0.0, 9.80665], 0.002)  # the offset rides along
    assert ekf.baro_referenced and ekf.P.shape == (NE_BARO, NE_BARO)
    ekf.reset_position(np.zeros(3))  # a position reset takes the reference again
    assert not ekf.baro_referenced and ekf.P.shape == (NE, NE)


# -- a flight --------------------------------------------------------------------------------


def _hover_with_gps_outage(profile: str, seed: int):
    from companion.skeleton.body import SkeletonConfig
    from companion.trajectory import TrajectoryConfig
    from sitl.scenario import FaultConfig, GpsFault, Scenario, SitlCompanionConfig
    from sitl.plant.start import StartPose

    return Scenario(name="outage", duration_s=22.0, seed=seed, skeleton=SkeletonConfig(n_links=1),
                    start=StartPose(center_w_m=(0.0, 0.0, 2.0), on_ground=False),
                    sensors=SensorConfig(profile=profile), companion=SitlCompanionConfig(enabled=False),
                    # 1.5 m above where it arms: out of the band where the firmware takes a low
                    # barometer for the rotors' ground effect (baro_ground_effect_height_m)
                    trajectory=TrajectoryConfig(kind="hover", takeoff_start_s=0.0, takeoff_duration_s=1.0,
                                                takeoff_altitude_m=3.5),
                    faults=FaultConfig(gps=GpsFault(link=1, outage_at_s=6.0, outage_s=16.0)))


@pytest.mark.integration
def test_the_barometer_holds_the_height_through_a_gnss_outage():
    """m8 against m8_baro_mag (the same GNSS, IMU and attitude errors, seeded): a hovering link
    loses its GNSS fix for 16 s. Without a barometer its height dead-reckons on the IMU (tens of
    centimetres to metres); with one the height error stays where it was at the outage's start.
    Before the outage both err alike (the barometer cannot tell the absolute height: the GNSS's
    few-metre error at the reference stays)."""
    from sitl.runner import BatchRunner

    drift: dict[str, list] = {"m8": [], "m8_baro_mag": []}
    before: dict[str, list] = {"m8": [], "m8_baro_mag": []}
    for seed in (0, 1):
        for profile in drift:
            runner = BatchRunner(_hover_with_gps_outage(profile, seed))
            runner.run(22.0)
            assert not runner.crashed, runner.crash_reason
            log = runner.log.arrays()
            t = log["t"]
            ez = log["p_ekf"][:, 0, 2] - log["p_true"][:, 0, 2]
            before[profile].append(ez[(t > 5.0) & (t < 6.0)].mean())
            drift[profile].append(ez[t >= 6.0] - before[profile][-1])
            if profile == "m8_baro_mag":
                ekf = runner.firmware[0].ekf
                assert ekf.baro_referenced and ekf.rejected["baro"] == 0 and ekf.accepted["mag"] > 900
    np.testing.assert_allclose(before["m8_baro_mag"], before["m8"], atol=0.3)
    rms = {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in drift.items()}
    assert rms["m8_baro_mag"] < 0.15, rms
    assert rms["m8_baro_mag"] < 0.35 * rms["m8"], rms

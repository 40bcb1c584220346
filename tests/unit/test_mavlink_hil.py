import numpy as np
import pytest

from companion.estimation.so3 import quat_normalize, quat_to_rotmat
from companion.mavlink.codec import MessageError
from companion.mavlink.dialect import load_dialect
from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.vehicle.hil import (
    decode_actuators,
    thrusts_from_controls,
    decode_ahrs,
    decode_hil_gps,
    decode_hil_sensor,
    encode_actuators,
    encode_ahrs,
    encode_hil_gps,
    encode_hil_sensor,
)

from ..mavlink_wire import over_mavlink

D = load_dialect()


def test_sensor_round_trip():
    rng = np.random.default_rng(0)
    acc, gyr = rng.normal(size=3) + [0, 0, 9.8], rng.normal(size=3)
    t, g, a = decode_hil_sensor(over_mavlink(encode_hil_sensor(1.234, acc, gyr)))
    assert t == pytest.approx(1.234, abs=1e-6)
    np.testing.assert_allclose(a, acc, rtol=1e-6)
    np.testing.assert_allclose(g, gyr, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("p", [[0.0, 0.0, 0.0], [120.0, -80.0, 35.0], [-3.3, 4.4, 2.5]])
def test_gps_round_trip_to_centimetres(p):
    origin = GeoOrigin()
    v = np.array([1.23, -0.45, 0.67])
    t, p2, v2 = decode_hil_gps(over_mavlink(encode_hil_gps(7.0, np.array(p), v, origin)), origin)
    assert t == pytest.approx(7.0)
    np.testing.assert_allclose(p2, p, atol=0.012)  # 1e-7 deg quantisation, mm altitude
    np.testing.assert_allclose(v2, v, atol=0.006)  # cm/s quantisation


def test_geodetic_origin_maps_north_and_east():
    origin = GeoOrigin(lat_deg=10.0, lon_deg=20.0, alt_m=100.0)
    lat, lon, alt = origin.to_geodetic(np.array([0.0, 1000.0, 5.0]))
    assert lat > 10.0 and lon == pytest.approx(20.0) and alt == pytest.approx(105.0)
    lat, lon, _ = origin.to_geodetic(np.array([1000.0, 0.0, 0.0]))
    assert lon > 20.0 and lat == pytest.approx(10.0)
    with pytest.raises(ValueError, match="lat_deg"):
        GeoOrigin(lat_deg=95.0)


def test_gps_without_fix_is_rejected():
    msg = encode_hil_gps(1.0, np.zeros(3), np.zeros(3), GeoOrigin())
    msg.fix_type = 1
    with pytest.raises(MessageError, match="fix"):
        decode_hil_gps(msg, GeoOrigin())


def test_ahrs_round_trip():
    q = quat_normalize(np.random.default_rng(1).normal(size=4))
    t, q2 = decode_ahrs(over_mavlink(encode_ahrs(2.0, q)))
    np.testing.assert_allclose(quat_to_rotmat(q2), quat_to_rotmat(q), atol=1e-6)


def test_actuators_round_trip_and_limits():
    thrust = np.array([8.0, -8.0, 3.0, -2.5, 0.0, 1.0, 9.0, -12.0])
    t_us, back = decode_actuators(over_mavlink(encode_actuators(0.5, thrust, 8.0, True)), 8.0)
    assert t_us == 500000
    np.testing.assert_allclose(back, np.clip(thrust, -8, 8), rtol=1e-6)
    assert over_mavlink(encode_actuators(0.5, thrust, 8.0, True)).mode & D.MAV_MODE_FLAG_SAFETY_ARMED


def test_a_ticks_answers_decode_together_as_each_alone_and_a_non_finite_row_is_named():
    """The harness decodes all links' HIL_ACTUATOR_CONTROLS of a tick in one call: the same thrusts
    as one message at a time; a non-finite control names its row."""
    rng = np.random.default_rng(5)
    thrust = rng.uniform(-12.0, 12.0, size=(4, 8))
    msgs = [over_mavlink(encode_actuators(0.5, row, 8.0, True)) for row in thrust]
    rows = np.array([m.controls[:8] for m in msgs])
    together = thrusts_from_controls(rows, 8.0)
    for i, m in enumerate(msgs):
        np.testing.assert_array_equal(together[i], decode_actuators(m, 8.0)[1])
    np.testing.assert_allclose(together, np.clip(thrust, -8.0, 8.0), rtol=1e-6)
    rows[2, 5] = np.nan
    rows[3, 0] = np.inf
    with pytest.raises(MessageError, match=r"row\(s\) \[2, 3\]"):
        thrusts_from_controls(rows, 8.0)

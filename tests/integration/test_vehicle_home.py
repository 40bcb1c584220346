"""The vehicle's home position over real MAVLink bytes: set once the EKF runs on the ground and
again at arming, set by MAV_CMD_DO_SET_HOME (COMMAND_LONG and COMMAND_INT), refused when out of
range, reported as HOME_POSITION on request and on change; the pre-arm bit of SYS_STATUS."""

import math

import numpy as np
import pytest

from companion.mavlink.dialect import load_dialect
from link_firmware_sim.vehicle.home import MAX_HOME_DISTANCE_M, HomePosition
from link_firmware_sim.vehicle.streams.system import sys_status

from ..vehicle_rig import ORIGIN

pytestmark = pytest.mark.usefixtures("compiled_kernels")
D = load_dialect()


def _homes(msgs):
    return [m for m in msgs if m.get_type() == "HOME_POSITION"]


def _acks(msgs, command):
    return [m.result for m in msgs if m.get_type() == "COMMAND_ACK" and m.command == command]


def _local_ned(home):
    return np.array([home.x, home.y, home.z])


def _heading_deg(home):
    """HOME_POSITION's heading: ``q`` is a rotation about the down axis (NED yaw, clockwise from north)."""
    return math.degrees(2.0 * math.atan2(home.q[3], home.q[0]))


def _request_home(rig, command=D.MAV_CMD_REQUEST_MESSAGE):
    param1 = D.MAVLINK_MSG_ID_HOME_POSITION if command == D.MAV_CMD_REQUEST_MESSAGE else 0
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, command, 0, param1, 0, 0, 0, 0, 0, 0))
    return rig.gcs_collect(0.02)


def test_no_home_before_the_ekf_then_the_first_estimate_on_the_ground(rig):
    msgs = _request_home(rig)
    assert _acks(msgs, D.MAV_CMD_REQUEST_MESSAGE) == [D.MAV_RESULT_TEMPORARILY_REJECTED] and not _homes(msgs)
    assert not sys_status(rig.vehicle).onboard_control_sensors_health & D.MAV_SYS_STATUS_PREARM_CHECK
    rig.start()
    msgs = rig.gcs_collect(0.05)
    assert rig.vehicle.home.position is not None
    assert sys_status(rig.vehicle).onboard_control_sensors_health & D.MAV_SYS_STATUS_PREARM_CHECK
    for command in (D.MAV_CMD_REQUEST_MESSAGE, D.MAV_CMD_GET_HOME_POSITION):
        msgs = _request_home(rig, command)
        assert _acks(msgs, command) == [D.MAV_RESULT_ACCEPTED]
        home = _homes(msgs)[-1]
        # where the fake GPS put the link: the origin, 2 m up (the EKF's estimate, to centimetres)
        np.testing.assert_allclose(_local_ned(home), [0.0, 0.0, -rig.height_m], atol=0.05)
        assert home.latitude == pytest.approx(ORIGIN.lat_deg * 1e7, abs=10)
        assert home.longitude == pytest.approx(ORIGIN.lon_deg * 1e7, abs=10)
        assert home.altitude == pytest.approx((ORIGIN.alt_m + rig.height_m) * 1e3, abs=50)
        assert _heading_deg(home) == pytest.approx(90.0, abs=0.5)  # the fake AHRS: ENU yaw 0, facing east


def test_arming_sets_the_home_again_and_every_link_hears_it(rig):
    rig.start()
    first = rig.vehicle.home.position
    rig.height_m += 0.5  # the link moved on the ground before arming
    for k in range(300):
        rig.tick(gps=k % 50 == 0)
    assert rig.vehicle.home.position is first  # not moved while disarmed
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    msgs = rig.gcs_collect(0.02)
    assert _acks(msgs, D.MAV_CMD_COMPONENT_ARM_DISARM) == [D.MAV_RESULT_ACCEPTED]
    homes = _homes(msgs)  # sent at once, not at the stream's next turn
    assert homes and homes[-1].time_usec > first.time_us
    assert -homes[-1].z > first.p_w_m[2] + 0.2  # where it armed, not where it first was
    # arming again (a retried command) changes nothing
    before = rig.vehicle.home.position
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    rig.gcs_collect(0.02)
    assert rig.vehicle.home.position is before


@pytest.mark.parametrize("motion", ["falling", "hanging still", "carried sideways"])
def test_arming_in_flight_keeps_the_home(rig, motion):
    """Re-armed in the air (after a forced disarm, or a reboot while its neighbours carry it): PX4
    sets no home in the air. Falling, the land detector says so; still or moving sideways, its
    height above the home does."""
    rig.vel_m_s = {"falling": np.array([0.0, 0.0, -2.0]), "hanging still": np.zeros(3),
                   "carried sideways": np.array([2.0, 0.0, 0.0])}[motion]
    rig.height_m = 6.6
    rig.start(0.5)
    if motion != "falling":  # its home where it rested before its neighbours lifted it, 4.6 m lower
        here = rig.vehicle.home.position
        rig.vehicle.home.position = HomePosition(here.p_w_m - [0.0, 0.0, 4.6], here.heading_ned_rad, here.time_us)
    before = rig.vehicle.home.position
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    msgs = rig.gcs_collect(0.02)
    assert _acks(msgs, D.MAV_CMD_COMPONENT_ARM_DISARM) == [D.MAV_RESULT_ACCEPTED]
    assert rig.vehicle.home.position is before and not _homes(msgs)


@pytest.mark.parametrize("kind", ["long", "int"])
def test_do_set_home_at_a_given_place_and_here(rig, kind):
    rig.start()
    lat, lon = ORIGIN.lat_deg + 1e-4, ORIGIN.lon_deg - 2e-4  # about 11 m north, 15 m west
    alt = ORIGIN.alt_m + 3.0
    if kind == "long":
        msg = D.MAVLink_command_long_message(2, 1, D.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, -30.0, lat, lon, alt)
    else:
        msg = D.MAVLink_command_int_message(2, 1, D.MAV_FRAME_GLOBAL, D.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, 0, -30.0,
                                            int(round(lat * 1e7)), int(round(lon * 1e7)), alt)
    rig.gcs_send(msg)
    msgs = rig.gcs_collect(0.02)
    assert _acks(msgs, D.MAV_CMD_DO_SET_HOME) == [D.MAV_RESULT_ACCEPTED]
    home = _homes(msgs)[-1]
    if kind == "long":  # (COMMAND_LONG's params are float32: decimetres at this latitude)
        lat, lon, alt = (float(np.float32(x)) for x in (lat, lon, alt))
    assert home.latitude == int(round(lat * 1e7)) and home.longitude == int(round(lon * 1e7))
    assert home.altitude == int(round(alt * 1e3))
    np.testing.assert_allclose(_local_ned(home), [ORIGIN.to_enu(lat, lon, alt)[i] for i in (1, 0)] + [-3.0],
                               atol=1e-3)
    assert _heading_deg(home) == pytest.approx(-30.0)  # as given
    # param1 1: here (the estimate), with the vehicle's heading when param4 is NaN
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_DO_SET_HOME, 0, 1, 0, 0, math.nan, 0, 0, 0))
    msgs = rig.gcs_collect(0.02)
    assert _acks(msgs, D.MAV_CMD_DO_SET_HOME) == [D.MAV_RESULT_ACCEPTED]
    home = _homes(msgs)[-1]
    np.testing.assert_allclose(_local_ned(home), [0.0, 0.0, -rig.height_m], atol=0.05)
    assert _heading_deg(home) == pytest.approx(90.0, abs=0.5)


def test_a_home_given_at_a_place_outlasts_arming_and_here_gives_it_back_to_arming(rig):
    """As PX4: a home sent as a place (QGroundControl's "set home here" on the map) is the user's,
    and arming keeps it; DO_SET_HOME here (param1 1) makes it the vehicle's again, which arming
    then sets where it arms. param4 is not read with param1 1: the vehicle's heading."""
    rig.start()
    lat, lon, alt = ORIGIN.lat_deg + 1e-4, ORIGIN.lon_deg, ORIGIN.alt_m
    rig.gcs_send(D.MAVLink_command_int_message(2, 1, D.MAV_FRAME_GLOBAL, D.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, 0,
                                               math.nan, int(round(lat * 1e7)), int(round(lon * 1e7)), alt))
    rig.gcs_collect(0.02)
    given = rig.vehicle.home.position
    assert given.given
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0))
    rig.gcs_collect(0.02)
    assert rig.vehicle.home.position is given and not rig.vehicle.fw.armed
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_DO_SET_HOME, 0, 1, 0, 0, 45.0, 0, 0, 0))
    home = _homes(rig.gcs_collect(0.02))[-1]
    assert _heading_deg(home) == pytest.approx(90.0, abs=0.5) and not rig.vehicle.home.position.given
    here = rig.vehicle.home.position
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    rig.gcs_collect(0.02)
    assert rig.vehicle.fw.armed and rig.vehicle.home.position is not here


def test_do_set_home_here_before_the_ekf_is_temporarily_rejected(rig):
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_DO_SET_HOME, 0, 1, 0, 0, 0, 0, 0, 0))
    msgs = rig.gcs_collect(0.02)
    assert _acks(msgs, D.MAV_CMD_DO_SET_HOME) == [D.MAV_RESULT_TEMPORARILY_REJECTED] and not _homes(msgs)


far = MAX_HOME_DISTANCE_M + 100.0


@pytest.mark.parametrize("lat, lon, alt, text", [
    (91.0, ORIGIN.lon_deg, ORIGIN.alt_m, "lat/lon"),
    (ORIGIN.lat_deg, 181.0, ORIGIN.alt_m, "lat/lon"),
    (ORIGIN.lat_deg + math.degrees(far / 6371000.0), ORIGIN.lon_deg, ORIGIN.alt_m, "from origin"),
    (ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m - far, "from origin"),
    # 800 m north and 800 m east: each axis within the limit, the distance beyond it
    (ORIGIN.lat_deg + math.degrees(800.0 / 6371000.0),
     ORIGIN.lon_deg + math.degrees(800.0 / (6371000.0 * math.cos(math.radians(ORIGIN.lat_deg)))), ORIGIN.alt_m,
     "from origin"),
])
def test_a_home_out_of_range_is_denied_with_a_reason_and_the_home_kept(rig, lat, lon, alt, text):
    rig.start()
    before = rig.vehicle.home.position
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, 0, lat, lon, alt))
    msgs = rig.gcs_collect(0.02)
    assert _acks(msgs, D.MAV_CMD_DO_SET_HOME) == [D.MAV_RESULT_DENIED]
    assert any(m.get_type() == "STATUSTEXT" and text in m.text for m in msgs)
    assert rig.vehicle.home.position is before


@pytest.mark.parametrize("params", [
    (math.nan, 0, 0, 0, 0, 0, 0),
    (0, 0, 0, 0, math.nan, ORIGIN.lon_deg, ORIGIN.alt_m),
    (0, 0, 0, 0, ORIGIN.lat_deg, ORIGIN.lon_deg, math.inf),
    (0, 0, 0, math.inf, ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m),
])
def test_a_non_finite_set_home_is_a_bad_message(rig, params):
    rig.start()
    before, errors = rig.vehicle.home.position, rig.vehicle.errors["mavlink"]
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_DO_SET_HOME, 0, *params))
    msgs = rig.gcs_collect(0.02)
    assert not _acks(msgs, D.MAV_CMD_DO_SET_HOME)
    assert rig.vehicle.errors["mavlink"] == errors + 1 and rig.vehicle.home.position is before


def test_set_home_in_a_relative_frame_is_unsupported(rig):
    rig.start()
    rig.gcs_send(D.MAVLink_command_int_message(2, 1, D.MAV_FRAME_GLOBAL_RELATIVE_ALT, D.MAV_CMD_DO_SET_HOME, 0, 0,
                                               0, 0, 0, 0, int(ORIGIN.lat_deg * 1e7), int(ORIGIN.lon_deg * 1e7), 1.0))
    assert _acks(rig.gcs_collect(0.02), D.MAV_CMD_DO_SET_HOME) == [D.MAV_RESULT_UNSUPPORTED]


def test_a_new_origin_clears_the_home_and_the_next_estimate_sets_it(rig):
    rig.start()
    before = rig.vehicle.home.position
    assert before is not None
    rig.gcs_send(D.MAVLink_set_gps_global_origin_message(2, int(ORIGIN.lat_deg * 1e7) + 100,
                                                         int(ORIGIN.lon_deg * 1e7), int(ORIGIN.alt_m * 1e3), 0))
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_REQUEST_MESSAGE, 0, D.MAVLINK_MSG_ID_HOME_POSITION,
                                                0, 0, 0, 0, 0, 0))
    homes = _homes(rig.gcs_collect(0.05))
    home = rig.vehicle.home.position
    assert rig.vehicle.origin.lat_deg != ORIGIN.lat_deg and home is not before and home.time_us > before.time_us
    lat, lon, _ = rig.vehicle.origin.to_geodetic(home.p_w_m)  # (the new origin's)
    assert homes[-1].latitude == int(round(lat * 1e7)) and homes[-1].longitude == int(round(lon * 1e7))

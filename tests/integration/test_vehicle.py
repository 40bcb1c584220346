"""The vehicle's MAVLink services, driven in-process over real loopback sockets."""

import json
import math
import socket
import struct
import time
from dataclasses import replace

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_euler_zyx, quat_to_rotmat
from companion.mavlink.frames import enu_ned
from companion.mavlink.codec import MessageError, encode_correction, encode_target_feedforward
from companion.mavlink.standard import encode_attitude_target
from companion.mavlink.dialect import load_dialect
from companion.mavlink.port import MavlinkPort
from companion.mavlink.signing import SigningConfig, load_key, signing_timestamp
from companion.messages import Correction, PoseTarget
from companion.skeleton.body import LinkInertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.estimators import X_BARO
from link_firmware_sim.geo import MAG_FIELD_NED_GAUSS
from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware
from link_firmware_sim.vehicle.core import Vehicle
from link_firmware_sim.vehicle.links import VehiclePorts
from link_firmware_sim.vehicle.params import ParamTable, StreamRates

from ..vehicle_rig import LEVEL, ORIGIN, Rig

#: the kernels compiled (or loaded) before a vehicle here runs against a deadline
pytestmark = pytest.mark.usefixtures("compiled_kernels")

D = load_dialect()


def _types(msgs):
    return [m.get_type() for m in msgs]


def test_heartbeat_and_answer_before_ekf_start(rig):
    thrust = rig.tick()  # no GPS yet: the EKF waits, the lockstep still gets an answer
    np.testing.assert_array_equal(thrust, 0.0)
    msgs = rig.gcs_collect(0.2)
    hb = [m for m in msgs if m.get_type() == "HEARTBEAT"]
    assert hb and hb[0].get_srcSystem() == 2 and hb[0].autopilot == D.MAV_AUTOPILOT_PX4
    assert hb[0].type == D.MAV_TYPE_OCTOROTOR


def test_silent_until_the_simulator_connects_like_px4_sitl(tmp_path):
    """A firmware process waiting for its simulator sends nothing (a scripted reboot starts the new
    process early and powers it on when the harness connects); then its heartbeat comes at once."""
    gcs = MavlinkPort("udpin://127.0.0.1:0", system_id=255, component_id=190)
    fw = LinkFirmware(1, FirmwareConfig(), LinkInertia(1.8, (0.04, 0.16, 0.16)), RotorGeometry.odar())
    params = ParamTable(2, FirmwareConfig(), ORIGIN, StreamRates(50.0, 0.0), tmp_path / "p.json")
    ports = VehiclePorts(sim="tcpin://127.0.0.1:0", onboard=f"udpout://127.0.0.1:{gcs.transport.local_port()}", gcs=None)
    vehicle = Vehicle(1, fw, params, ports, tmp_path / "out", key_path=tmp_path / "vehicle.key")
    sim = None
    try:
        end = time.monotonic() + 1.2  # longer than the heartbeat period
        while time.monotonic() < end:
            vehicle.poll(0.02)
            assert not gcs.read(), "the firmware spoke before its simulator connected"
        sim = MavlinkPort(f"tcpout://127.0.0.1:{vehicle.sim.transport.local_port()}", system_id=250, component_id=1)
        got = []
        end = time.monotonic() + 0.5
        while time.monotonic() < end and not got:
            vehicle.poll(0.02)
            got = [m for m in gcs.read() if m.get_type() == "HEARTBEAT"]
        assert got and got[0].get_srcSystem() == 2
    finally:
        vehicle.close()
        gcs.close()
        if sim is not None:
            sim.close()


def test_arming_is_refused_until_the_ekf_runs_then_accepted(rig):
    rig.gcs_collect(0.05)  # let the GCS port learn the vehicle's address
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    acks = [m for m in rig.gcs_collect(0.1) if m.get_type() == "COMMAND_ACK"]
    assert acks[0].result == D.MAV_RESULT_TEMPORARILY_REJECTED
    rig.start()
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    acks = [m for m in rig.gcs_collect(0.1) if m.get_type() == "COMMAND_ACK"]
    assert acks[0].result == D.MAV_RESULT_ACCEPTED and rig.vehicle.fw.armed
    thrust = rig.tick()
    assert np.abs(thrust).sum() > 10.0  # armed: carrying its weight


def test_parameter_protocol_and_persistence(tmp_path):
    rig = Rig(tmp_path)
    try:
        rig.start()
        rig.gcs_send(D.MAVLink_param_request_list_message(2, 1))
        values = [m for m in rig.gcs_collect(0.2) if m.get_type() == "PARAM_VALUE"]
        names = {m.param_id for m in values}
        assert {"IMP_KP_Z", "COM_OF_LOSS_T", "SKL_STATE_HZ", "MAV_SYS_ID"} <= names
        assert all(m.param_count == len(rig.vehicle.params.names) for m in values)
        sysid = next(m for m in values if m.param_id == "MAV_SYS_ID")
        assert sysid.param_type == D.MAV_PARAM_TYPE_INT32
        assert struct.unpack("<i", struct.pack("<f", sysid.param_value))[0] == 2  # bytewise (PX4)
        rig.gcs_send(D.MAVLink_param_set_message(2, 1, b"IMP_KP_Z", 14.5, D.MAV_PARAM_TYPE_REAL32))
        reply = [m for m in rig.gcs_collect(0.1) if m.get_type() == "PARAM_VALUE"]
        assert reply[0].param_id == "IMP_KP_Z" and reply[0].param_value == pytest.approx(14.5)
        assert rig.vehicle.fw.config.gains.kp_n_m[2] == pytest.approx(14.5)
        # out of range: refused, the old value is reported back
        rig.gcs_send(D.MAVLink_param_set_message(2, 1, b"IMP_KP_Z", -3.0, D.MAV_PARAM_TYPE_REAL32))
        reply = [m for m in rig.gcs_collect(0.1) if m.get_type() == "PARAM_VALUE"]
        assert reply[0].param_value == pytest.approx(14.5)
        rig.gcs_send(D.MAVLink_param_request_read_message(2, 1, b"COM_OF_LOSS_T", -1))
        reply = [m for m in rig.gcs_collect(0.1) if m.get_type() == "PARAM_VALUE"]
        assert reply[0].param_id == "COM_OF_LOSS_T"
    finally:
        rig.close()
    again = Rig(tmp_path)  # same parameter file: the change persisted
    try:
        assert again.vehicle.params.values["IMP_KP_Z"] == pytest.approx(14.5)
        assert again.vehicle.fw.config.gains.kp_n_m[2] == pytest.approx(14.5)
    finally:
        again.close()


def test_message_interval_request_message_and_unsupported_commands(rig):
    rig.start()
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                D.MAVLINK_MSG_ID_ATTITUDE, 20000, 0, 0, 0, 0, 0))
    msgs = rig.gcs_collect(0.4)
    ack = [m for m in msgs if m.get_type() == "COMMAND_ACK"][0]
    assert ack.command == D.MAV_CMD_SET_MESSAGE_INTERVAL and ack.result == D.MAV_RESULT_ACCEPTED
    att = [m for m in rig.gcs_collect(0.3) if m.get_type() == "ATTITUDE"]
    times = np.diff([m.time_boot_ms for m in att])
    assert np.all(times == 20)  # 50 Hz on flight-controller time
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                D.MAVLINK_MSG_ID_ATTITUDE, 0, 0, 0, 0, 0, 0))  # 0: the default
    rig.gcs_collect(0.1)
    att = [m for m in rig.gcs_collect(0.4) if m.get_type() == "ATTITUDE"]
    assert np.all(np.diff([m.time_boot_ms for m in att]) == 100)  # the onboard default, 10 Hz
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                D.MAVLINK_MSG_ID_ATTITUDE, -1, 0, 0, 0, 0, 0))  # -1: off
    rig.gcs_collect(0.05)
    assert "ATTITUDE" not in _types(rig.gcs_collect(0.3))
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_REQUEST_MESSAGE, 0,
                                                D.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0))
    msgs = rig.gcs_collect(0.1)
    assert "AUTOPILOT_VERSION" in _types(msgs)
    assert [m for m in msgs if m.get_type() == "AUTOPILOT_VERSION"][0].capabilities & D.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 5))
    ack = [m for m in rig.gcs_collect(0.1) if m.get_type() == "COMMAND_ACK"][0]
    assert ack.result == D.MAV_RESULT_UNSUPPORTED


def test_link_state_stream_and_correction_latency(rig):
    rig.start()
    states = [m for m in rig.gcs_collect(0.2) if m.get_type() == "SKELETON_LINK_STATE"]
    assert len(states) >= 5 and states[-1].flags & D.SKELETON_STATE_FLAGS_EKF_OK
    t_state = states[-1].time_usec * 1e-6
    corr = Correction(1, t_state, np.array([0.1, 0.0, 0.0]), np.zeros(3), np.zeros(3), seq=7)
    rig.gcs_send(encode_correction(corr, target_system=2))
    after = [m for m in rig.gcs_collect(0.1) if m.get_type() == "SKELETON_LINK_STATE"]
    assert after[-1].correction_seq == 7
    first = next(m for m in after if m.correction_seq == 7)
    assert 0 < first.correction_latency_us < 20_000
    assert first.flags & D.SKELETON_STATE_FLAGS_CORRECTION_ACTIVE
    # a correction for another system is not acted on
    rig.gcs_send(encode_correction(Correction(1, t_state, np.ones(3), np.zeros(3), np.zeros(3), seq=9), target_system=3))
    after = [m for m in rig.gcs_collect(0.1) if m.get_type() == "SKELETON_LINK_STATE"]
    assert after[-1].correction_seq == 7


def test_the_streams_due_on_one_tick_leave_in_one_datagram(rig):
    """The onboard link's streams due together (state, attitude, positions on the 10 Hz ticks) go
    as one datagram: one wake-up of the companion, not one per message. The once-a-second
    heartbeat and SYS_STATUS go together too."""
    rig.start()
    rig.gcs.read()
    streams = {"SKELETON_LINK_STATE", "ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "SYSTEM_TIME"}
    kinds_per_datagram = []
    for _ in range(300):  # 0.6 s: 30 state ticks, 6 attitude ones, a heartbeat
        rig.tick()
        chunks = rig.gcs.transport.recv_chunks()
        parser = D.MAVLink(None)
        decoded = [[m.get_type() for m in parser.parse_buffer(bytearray(data)) or []] for data, _ in chunks]
        with_streams = [kinds for kinds in decoded if streams & set(kinds)]
        assert len(with_streams) <= 1  # every stream due on this tick in one datagram
        kinds_per_datagram += decoded
    assert sum(kinds.count("SKELETON_LINK_STATE") for kinds in kinds_per_datagram) >= 29
    together = [kinds for kinds in kinds_per_datagram if {"SKELETON_LINK_STATE", "ATTITUDE", "LOCAL_POSITION_NED"} <= set(kinds)]
    assert len(together) >= 5
    deadline = time.monotonic() + 2.5  # the heartbeat is once a wall-clock second
    while ["HEARTBEAT", "SYS_STATUS"] not in kinds_per_datagram and time.monotonic() < deadline:
        rig.tick()
        parser = D.MAVLink(None)
        kinds_per_datagram += [[m.get_type() for m in parser.parse_buffer(bytearray(data)) or []]
                               for data, _ in rig.gcs.transport.recv_chunks()]
    assert ["HEARTBEAT", "SYS_STATUS"] in kinds_per_datagram


def test_targets_from_mavlink_and_stale_target_hold(rig):
    rig.start()
    rig.vehicle.fw.arm(rig.t)
    rig.gcs_send(D.MAVLink_set_position_target_local_ned_message(0, 2, 1, D.MAV_FRAME_LOCAL_NED, 0b110000000000,
                                                                  1.0, 2.0, -3.0, 0, 0, 0, 0, 0, 0, 0, 0))
    rig.gcs_collect(0.05)
    target = rig.vehicle.fw.target
    np.testing.assert_allclose(target.p_w_m, [2.0, 1.0, 3.0])  # NED -> ENU
    # 1.1 s of simulated time without new targets: position hold at the current estimate
    for _ in range(600):
        rig.tick()
    hold = rig.vehicle.fw.active_target(rig.t)
    assert hold is not target and np.linalg.norm(hold.p_w_m - [2.0, 1.0, 3.0]) > 0.5


@pytest.mark.parametrize("yaw_ned_deg", [0.0, 90.0, -135.0])
def test_a_position_target_with_a_heading_is_flown_level_at_that_heading(rig, yaw_ned_deg):
    """As a stock PX4's offboard setpoint (what a standard-mode companion sends): the yaw and yaw
    rate of SET_POSITION_TARGET_LOCAL_NED make the attitude target, level; a later attitude target
    is the whole attitude again."""
    rig.start()
    rig.vehicle.fw.arm(rig.t)
    yaw = math.radians(yaw_ned_deg)
    rig.gcs_send(D.MAVLink_set_position_target_local_ned_message(0, 2, 1, D.MAV_FRAME_LOCAL_NED, 0, 1.0, 2.0, -3.0,
                                                                  0, 0, 0, 0, 0, 0, yaw, 0.2))
    rig.gcs_collect(0.02)
    target = rig.vehicle.fw.target
    R = quat_to_rotmat(target.q_wxyz)
    np.testing.assert_allclose(R[:, 2], [0.0, 0.0, 1.0], atol=1e-9)  # level
    off = math.atan2(R[1, 0], R[0, 0]) - (math.pi / 2 - yaw)  # from the ENU yaw of that heading (float32 on the wire)
    assert math.remainder(off, 2.0 * math.pi) == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(target.omega_d_rad_s, [0.0, 0.0, -0.2], atol=1e-9)  # NED yaw rate: about up, negated
    q = quat_from_euler_zyx(0.3, 0.0, 0.0)
    rig.gcs_send(encode_attitude_target(PoseTarget.hold(np.zeros(3), q), 0, 2))
    rig.gcs_collect(0.02)
    np.testing.assert_allclose(rig.vehicle.fw.target.q_wxyz, q, atol=1e-6)


def test_the_feedforward_holds_over_a_lost_message_for_a_while(rig):
    """SKELETON_TARGET_FEEDFORWARD applies to the position target of its time_boot_ms, whichever
    comes first (the companion sends it first: until its position target comes the last one
    stays, so no tick runs without it). A position target whose own was lost keeps the last one
    (a link carrying a neighbour without rotors must not drop its weight for a target period);
    one that comes more than FEEDFORWARD_HOLD_MS after the last feed-forward gets none."""
    rig.start()
    rig.vehicle.fw.arm(rig.t)

    def send_ff(ms, ff):
        rig.gcs_send(encode_target_feedforward(replace(PoseTarget.hold(np.zeros(3), LEVEL), force_ff_w_n=np.array(ff)),
                                               ms, 2))
        rig.gcs_collect(0.05)
        return rig.vehicle.fw.target.force_ff_w_n

    def target(ms, ff=None):
        rig.gcs_send(D.MAVLink_set_position_target_local_ned_message(ms, 2, 1, D.MAV_FRAME_LOCAL_NED, 0b110000000000,
                                                                      0.0, 0.0, -2.0, 0, 0, 0, 0, 0, 0, 0, 0))
        rig.gcs_collect(0.05)
        return rig.vehicle.fw.target.force_ff_w_n if ff is None else send_ff(ms, ff)

    np.testing.assert_allclose(target(1000, ff=(1.0, 2.0, 8.8)), [1.0, 2.0, 8.8])  # after its position target
    np.testing.assert_allclose(target(1020), [1.0, 2.0, 8.8])  # its own was lost: the last one's
    np.testing.assert_allclose(send_ff(1040, (0.0, 0.0, 4.0)), [1.0, 2.0, 8.8])  # before its position target
    np.testing.assert_allclose(target(1040), [0.0, 0.0, 4.0])
    np.testing.assert_allclose(target(1140), [0.0, 0.0, 4.0])
    np.testing.assert_allclose(target(1160), 0.0)  # too long without one


def test_a_target_sent_as_its_three_messages_in_one_datagram_is_one_target(rig):
    """The companion sends a target as SKELETON_TARGET_FEEDFORWARD, SET_POSITION_TARGET_LOCAL_NED
    and SET_ATTITUDE_TARGET in one datagram: the firmware gets one target with all three (one
    set_target, so PSPM sees one set pose), not a position with the old attitude first."""
    rig.start()
    fw = rig.vehicle.fw
    fw.arm(rig.t)
    rig.gcs_send(D.MAVLink_param_request_read_message(2, 1, b"SKL_CORR_HOLD", -1))  # the GCS is heard
    rig.gcs_collect(0.02)
    calls = []
    plain = fw.set_target
    fw.set_target = lambda t, target: calls.append(target) or plain(t, target)
    q = quat_from_euler_zyx(0.3, 0.0, 0.0)
    target = replace(PoseTarget.hold(np.array([1.0, 2.0, 3.0]), q), force_ff_w_n=np.array([0.5, -0.5, 9.0]))
    rig.gcs.send_many([
        encode_target_feedforward(target, 2000, 2),
        D.MAVLink_set_position_target_local_ned_message(2000, 2, 1, D.MAV_FRAME_LOCAL_NED, 0b110000000000,
                                                        *enu_ned(target.p_w_m).tolist(), 0, 0, 0, 0, 0, 0, 0, 0),
        encode_attitude_target(target, 2000, 2),
    ])
    rig.gcs_collect(0.02)
    assert len(calls) == 1, calls
    got = calls[0]
    np.testing.assert_allclose(got.p_w_m, target.p_w_m, atol=1e-6)
    np.testing.assert_allclose(abs(np.dot(got.q_wxyz, q)), 1.0, atol=1e-6)
    np.testing.assert_allclose(got.force_ff_w_n, target.force_ff_w_n, atol=1e-6)
    assert fw.target is got

    def refuse(t, target):
        raise MessageError("refused")

    fw.set_target = refuse  # a target the firmware refuses: counted as a bad message, the vehicle goes on
    before = rig.vehicle.errors["mavlink"]
    rig.gcs.send(encode_attitude_target(target, 2020, 2))
    rig.gcs_collect(0.02)
    assert rig.vehicle.errors["mavlink"] == before + 1 and fw.target is got
    assert np.all(np.isfinite(rig.tick()))


def test_garbage_is_counted_and_dropped(rig):
    rig.start()
    rng = np.random.default_rng(0)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    onboard = rig.vehicle.endpoints[0].port.transport.local_port()
    good = encode_correction(Correction(1, 0.0, np.zeros(3), np.zeros(3), np.zeros(3), seq=1), 2).pack(
        D.MAVLink(None, srcSystem=255, srcComponent=1))
    for k in range(200):
        raw.sendto(rng.bytes(1000), ("127.0.0.1", onboard))
        raw.sendto(good[: 5 + k % 20], ("127.0.0.1", onboard))  # truncated frames
    raw.close()
    rig.gcs_collect(0.3)
    stats = rig.vehicle.endpoints[0].port.stats
    assert stats.dropped_bytes > 100_000 and stats.dropped > 100
    assert rig.vehicle.fw.initialized and np.all(np.isfinite(rig.tick()))


def mavproxy_param_value(m, autopilot: int) -> float:
    """A PARAM_VALUE as MAVProxy 1.8 decodes it (mavproxy_param.handle_px4_param_value): bytewise
    only for MAV_AUTOPILOT_PX4, otherwise the float as it is (then shown as an integer for integer types)."""
    if m.param_type == D.MAV_PARAM_TYPE_REAL32 or autopilot != D.MAV_AUTOPILOT_PX4:
        return m.param_value
    return struct.unpack(">i", struct.pack(">f", m.param_value))[0]


def _param(rig, name):
    rig.gcs_send(D.MAVLink_param_request_read_message(2, 1, name.encode(), -1))
    return next(m for m in rig.gcs_collect(0.1) if m.get_type() == "PARAM_VALUE" and m.param_id == name)


def test_integer_and_float_parameters_as_a_stock_ground_station_reads_and_sets_them(rig):
    rig.start()
    hb = next(m for m in rig.gcs_collect(0.1) + rig.gcs_collect(1.0) if m.get_type() == "HEARTBEAT")
    assert mavproxy_param_value(_param(rig, "MAV_SYS_ID"), hb.autopilot) == 2
    assert mavproxy_param_value(_param(rig, "IMP_KP_Z"), hb.autopilot) == pytest.approx(
        FirmwareConfig().gains.kp_n_m[2], rel=1e-6)
    assert hb.autopilot == D.MAV_AUTOPILOT_PX4
    # MAVProxy's `param set SKL_SM_EN 0`, then 1 (it packs an INT32 bytewise), and once C-cast (a
    # client that did not know the type)
    for value, raw in ((0, 0.0), (1, struct.unpack(">f", struct.pack(">i", 1))[0]), (0, 0.0), (1, 1.0)):
        rig.gcs_send(D.MAVLink_param_set_message(2, 1, b"SKL_SM_EN", raw, D.MAV_PARAM_TYPE_INT32))
        reply = next(m for m in rig.gcs_collect(0.1) if m.get_type() == "PARAM_VALUE")
        assert mavproxy_param_value(reply, hb.autopilot) == value
        assert rig.vehicle.fw.config.allocation.selective_mapping is bool(value)


@pytest.mark.parametrize("name, value, text", [
    ("MAV_SYS_ID", 7.0, "Param MAV_SYS_ID is read-only"),
    ("SKL_SM_EN", 2.0, "Param SKL_SM_EN: 2 out of [0, 1]"),
    ("SKL_SM_EN", 0.5, "Param SKL_SM_EN refused: integer parameter, got 0."),  # 50 characters
    ("IMP_KP_Z", -3.0, "Param IMP_KP_Z: -3 out of [0, 200]"),
])
def test_a_refused_parameter_write_answers_statustext_and_the_unchanged_value(rig, name, value, text):
    rig.start()
    before = rig.vehicle.params.values[name]
    rig.gcs_send(D.MAVLink_param_set_message(2, 1, name.encode(), value, D.MAV_PARAM_TYPE_REAL32))
    msgs = rig.gcs_collect(0.1)
    status = [m for m in msgs if m.get_type() == "STATUSTEXT"]
    assert [m.text for m in status] == [text] and status[0].severity == D.MAV_SEVERITY_ERROR
    reply = next(m for m in msgs if m.get_type() == "PARAM_VALUE")
    assert reply.param_id == name and mavproxy_param_value(reply, D.MAV_AUTOPILOT_PX4) == before
    assert rig.vehicle.params.values[name] == before


def test_origin_by_set_gps_global_origin_is_answered_and_persisted(tmp_path):
    rig = Rig(tmp_path)
    try:
        rig.start()
        rig.gcs_send(D.MAVLink_set_gps_global_origin_message(2, 473977420, 85455940, 488000, 0))
        reply = next(m for m in rig.gcs_collect(0.1) if m.get_type() == "GPS_GLOBAL_ORIGIN")
        assert (reply.latitude, reply.longitude, reply.altitude) == (473977420, 85455940, 488000)
        rig.gcs_send(D.MAVLink_set_gps_global_origin_message(2, 473987654, 85461234, 500250, 0))
        reply = next(m for m in rig.gcs_collect(0.1) if m.get_type() == "GPS_GLOBAL_ORIGIN")
        assert (reply.latitude, reply.longitude, reply.altitude) == (473987654, 85461234, 500250)  # degE7 exact
        rig.vehicle.fw.arm(rig.t)
        rig.gcs_send(D.MAVLink_set_gps_global_origin_message(2, 0, 0, 0, 0))
        msgs = rig.gcs_collect(0.1)
        assert [m.text for m in msgs if m.get_type() == "STATUSTEXT"] == ["Origin not changed: armed"]
        assert next(m for m in msgs if m.get_type() == "GPS_GLOBAL_ORIGIN").latitude == 473987654
    finally:
        rig.close()
    again = Rig(tmp_path)
    try:
        o = again.vehicle.origin
        assert (round(o.lat_deg * 1e7), round(o.lon_deg * 1e7), o.alt_m) == (473987654, 85461234, 500.25)
    finally:
        again.close()


def test_mavftp_parameter_download_is_refused_at_once(rig):
    """MAVProxy tries @PARAM/param.pck over MAVLink FTP first: a NAK (file not found) at once lets it
    fall back to PARAM_REQUEST_LIST without its timeout."""
    rig.start()
    name = b"@PARAM/param.pck?withdefaults=1"
    request = struct.pack("<HBBBBBBI", 41, 0, 4, len(name), 0, 0, 0, 0) + name
    rig.gcs_send(D.MAVLink_file_transfer_protocol_message(0, 2, 1, list(request.ljust(251, b"\0"))))
    reply = next(m for m in rig.gcs_collect(0.05) if m.get_type() == "FILE_TRANSFER_PROTOCOL")
    seq, session, opcode, size, req_opcode = struct.unpack_from("<HBBBB", bytes(reply.payload))
    assert (seq, opcode, size, req_opcode, reply.payload[12]) == (42, 129, 1, 4, 10)  # NAK, FileNotFound


def _flying(rig):
    """Armed at rest, then climbing 1 m (the fake GPS): the land detector sees the take-off."""
    rig.start()
    rig.vehicle.fw.arm(rig.t)
    assert rig.vehicle.fw.landed(rig.t)  # armed on the ground, not yet taken off
    rig.height_m += 1.0
    for k in range(500):
        rig.tick(gps=k % 50 == 0)
    assert not rig.vehicle.fw.landed(rig.t)


def test_a_link_armed_while_moving_is_in_flight_from_the_start(rig):
    """Re-armed while falling (after a forced disarm in the air): a disarm needs the force value."""
    rig.vel_m_s = np.array([0.0, 0.0, -2.0])
    rig.start(0.5)
    assert abs(rig.vehicle.fw.control_estimate(rig.t)[1][2]) > 1.0
    rig.vehicle.fw.arm(rig.t)
    assert not rig.vehicle.fw.landed(rig.t)


def test_a_link_armed_on_the_ground_disarms_without_force(rig):
    """Armed at rest, holding its pose on the ground (the rotors carry its weight): not in flight."""
    rig.start()
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    rig.gcs_collect(0.2)
    assert rig.vehicle.fw.armed and rig.vehicle.fw.landed(rig.t)
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0))
    ack = next(m for m in rig.gcs_collect(0.05) if m.get_type() == "COMMAND_ACK")
    assert ack.result == D.MAV_RESULT_ACCEPTED and not rig.vehicle.fw.armed


def test_disarm_in_flight_needs_the_force_value(rig):
    _flying(rig)
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0))
    msgs = rig.gcs_collect(0.05)
    ack = next(m for m in msgs if m.get_type() == "COMMAND_ACK")
    assert ack.result == D.MAV_RESULT_DENIED and rig.vehicle.fw.armed
    assert any("Disarm refused" in m.text for m in msgs if m.get_type() == "STATUSTEXT")
    assert rig.vehicle.errors["disarm_refused"] == 1
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0))
    ack = next(m for m in rig.gcs_collect(0.05) if m.get_type() == "COMMAND_ACK")
    assert ack.result == D.MAV_RESULT_ACCEPTED and not rig.vehicle.fw.armed


@pytest.mark.parametrize("command, params", [
    ("SET_MESSAGE_INTERVAL", (math.nan, 20000)),
    ("SET_MESSAGE_INTERVAL", (D.MAVLINK_MSG_ID_ATTITUDE, math.inf)),
    ("REQUEST_MESSAGE", (math.nan, 0)),
    ("COMPONENT_ARM_DISARM", (math.nan, 0)),
    ("COMPONENT_ARM_DISARM", (0, math.nan)),
])
def test_a_command_with_a_non_finite_number_is_a_bad_message_and_the_vehicle_goes_on(rig, command, params):
    """A message id, an interval, an arm flag or the force value that is NaN or infinite: the
    command is counted as a bad message and not acted on (no ACK); the vehicle flies on."""
    _flying(rig)
    cmd = getattr(D, f"MAV_CMD_{command}")
    for msg in (D.MAVLink_command_long_message(2, 1, cmd, 0, *params, 0, 0, 0, 0, 0),
                D.MAVLink_command_int_message(2, 1, 0, cmd, 0, 0, *params, 0, 0, 0, 0, 0)):
        before = rig.vehicle.errors["mavlink"]
        rig.gcs_send(msg)
        msgs = rig.gcs_collect(0.05)
        assert not [m for m in msgs if m.get_type() == "COMMAND_ACK"]
        assert rig.vehicle.errors["mavlink"] == before + 1 and rig.vehicle.fw.armed
    assert np.all(np.isfinite(rig.tick()))


def test_an_out_of_bounds_correction_is_rejected_and_counted(rig):
    rig.start()
    t = rig.vehicle.fw.time_s
    rig.gcs_send(encode_correction(Correction(1, t, np.array([0.3, 0, 0]), np.zeros(3), np.zeros(3), seq=3), 2))
    rig.gcs_collect(0.02)
    assert rig.vehicle.fw.correction_seq == 3
    for dp, dv, dth in (([5.0, 0, 0], [0, 0, 0], [0, 0, 0]), ([0, 0, 0], [0, 3.0, 0], [0, 0, 0]),
                        ([0, 0, 0], [0, 0, 0], [0, 0, 1.0])):
        rig.gcs_send(encode_correction(Correction(1, t, np.array(dp), np.array(dv), np.array(dth), seq=4), 2))
    msgs = rig.gcs_collect(0.05)
    assert rig.vehicle.fw.correction_seq == 3 and rig.vehicle.errors["correction_rejected"] == 3
    np.testing.assert_allclose(rig.vehicle.fw.correction.dp_w_m, [0.3, 0, 0])  # the good one stays, never clamped
    assert any(m.text == "Correction rejected: out of bounds" for m in msgs if m.get_type() == "STATUSTEXT")


KEY = bytes(range(32))


def _raw_sender(key=None, link_id=0, sysid=255):
    mav = D.MAVLink(None, srcSystem=sysid, srcComponent=190)
    if key is not None:
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = key, True, link_id
        mav.signing.timestamp = signing_timestamp()
    return mav


def test_signing_required_rejects_unsigned_wrong_key_and_replayed_commands(tmp_path):
    rig = Rig(tmp_path, signing=SigningConfig(mode="required", key_file="k"), key=KEY, gcs_key=KEY)
    try:
        _flying(rig)
        onboard = ("127.0.0.1", rig.vehicle.endpoints[0].port.transport.local_port())
        raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        force_disarm = D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0)
        raw.sendto(force_disarm.pack(_raw_sender()), onboard)  # unsigned
        raw.sendto(force_disarm.pack(_raw_sender(bytes(32))), onboard)  # signed with another key
        spoof = encode_correction(Correction(1, rig.t, np.array([1.0, 0, 0]), np.zeros(3), np.zeros(3), seq=9), 2)
        raw.sendto(spoof.pack(_raw_sender()), onboard)
        rig.gcs_collect(0.05)
        st = rig.vehicle.endpoints[0].port.stats
        assert rig.vehicle.fw.armed and rig.vehicle.fw.correction_seq != 9
        assert (st.rejected_unsigned, st.rejected_signature) == (2, 1)
        # the owner's signed command is accepted; the same frame replayed is not
        arm = D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        frame = arm.pack(_raw_sender(KEY))
        raw.sendto(frame, onboard)
        msgs = rig.gcs_collect(0.05)
        assert [m.result for m in msgs if m.get_type() == "COMMAND_ACK"] == [D.MAV_RESULT_ACCEPTED]
        raw.sendto(frame, onboard)
        msgs = rig.gcs_collect(0.05)
        assert not [m for m in msgs if m.get_type() == "COMMAND_ACK"] and st.rejected_replay == 1
        # what the vehicle sends is signed with the key: the keyed GCS port accepted all of it
        assert rig.gcs.stats.signed > 20 and rig.gcs.stats.unsigned == 0 and rig.gcs.stats.rejected_signing == 0
        raw.close()
    finally:
        rig.close()


def test_setup_signing_only_over_a_trusted_link(tmp_path):
    rig = Rig(tmp_path)  # signing off, no trusted link
    try:
        rig.start()
        new_key = bytes(range(100, 132))
        rig.gcs_send(D.MAVLink_setup_signing_message(2, 1, list(new_key), signing_timestamp()))
        msgs = rig.gcs_collect(0.05)
        assert [m.text for m in msgs if m.get_type() == "STATUSTEXT"] == ["Signing setup refused: untrusted link"]
        assert rig.vehicle.endpoints[0].port.signing_mode == "off" and not (tmp_path / "vehicle.key").exists()
    finally:
        rig.close()
    rig = Rig(tmp_path, signing=SigningConfig(trusted=("onboard",)))
    try:
        rig.start()
        rig.gcs_send(D.MAVLink_setup_signing_message(2, 1, list(new_key), signing_timestamp()))
        rig.gcs_collect(0.05)
        port = rig.vehicle.endpoints[0].port
        assert port.signing_mode == "required" and load_key(tmp_path / "vehicle.key") == new_key
        rig.gcs_send(D.MAVLink_param_request_read_message(2, 1, b"MAV_SYS_ID", -1))  # unsigned now: refused
        assert not [m for m in rig.gcs_collect(0.05) if m.get_type() == "PARAM_VALUE"]
        assert port.stats.rejected_unsigned >= 1
    finally:
        rig.close()


def test_a_gps_glitch_is_reported_in_statustext_sys_status_and_the_link_state(rig):
    rig.start(1.0)
    rig.height_m = 12.0  # a 10 m jump in the fixes: rejected by the EKF's gate
    msgs = []
    for k in range(300):  # 0.6 s, GPS at 10 Hz
        rig.tick(gps=k % 50 == 0, ahrs=k % 10 == 0)
        msgs += rig.gcs.read()
    deadline = time.monotonic() + 2.5  # SYS_STATUS goes out once a second (wall clock)
    while time.monotonic() < deadline and not any(m.get_type() == "SYS_STATUS" for m in msgs[-50:]):
        rig.tick()
        msgs += rig.gcs.read()
    texts = [m.text for m in msgs if m.get_type() == "STATUSTEXT"]
    assert any(t.startswith("GPS glitch") for t in texts), texts
    status = [m for m in msgs if m.get_type() == "SYS_STATUS"][-1]
    assert status.onboard_control_sensors_present & D.MAV_SYS_STATUS_SENSOR_GPS
    assert not status.onboard_control_sensors_health & D.MAV_SYS_STATUS_SENSOR_GPS
    state = [m for m in msgs if m.get_type() == "SKELETON_LINK_STATE"][-1]
    assert state.flags & D.SKELETON_STATE_FLAGS_GPS_FAULT and state.flags & D.SKELETON_STATE_FLAGS_EKF_OK
    assert abs(state.p_ned[2] + 2.0) < 0.3  # the estimate did not follow the jump (NED: up is -z)
    rig.vehicle.close()
    report = json.loads((rig.vehicle.out_dir / "link2_ports.json").read_text())["gps"]
    assert report["faults"] == 1 and report["fault_now"] and report["rejected_fixes"] >= 3


def test_hil_barometer_and_magnetometer_reach_the_ekf_and_invalid_samples_are_dropped(rig):
    rig.start()
    fw = rig.vehicle.fw
    assert not fw.ekf.baro_referenced  # no barometer in the HIL_SENSORs yet: nothing fused
    mag = quat_to_rotmat(LEVEL).T @ enu_ned(MAG_FIELD_NED_GAUSS)  # level: the earth's field in FLU
    for _ in range(5):
        rig.tick(baro_alt_m=ORIGIN.alt_m + rig.height_m, mag_flu_gauss=mag)
    assert fw.ekf.baro_referenced and fw.ekf.accepted["baro"] == 5 and fw.ekf.accepted["mag"] == 5
    assert fw.ekf.x[X_BARO][0] == pytest.approx(rig.height_m - fw.ekf.x[2], abs=0.01)  # offset: height above origin
    thrust = rig.tick(baro_alt_m=math.nan, mag_flu_gauss=np.array([math.nan, 0.0, 0.0]))
    assert np.all(np.isfinite(thrust))  # the tick goes on: the IMU sample was good
    assert rig.vehicle.errors["hil_baro"] == 1 and rig.vehicle.errors["hil_mag"] == 1
    assert rig.vehicle.errors["hil"] == 0
    assert fw.ekf.accepted["baro"] == 5 and fw.ekf.accepted["mag"] == 5
    rig.tick(baro_alt_m=ORIGIN.alt_m + rig.height_m, mag_flu_gauss=mag)
    assert fw.ekf.accepted["baro"] == 6 and fw.ekf.accepted["mag"] == 6

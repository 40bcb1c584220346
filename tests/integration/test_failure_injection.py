"""MAV_CMD_INJECT_FAILURE on a vehicle in-process behind loopback sockets (signed links): denied
while SYS_FAILURE_EN is 0, enabled by PARAM_SET, a GPS failure that the firmware's GPS health
flags, cleared again; unsigned commands never reach it; motor and gyro failures on the
record-tick path; MAVSDK's Failure plugin."""

import json
import math
import socket
import struct
import threading

import numpy as np
import pytest

from companion.mavlink.dialect import load_dialect
from companion.mavlink.port import MavlinkPort
from companion.mavlink.signing import SigningConfig
from companion.messages import PoseTarget
from companion.skeleton.body import LinkInertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware
from link_firmware_sim.vehicle.core import Vehicle
from link_firmware_sim.vehicle.links import VehiclePorts
from link_firmware_sim.vehicle.params import ParamTable, StreamRates
from link_firmware_sim.vehicle.streams.system import sys_status

from ..ports import free_ports
from ..vehicle_rig import ORIGIN, Rig

pytestmark = pytest.mark.usefixtures("compiled_kernels")

D = load_dialect()
KEY = bytes(range(32))


def _inject(unit, ftype, instance=0):
    return D.MAVLink_command_long_message(2, 1, D.MAV_CMD_INJECT_FAILURE, 0, unit, ftype, instance, 0, 0, 0, 0)


def _fly(rig, seconds):
    """``seconds`` of ticks with GPS at 10 Hz and the attitude reference at 50 Hz; what reached the GCS."""
    out = []
    for k in range(int(round(seconds / 0.002))):
        rig.tick(gps=k % 50 == 0, ahrs=k % 10 == 0)
        out += rig.gcs.read()
    return out


def _acks(msgs):
    return [m.result for m in msgs if m.get_type() == "COMMAND_ACK" and m.command == D.MAV_CMD_INJECT_FAILURE]


def _texts(msgs):
    return [m.text for m in msgs if m.get_type() == "STATUSTEXT"]


def test_gps_failure_denied_until_enabled_then_flagged_and_cleared(tmp_path):
    rig = Rig(tmp_path, signing=SigningConfig(mode="required", key_file="k"), key=KEY, gcs_key=KEY)
    v = rig.vehicle
    try:
        rig.start()
        v.set_param("SKL_GPS_TOUT", 0.3)  # (a short outage and recovery keep the test short)
        v.set_param("SKL_GPS_RECOV", 0.2)
        rig.gcs_send(_inject(D.FAILURE_UNIT_SENSOR_GPS, D.FAILURE_TYPE_OFF))
        msgs = _fly(rig, 0.05)
        assert _acks(msgs) == [D.MAV_RESULT_DENIED]
        assert "Failure injection disabled (SYS_FAILURE_EN 0)" in _texts(msgs)
        assert not v.failures.active

        # enabled over the parameter protocol (an integer: bytewise, as PX4 and MAVSDK send it)
        one = struct.unpack("<f", struct.pack("<i", 1))[0]
        rig.gcs_send(D.MAVLink_param_set_message(2, 1, b"SYS_FAILURE_EN", one, D.MAV_PARAM_TYPE_INT32))
        msgs = _fly(rig, 0.02)
        assert [m.param_id for m in msgs if m.get_type() == "PARAM_VALUE"] == ["SYS_FAILURE_EN"]
        assert v.params.values["SYS_FAILURE_EN"] == 1

        # an unsigned command on the signed link is dropped before it is read
        raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            unsigned = _inject(D.FAILURE_UNIT_SENSOR_GPS, D.FAILURE_TYPE_OFF).pack(D.MAVLink(None, 255, 190))
            raw.sendto(unsigned, ("127.0.0.1", v.endpoints[0].port.transport.local_port()))
            msgs = _fly(rig, 0.02)
        finally:
            raw.close()
        assert not _acks(msgs) and not v.failures.active and v.endpoints[0].port.stats.rejected_unsigned == 1

        # hostile or unsimulated params
        rig.gcs_send(_inject(math.nan, D.FAILURE_TYPE_OFF))
        rig.gcs_send(_inject(D.FAILURE_UNIT_SENSOR_GPS, D.FAILURE_TYPE_OFF, 1e9))
        rig.gcs_send(_inject(D.FAILURE_UNIT_SENSOR_BARO, D.FAILURE_TYPE_OFF))
        rig.gcs_send(_inject(D.FAILURE_UNIT_SENSOR_GPS, D.FAILURE_TYPE_OFF, 2))
        msgs = _fly(rig, 0.02)
        assert _acks(msgs) == [D.MAV_RESULT_DENIED, D.MAV_RESULT_DENIED, D.MAV_RESULT_UNSUPPORTED,
                               D.MAV_RESULT_UNSUPPORTED]
        assert not v.failures.active

        # GPS off: no fix reaches the firmware, its GPS health reports the outage
        rig.gcs_send(_inject(D.FAILURE_UNIT_SENSOR_GPS, D.FAILURE_TYPE_OFF))
        rig.tick()  # (the command is read after the tick's sensors)
        fused = v.fw.ekf.accepted["pos"], v.fw.ekf.accepted["vel"]
        msgs = rig.gcs.read() + _fly(rig, 0.5)
        assert _acks(msgs) == [D.MAV_RESULT_ACCEPTED]
        texts = _texts(msgs)
        assert "Failure injection: gps off" in texts and "GPS lost: no fix for 0.3 s" in texts
        assert v.fw.gps_health.fault and v.fw.gps_health.reason == "lost"
        assert (v.fw.ekf.accepted["pos"], v.fw.ekf.accepted["vel"]) == fused  # no GPS fused meanwhile
        assert v.failures.changed["gps"] >= 4
        assert not sys_status(v).onboard_control_sensors_health & D.MAV_SYS_STATUS_SENSOR_GPS  # (1 Hz of wall time)

        # ok: the fixes come back and the fault clears
        rig.gcs_send(_inject(D.FAILURE_UNIT_SENSOR_GPS, D.FAILURE_TYPE_OK))
        msgs = _fly(rig, 0.5)
        assert _acks(msgs) == [D.MAV_RESULT_ACCEPTED]
        assert "Failure injection: gps ok" in _texts(msgs)
        assert any(t.startswith("GPS ok again") for t in _texts(msgs))
        assert not v.fw.gps_health.fault and not v.failures.active
    finally:
        rig.close()
    stats = json.loads((tmp_path / "out" / "link2_ports.json").read_text())
    assert stats["failures"]["injected"] == 2 and stats["failures"]["active"] == []
    assert stats["gps"]["faults"] == 1


def test_a_wrong_gps_is_a_glitch_to_the_firmware(rig):
    """GPS wrong (50 m off): the EKF's gate rejects the fixes, the GPS health reports a glitch."""
    rig.start()
    rig.vehicle.set_param("SYS_FAILURE_EN", 1)
    rig.gcs_send(_inject(D.FAILURE_UNIT_SENSOR_GPS, D.FAILURE_TYPE_WRONG))
    msgs = _fly(rig, 0.3)
    assert _acks(msgs) == [D.MAV_RESULT_ACCEPTED]
    assert "GPS glitch: position fix rejected" in _texts(msgs)
    health = rig.vehicle.fw.gps_health
    assert health.fault and health.reason == "rejected" and health.rejected >= 2

def test_motor_and_gyro_failures_take_the_ticks_off_the_compiled_path(tmp_path):
    """Armed with a target over the same-host link (the record tick's case): a motor off zeroes that
    rotor's command in the answer, a stuck gyro holds its sample; cleared, the answers are whole."""
    rig = Rig(tmp_path, sim_link="unix")
    v = rig.vehicle
    try:
        rig.start(0.1)
        v.set_param("SYS_FAILURE_EN", 1)
        v.set_param("COM_OF_LOSS_T", 60.0)  # (one target stays fresh)
        assert v.fw.arm(rig.t)
        p, _, q = v.fw.control_estimate(rig.t)
        v.fw.set_target(rig.t, PoseTarget.hold(p, q))
        assert np.all(rig.tick() != 0.0)
        rig.gcs_send(_inject(D.FAILURE_UNIT_SYSTEM_MOTOR, D.FAILURE_TYPE_OFF, 3))
        rig.gcs_send(_inject(D.FAILURE_UNIT_SENSOR_GYRO, D.FAILURE_TYPE_STUCK, 1))
        msgs = _fly(rig, 0.02)
        assert _acks(msgs) == [D.MAV_RESULT_ACCEPTED] * 2
        assert {"Failure injection: motor 3 off", "Failure injection: gyro stuck"} <= set(_texts(msgs))
        thrust = rig.tick()
        assert thrust[2] == 0.0 and np.all(np.delete(thrust, 2) != 0.0)
        assert v.failures.changed["motor"] > 0 and v.failures.changed["gyro"] > 0
        rig.gcs_send(_inject(D.FAILURE_UNIT_SYSTEM_MOTOR, D.FAILURE_TYPE_OK, 0))
        rig.gcs_send(_inject(D.FAILURE_UNIT_SENSOR_GYRO, D.FAILURE_TYPE_OK, 0))
        msgs = _fly(rig, 0.02)
        assert _acks(msgs) == [D.MAV_RESULT_ACCEPTED] * 2 and not v.failures.active
        assert np.all(rig.tick() != 0.0)
    finally:
        rig.close()


def test_mavlink_signal_off_cuts_the_link_to_the_companion_both_ways_until_cleared(tmp_path):
    """FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL off from the ground station: the vehicle acknowledges, then
    sends nothing on its onboard link and drops what arrives there (counted), while the
    ground-station link stays up (the ok command arrives and is acknowledged on it), and the
    onboard link is whole again."""
    rig = Rig(tmp_path, companion=True)
    v = rig.vehicle
    try:
        rig.start()
        v.set_param("SYS_FAILURE_EN", 1)
        _fly(rig, 0.1)
        assert [m for m in rig.companion.read() if m.get_type() == "SKELETON_LINK_STATE"]
        rig.gcs_send(_inject(D.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL, D.FAILURE_TYPE_OFF))
        msgs = _fly(rig, 0.05)
        assert _acks(msgs) == [D.MAV_RESULT_ACCEPTED] and "Failure injection: mavlink_signal off" in _texts(msgs)
        rig.companion.read()  # (what it sent before the command)
        rig.companion.send(D.MAVLink_heartbeat_message(D.MAV_TYPE_ONBOARD_CONTROLLER, D.MAV_AUTOPILOT_INVALID,
                                                       0, 0, 0, 3))
        msgs = _fly(rig, 0.3)
        assert rig.companion.read() == []
        assert v.failures.changed["mavlink_signal"] > 10  # the states not sent, the heartbeat dropped
        rig.gcs_send(_inject(D.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL, D.FAILURE_TYPE_OK))
        msgs = _fly(rig, 0.1)
        assert _acks(msgs) == [D.MAV_RESULT_ACCEPTED] and not v.failures.active
        assert [m for m in rig.companion.read() if m.get_type() == "SKELETON_LINK_STATE"]
    finally:
        rig.close()


def test_mavsdk_failure_plugin_injects_and_clears_a_gps_failure(tmp_path):
    """MAVSDK's Failure plugin (which reads SYS_FAILURE_EN when it starts, so the parameter is set
    first, through its Param plugin) against one vehicle polling in its own thread."""
    mavsdk = pytest.importorskip("mavsdk")
    from mavsdk.plugins.failure import Failure, FailureError, FailureResult, FailureType, FailureUnit
    from mavsdk.plugins.param import Param

    (port,) = free_ports(1, udp=True)
    fw = LinkFirmware(1, FirmwareConfig(), LinkInertia(1.8, (0.04, 0.16, 0.16)), RotorGeometry.odar())
    params = ParamTable(2, FirmwareConfig(), ORIGIN, StreamRates(50.0, 0.0), tmp_path / "p.json")
    ports = VehiclePorts(sim="tcpin://127.0.0.1:0", onboard=f"udpout://127.0.0.1:{port}", gcs=None)
    v = Vehicle(1, fw, params, ports, tmp_path / "out")
    sim = MavlinkPort(f"tcpout://127.0.0.1:{v.sim.transport.local_port()}", system_id=250, component_id=1)
    stop = threading.Event()
    thread = threading.Thread(target=lambda: [v.poll(0.02) for _ in iter(stop.is_set, True)], daemon=True)
    thread.start()
    cfg = mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
    mav = mavsdk.Mavsdk(cfg)
    cfg.destroy()
    try:
        mav.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = mav.first_autopilot(3.0)  # (the vehicle's heartbeat: 1 Hz)
        assert system is not None and system.get_system_id() == 2
        Param(system).set_param_int("SYS_FAILURE_EN", 1)
        failure = Failure(system)
        failure.inject(FailureUnit.SENSOR_GPS, FailureType.OFF, 0)
        assert v.failures.active == {(D.FAILURE_UNIT_SENSOR_GPS, 1): D.FAILURE_TYPE_OFF}
        with pytest.raises(FailureError) as refused:
            failure.inject(FailureUnit.SENSOR_BARO, FailureType.OFF, 0)
        assert refused.value.result == FailureResult.UNSUPPORTED
        failure.inject(FailureUnit.SENSOR_GPS, FailureType.OK, 0)
        assert not v.failures.active
    finally:
        stop.set()
        thread.join(2.0)
        del mav
        v.close()
        sim.close()

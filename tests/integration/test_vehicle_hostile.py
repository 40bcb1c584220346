"""Hostile numbers in every message the vehicle takes, one field at a time: NaN, +-inf and 1e30 in
each float field, the smallest and largest value of each integer field. Each is sent to the
in-process vehicle (:class:`tests.vehicle_rig.Rig`); no exception may escape its poll, a refused
message is counted (``Vehicle.errors``) or answered (a COMMAND_ACK other than ACCEPTED, a
STATUSTEXT), it moves nothing (the targets, the correction, the EKF, the parameters, the origin,
the injected failures, arming), and the vehicle still answers its ground station and every
simulator tick with finite thrusts.

Every message type the vehicle acts on is swept (a few seconds: no opt-in subset)."""

import math
import time

import numpy as np
import pytest

from companion.mavlink.codec import encode_correction, encode_target_feedforward
from companion.mavlink.dialect import load_dialect
from companion.mavlink.standard import (encode_attitude_target, encode_odometry, encode_position_target,
                                        encode_vision_position_estimate)
from companion.messages import Correction, PoseTarget
from link_firmware_sim.vehicle.hil import encode_ahrs, encode_hil_gps, encode_hil_sensor

from ..vehicle_rig import LEVEL, ORIGIN

pytestmark = pytest.mark.usefixtures("compiled_kernels")

D = load_dialect()
BAD_FLOATS = (math.nan, math.inf, -math.inf, 1e30)
INT_RANGE = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535), "int16_t": (-32768, 32767),
             "uint32_t": (0, 2**32 - 1), "int32_t": (-2**31, 2**31 - 1), "uint64_t": (0, 2**64 - 1)}
#: the counters of a refused message
REFUSALS = ("mavlink", "correction_rejected", "setup_signing_refused", "hil", "hil_baro", "hil_mag")


def mutations(msg, floats=True, ints=False, skip=()):
    """``(field, value, copy of msg with it)``: each float field (element 0 of an array) set to each
    of :data:`BAD_FLOATS`, each integer field to its type's extremes."""
    cls = type(msg)
    for name, ftype in zip(cls.fieldnames, cls.fieldtypes):
        if name in skip:
            continue
        values = BAD_FLOATS if floats and ftype in ("float", "double") else ()
        values += INT_RANGE[ftype] if ints and ftype in INT_RANGE else ()
        for value in values:
            args = {f: getattr(msg, f"_{f}_raw", getattr(msg, f)) for f in cls.fieldnames}  # (char[]: bytes)
            if isinstance(args[name], list):
                args[name] = [value] + list(args[name][1:])
            else:
                args[name] = value
            yield name, value, cls(**args)


def _state(v) -> dict:
    """What a bad message must not move."""
    fw, t = v.fw, v.targets
    tgt = fw.target
    return {"target": None if tgt is None else [np.asarray(getattr(tgt, k)).copy() for k in vars(tgt)],
            "position": t.position, "attitude": t.attitude, "feedforward": t.feedforward,
            "correction": None if fw.correction is None else (fw.correction.dp_w_m, fw.correction.dv_w_m_s,
                                                              fw.correction.dtheta_w_rad),
            "ekf": fw.ekf.x.copy(), "armed": fw.armed, "params": dict(v.params.values), "origin": v.origin,
            "failures": dict(v.failures.active), "contact": fw.contact}


def _same(a, b, atol=0.0) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k], atol) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y, atol) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and np.allclose(a, b, rtol=0.0, atol=atol, equal_nan=True)
    return a == b


def _exchange(rig, msg) -> tuple[dict, list]:
    """``msg`` from the ground station, handled by the vehicle: the error counters it moved and
    the replies. Exceptions in the vehicle's poll propagate."""
    v = rig.vehicle
    stats = v.endpoints[0].port.stats
    before, seen = dict(v.errors), stats.rx_messages + stats.ignored
    rig.gcs.send(msg)
    deadline = time.monotonic() + 1.0
    while stats.rx_messages + stats.ignored == seen:
        assert time.monotonic() < deadline, f"the vehicle never read {msg.get_type()}"
        v.poll(0.002)
    v.poll(0.0)
    time.sleep(0.001)
    return {k: v.errors[k] - before[k] for k in v.errors if v.errors[k] != before[k]}, rig.gcs.read()


def _refused(counted: dict, replies: list) -> bool:
    acks = [m.result for m in replies if m.get_type() == "COMMAND_ACK"]
    texts = [m.text for m in replies if m.get_type() == "STATUSTEXT"]
    return bool(set(counted) & set(REFUSALS)) or any(r != D.MAV_RESULT_ACCEPTED for r in acks) or bool(texts)


def _alive(rig) -> None:
    """Ticks answered with finite thrusts, and a PARAM_REQUEST_READ answered."""
    for _ in range(5):
        assert np.all(np.isfinite(rig.tick()))
    rig.gcs.send(D.MAVLink_param_request_read_message(2, 1, b"MAV_SYS_ID", -1))
    assert any(m.get_type() == "PARAM_VALUE" for m in rig.gcs_collect(0.02))


@pytest.fixture
def armed(rig):
    """The rig's vehicle running, armed at rest, its GCS port connected, injection enabled."""
    rig.start()
    rig.vehicle.fw.arm(rig.t)
    rig.vehicle.set_param("SYS_FAILURE_EN", 1)
    rig.gcs_collect(0.02)
    return rig


def _bases(rig) -> dict:
    """A valid message of each GCS-side type (the vehicle's own pose for targets and external
    vision) and the fields it does not read (a bad number there changes nothing)."""
    fw = rig.vehicle.fw
    st = fw.state_report()
    target = PoseTarget.hold(st.p_w_m, st.q_wxyz)
    ms = rig.vehicle.time_boot_ms
    return {
        "SET_POSITION_TARGET_LOCAL_NED": (encode_position_target(target, ms, 2), {"yaw", "yaw_rate"}),
        "SET_ATTITUDE_TARGET": (encode_attitude_target(target, ms, 2), {"thrust"}),
        "SKELETON_TARGET_FEEDFORWARD": (encode_target_feedforward(target, ms, 2), set()),
        "SKELETON_CORRECTION": (encode_correction(Correction(1, st.time_s, np.array([0.1, 0, 0]), np.zeros(3),
                                                             np.zeros(3), seq=3), 2), set()),
        "ODOMETRY": (encode_odometry(st, int(st.time_s * 1e6), estimator_type=D.MAV_ESTIMATOR_TYPE_VISION),
                     {"rollspeed", "pitchspeed", "yawspeed", "pose_covariance", "velocity_covariance"}),
        "VISION_POSITION_ESTIMATE": (encode_vision_position_estimate(st, int(st.time_s * 1e6)), {"covariance"}),
        "PARAM_SET": (D.MAVLink_param_set_message(2, 1, b"IMP_KP_Z", 14.5, D.MAV_PARAM_TYPE_REAL32), set()),
        "PARAM_SET int": (D.MAVLink_param_set_message(2, 1, b"SKL_SM_EN", 0.0, D.MAV_PARAM_TYPE_INT32), set()),
    }


#: commands with params that are read (a bad number is refused) and, for 1e30, legal (an interval)
COMMANDS = {
    "COMPONENT_ARM_DISARM": ((1, 0, 0, 0, 0, 0, 0), {"param1"}),
    "SET_MESSAGE_INTERVAL": ((D.MAVLINK_MSG_ID_ATTITUDE, 100000, 0, 0, 0, 0, 0), {"param1", "param2"}),
    "REQUEST_MESSAGE": ((D.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0), {"param1"}),
    "INJECT_FAILURE": ((4, 0, 0, 0, 0, 0, 0), {"param1", "param2", "param3"}),
    "SKELETON_SET_CONTACT": ((5, 1, 0, 0, 0, 0, 0), {"param1", "param2", "param3", "param4", "param5", "param6",
                                                      "param7"}),
    "REQUEST_AUTOPILOT_CAPABILITIES": ((1, 0, 0, 0, 0, 0, 0), set()),
}
LEGAL_1E30 = {("SET_MESSAGE_INTERVAL", "param2")}  # a long interval


def _sweep(rig, name, base, ignored, ints=False):
    """Every mutation of ``base``: refused (unless in a field of ``ignored``) and moving nothing."""
    _exchange(rig, base)
    control = _state(rig.vehicle)
    failures = []
    for field, value, msg in mutations(base, ints=ints):
        counted, replies = _exchange(rig, msg)
        is_float = isinstance(value, float)
        if is_float and field not in ignored and not _refused(counted, replies):
            failures.append(f"{name}.{field} = {value!r} was not refused")
        if field in ignored and counted:
            failures.append(f"{name}.{field} = {value!r} (not read) was refused: {counted}")
        if not _same(_state(rig.vehicle), control, atol=1e-6):
            failures.append(f"{name}.{field} = {value!r} moved the vehicle's state")
            _exchange(rig, base)
            control = _state(rig.vehicle)
    return failures


def test_every_float_field_of_the_gcs_messages(armed):
    """Targets, feed-forward, corrections, external vision, PARAM_SET: each bad number is refused
    and counted (or, for PARAM_SET, answered with a STATUSTEXT and the unchanged value)."""
    failures = []
    for name, (base, ignored) in _bases(armed).items():
        failures += _sweep(armed, name, base, ignored)
    assert not failures, "\n".join(failures)
    errors = armed.vehicle.errors
    assert errors["mavlink"] > 100 and errors["correction_rejected"] > 10
    _alive(armed)


def _command_sweep(rig, commands, kinds, ints=False):
    failures = []
    for command, (params, read) in commands.items():
        cmd = getattr(D, f"MAV_CMD_{command}")
        for kind in kinds:
            if kind == "COMMAND_LONG":
                base = D.MAVLink_command_long_message(2, 1, cmd, 0, *params)
            else:
                base = D.MAVLink_command_int_message(2, 1, 0, cmd, 0, 0, *params[:4], int(params[4]),
                                                     int(params[5]), params[6])
            unread = set(base.fieldnames) - read
            for field, value, msg in mutations(base, ints=ints, skip=("command", "target_system")):
                before = _state(rig.vehicle)
                counted, replies = _exchange(rig, msg)
                acks = [m.result for m in replies if m.get_type() == "COMMAND_ACK"]
                where = f"{kind} {command}.{field} = {value!r}"
                if field in read and not (value == 1e30 and (command, field) in LEGAL_1E30):
                    if not _refused(counted, replies):
                        failures.append(f"{where} was not refused: {acks}")
                    elif not _same(_state(rig.vehicle), before, atol=1e-6):
                        failures.append(f"{where} moved the vehicle's state")
                elif field in unread and isinstance(value, float) and counted:
                    failures.append(f"{where} (not read) was refused: {counted}")
                if not rig.vehicle.fw.armed:  # (a valid disarm, at rest)
                    rig.vehicle.fw.arm(rig.t)
                rig.vehicle.failures.active.clear()
    return failures


def test_every_command_and_every_integer_field(armed):
    """Every command as COMMAND_LONG and COMMAND_INT (the hybrid controller's, for the contact): in
    the numbers it reads, NaN or infinite is a bad message (counted, no ACK) and out of range is
    DENIED or UNSUPPORTED; the params it does not read are not looked at. Then the integer
    extremes of every GCS-side message (their values may be legal: nothing may escape, and an
    armed vehicle's origin, parameters and targets stay)."""
    armed.vehicle.set_param("SKL_CTRL", 2)
    failures = _command_sweep(armed, COMMANDS, ("COMMAND_LONG", "COMMAND_INT"), ints=True)
    others = {"SET_GPS_GLOBAL_ORIGIN": D.MAVLink_set_gps_global_origin_message(2, 473977420, 85455940, 488000, 0),
              "SETUP_SIGNING": D.MAVLink_setup_signing_message(2, 1, list(range(32)), 1000),
              "FILE_TRANSFER_PROTOCOL": D.MAVLink_file_transfer_protocol_message(0, 2, 1, [0] * 251),
              "PARAM_REQUEST_READ": D.MAVLink_param_request_read_message(2, 1, b"MAV_SYS_ID", -1),
              "PARAM_REQUEST_LIST": D.MAVLink_param_request_list_message(2, 1)}
    for name, (base, _) in list(_bases(armed).items()):
        for field, value, msg in mutations(base, floats=False, ints=True):
            _exchange(armed, msg)
    for name, base in others.items():
        for field, value, msg in mutations(base, floats=False, ints=True):
            before = _state(armed.vehicle)
            _exchange(armed, msg)
            if not _same(_state(armed.vehicle), before, atol=1e-6):  # armed: no origin change
                failures.append(f"{name}.{field} = {value!r} moved the vehicle's state")
    assert not failures, "\n".join(failures)
    _alive(armed)


def test_setup_signing_with_a_timestamp_beyond_48_bits_is_refused(tmp_path):
    """On a trusted link: the key is not taken (the vehicle would fail to sign its next frame)."""
    from companion.mavlink.signing import SigningConfig

    from ..vehicle_rig import Rig

    rig = Rig(tmp_path, signing=SigningConfig(trusted=("onboard",)))
    try:
        rig.start()
        rig.gcs_collect(0.02)
        for ts in (2**48, 2**64 - 1):
            counted, _ = _exchange(rig, D.MAVLink_setup_signing_message(2, 1, list(range(100, 132)), ts))
            assert counted == {"mavlink": 1}
        assert rig.vehicle.endpoints[0].port.signing_mode == "off"
        _alive(rig)
    finally:
        rig.close()


def _sim_exchange(rig, msg) -> tuple[dict, list]:
    """``msg`` from the simulator: the error counters it moved and the answers it got (a
    HIL_SENSOR exactly one)."""
    v = rig.vehicle
    before = dict(v.errors)
    rig.sim.send(msg)
    answers = []
    deadline = time.monotonic() + (1.0 if msg.get_type() == "HIL_SENSOR" else 0.01)
    while time.monotonic() < deadline and not answers:
        v.poll(0.002)
        answers += rig.sim.read()
    return {k: v.errors[k] - before[k] for k in v.errors if v.errors[k] != before[k]}, answers


def test_every_field_of_the_simulator_messages(armed):
    """HIL_SENSOR (IMU, barometer, magnetometer, time), HIL_GPS, SKELETON_AHRS_REFERENCE: a bad
    IMU sample or time is counted and answered with zero thrust at its own time (the lockstep goes
    on) and moves neither the clock nor the EKF; a bad barometer or magnetometer sample is dropped
    and counted, the tick goes on; a GPS fix with absurd integers is gated by the EKF."""
    rig, v = armed, armed.vehicle
    fw = v.fw
    mag = np.array([0.2, 0.0, -0.4])
    failures = []

    def sensor():
        rig.t = round(rig.t + 0.002, 6)
        return encode_hil_sensor(rig.t, np.array([0.0, 0.0, 9.80665]), np.zeros(3), baro_alt_m=ORIGIN.alt_m + 2.0,
                                 mag_flu_gauss=mag)

    for field, value, msg in mutations(sensor(), ints=True, skip=("time_usec",)):
        msg.time_usec = sensor().time_usec
        x, clock, fused = fw.ekf.x.copy(), v.fc_time_us, dict(fw.ekf.accepted)
        counted, answers = _sim_exchange(rig, msg)
        where = f"HIL_SENSOR.{field} = {value!r}"
        if len(answers) != 1 or answers[0].time_usec != msg.time_usec:
            failures.append(f"{where}: answers {answers}")
            continue
        imu = field[1:] in ("acc", "gyro")
        if imu and (counted != {"hil": 1} or v.fc_time_us != clock or not np.array_equal(fw.ekf.x, x)
                    or any(answers[0].controls)):
            failures.append(f"{where}: counted {counted}, the clock or the EKF moved, or thrust {answers[0].controls[:8]}")
        sensor_kind = {"xmag": "mag", "ymag": "mag", "zmag": "mag", "abs_pressure": "baro"}.get(field)
        if sensor_kind and (counted != {f"hil_{sensor_kind}": 1} or fw.ekf.accepted[sensor_kind] != fused[sensor_kind]):
            failures.append(f"{where}: counted {counted}, fused {fw.ekf.accepted[sensor_kind] - fused[sensor_kind]}")
        if not imu and not sensor_kind and field != "fields_updated" and counted:
            failures.append(f"{where} (not read) was refused: {counted}")
        assert np.all(np.isfinite(answers[0].controls))
    for bad_time in (2**64 - 1, 2**50 + 1):
        msg = sensor()
        msg.time_usec = bad_time
        clock = v.fc_time_us
        counted, answers = _sim_exchange(rig, msg)
        assert counted == {"hil": 1} and [a.time_usec for a in answers] == [bad_time] and v.fc_time_us == clock
    p = fw.ekf.x[:3].copy()
    for field, value, msg in mutations(encode_hil_gps(rig.t, np.array([0.0, 0.0, rig.height_m]), np.zeros(3), ORIGIN),
                                       ints=True):
        counted, _ = _sim_exchange(rig, msg)
        if field in ("lat", "lon", "alt", "vn", "ve", "vd") and np.linalg.norm(fw.ekf.x[:3] - p) > 0.1:
            failures.append(f"HIL_GPS.{field} = {value!r} moved the EKF {np.linalg.norm(fw.ekf.x[:3] - p):.3g} m")
        if (field, value) in (("fix_type", 0), ("time_usec", 2**64 - 1)) and counted != {"hil": 1}:
            failures.append(f"HIL_GPS.{field} = {value} not refused: {counted}")
        rig.tick()
    for field, value, msg in mutations(encode_ahrs(rig.t, LEVEL), ints=True):
        counted, _ = _sim_exchange(rig, msg)
        if (field == "q" or value == 2**64 - 1) and counted != {"hil": 1}:
            failures.append(f"SKELETON_AHRS_REFERENCE.{field} = {value!r} not refused: {counted}")
    assert not failures, "\n".join(failures)
    _alive(rig)

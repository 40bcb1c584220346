"""The hybrid controller over MAVLink: the observer's SKELETON_EXTERNAL_WRENCH stream and the
contact command MAV_CMD_SKELETON_SET_CONTACT, codec and vehicle."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.mavlink.codec import (
    CONTACT_RELEASE,
    MessageError,
    decode_contact_command,
    decode_external_wrench,
    encode_contact_command,
    encode_external_wrench,
)
from companion.mavlink.dialect import load_dialect
from companion.messages import ContactTarget, ExternalWrench
from companion.skeleton.body import LinkInertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware

from ..mavlink_wire import over_mavlink
from ..vehicle_rig import Rig

#: the kernels compiled (or loaded) before a vehicle here runs against a deadline
pytestmark = pytest.mark.usefixtures("compiled_kernels")

D = load_dialect()
finite = st.floats(-50.0, 50.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)


# -- codec -----------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(f=vec3, tau=vec3, t=st.floats(0.0, 1e5), contact=st.one_of(st.none(), st.tuples(finite, st.floats(0.0, 100.0))))
def test_external_wrench_round_trip(f, tau, t, contact):
    lam, lam_d = contact if contact is not None else (math.nan, math.nan)
    sent = ExternalWrench(3, t, f, tau, lam, lam_d)
    back = decode_external_wrench(over_mavlink(encode_external_wrench(sent)), 3)
    assert back.link == 3 and back.time_s == pytest.approx(t, abs=1e-6)
    np.testing.assert_allclose(back.force_w_n, f, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(back.torque_b_nm, tau, rtol=1e-6, atol=1e-5)
    if contact is None:
        assert math.isnan(back.contact_force_n) and math.isnan(back.contact_force_cmd_n)
    else:
        assert back.contact_force_n == pytest.approx(lam, rel=1e-6, abs=1e-5)
        assert back.contact_force_cmd_n == pytest.approx(lam_d, rel=1e-6, abs=1e-5)


def test_external_wrench_frames_are_ned_and_frd():
    msg = encode_external_wrench(ExternalWrench(0, 1.0, np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 0.3])))
    np.testing.assert_allclose(msg.force_ned, [2.0, 1.0, -3.0])  # ENU -> NED
    np.testing.assert_allclose(msg.torque_frd, [0.1, -0.2, -0.3])  # FLU -> FRD


@pytest.mark.parametrize("field, value, match", [
    ("force_ned", [math.nan, 0.0, 0.0], "force_ned"),
    ("torque_frd", [0.0, math.inf, 0.0], "torque_frd"),
    ("force_ned", [2e4, 0.0, 0.0], "exceeds"),
    ("contact_force", 3.0, "both finite or both NaN"),  # a force without a setpoint
    ("contact_force_setpoint", -1.0, "outside"),
])
def test_external_wrench_decoder_rejects(field, value, match):
    msg = over_mavlink(encode_external_wrench(ExternalWrench(0, 1.0, np.zeros(3), np.zeros(3))))
    setattr(msg, field, value)
    if field == "contact_force_setpoint":
        msg.contact_force = 0.0
    with pytest.raises(MessageError, match=match):
        decode_external_wrench(msg, 0)


unit = st.tuples(finite, finite, finite).filter(lambda v: np.linalg.norm(v) > 1e-2).map(lambda v: np.array(v) / np.linalg.norm(v))


@settings(max_examples=40, deadline=None)
@given(n=unit, r=st.tuples(*[st.floats(-2.0, 2.0)] * 3).map(np.array), force=st.floats(0.0, 200.0))
def test_contact_command_round_trip(n, r, force):
    back = decode_contact_command(over_mavlink(encode_contact_command(ContactTarget(n, r, force), 2)))
    np.testing.assert_allclose(back.normal_w, n, atol=1e-6)
    assert np.linalg.norm(back.normal_w) == pytest.approx(1.0, abs=1e-12)  # renormalised after float32
    np.testing.assert_allclose(back.contact_b_m, r, atol=1e-6)
    assert back.force_n == pytest.approx(force, rel=1e-6)


def test_contact_command_release_and_wire_frames():
    msg = encode_contact_command(None, 2)
    assert msg.command == D.MAV_CMD_SKELETON_SET_CONTACT and msg.param1 == CONTACT_RELEASE
    assert decode_contact_command(over_mavlink(msg)) is None
    msg = encode_contact_command(ContactTarget(np.array([0.0, 0.0, -1.0]), np.array([0.6, 0.1, 0.0]), 5.0), 2)
    assert [msg.param2, msg.param3, msg.param4] == [0.0, 0.0, 1.0]  # world down = NED +D
    assert [msg.param5, msg.param6, msg.param7] == pytest.approx([0.6, -0.1, 0.0])  # FLU -> FRD


@pytest.mark.parametrize("params, match", [
    ({"param1": -2.0}, "force"),
    ({"param1": math.nan}, "force"),
    ({"param1": 5e3}, "force"),
    ({"param2": 0.5}, "normal"),  # |n| != 1
    ({"param3": math.inf}, "normal"),
    ({"param5": math.nan}, "contact point"),
    ({"param5": 50.0}, "contact point"),
])
def test_contact_command_decoder_rejects(params, match):
    msg = over_mavlink(encode_contact_command(ContactTarget(np.array([1.0, 0.0, 0.0]), np.array([0.6, 0.0, 0.0]), 5.0), 2))
    for k, v in params.items():
        setattr(msg, k, v)
    with pytest.raises(MessageError, match=match):
        decode_contact_command(msg)


# -- firmware ----------------------------------------------------------------------------------------


def test_firmware_bounds_the_commanded_force_and_reports_the_estimate():
    fw = LinkFirmware(0, FirmwareConfig(controller="hybrid", contact_max_force_n=20.0),
                      LinkInertia(2.6, (0.05, 0.3, 0.3)), RotorGeometry.odar())
    contact = ContactTarget(np.array([1.0, 0.0, 0.0]), np.array([0.6, 0.0, 0.0]), 15.0)
    fw.set_contact(0.0, contact)
    with pytest.raises(ValueError, match="bound 20"):
        fw.set_contact(0.0, ContactTarget(contact.normal_w, contact.contact_b_m, 25.0))
    assert fw.contact is contact  # a refused command changes nothing
    report = fw.external_wrench_report()
    assert report.contact_force_cmd_n == 15.0 and np.all(report.force_w_n == 0.0)
    assert LinkFirmware(0, FirmwareConfig(), LinkInertia(2.6, (0.05, 0.3, 0.3)),
                        RotorGeometry.odar()).external_wrench_report() is None


# -- the vehicle ---------------------------------------------------------------------------------------


def _hybrid(rig: Rig, wrench_hz: float = 0.0) -> None:
    for name, value in (("SKL_CTRL", 2), ("SKL_WRENCH_HZ", wrench_hz)):
        rig.vehicle.set_param(name, value)  # what a PARAM_SET does


def test_vehicle_streams_the_external_wrench_only_with_the_hybrid_controller(rig):
    rig.start(0.1)
    rig.vehicle.set_param("SKL_WRENCH_HZ", 50.0)
    assert not [m for m in rig.gcs_collect(0.1) if m.get_type() == "SKELETON_EXTERNAL_WRENCH"]  # impedance: none
    _hybrid(rig, wrench_hz=50.0)
    rig.vehicle.fw.arm(rig.t)
    msgs = [m for m in rig.gcs_collect(0.2) if m.get_type() == "SKELETON_EXTERNAL_WRENCH"]
    assert 7 <= len(msgs) <= 12  # 50 Hz over 0.2 s
    w = decode_external_wrench(msgs[-1], 1)
    assert np.all(np.isfinite(w.force_w_n)) and math.isnan(w.contact_force_cmd_n)  # no contact commanded
    assert msgs[-1].time_usec > msgs[0].time_usec


def _command(rig: Rig, msg) -> tuple[int, list[str]]:
    rig.gcs_send(msg)
    out = rig.gcs_collect(0.02)
    acks = [m for m in out if m.get_type() == "COMMAND_ACK" and m.command == D.MAV_CMD_SKELETON_SET_CONTACT]
    assert len(acks) == 1
    return acks[0].result, [m.text for m in out if m.get_type() == "STATUSTEXT"]


def test_contact_command_refused_unless_hybrid_then_applied_and_released(rig):
    rig.start(0.1)
    contact = ContactTarget(np.array([0.0, 1.0, 0.0]), np.array([0.6, 0.0, 0.0]), 8.0)
    result, texts = _command(rig, encode_contact_command(contact, 2))
    assert result == D.MAV_RESULT_DENIED and any("controller impedance" in t for t in texts)
    _hybrid(rig)
    result, _ = _command(rig, encode_contact_command(contact, 2))
    assert result == D.MAV_RESULT_ACCEPTED
    fw = rig.vehicle.fw
    np.testing.assert_allclose(fw.contact.normal_w, contact.normal_w, atol=1e-7)
    assert fw.contact.force_n == 8.0
    result, texts = _command(rig, encode_contact_command(ContactTarget(contact.normal_w, contact.contact_b_m, 80.0), 2))
    assert result == D.MAV_RESULT_DENIED and any("bound 30" in t for t in texts) and fw.contact.force_n == 8.0
    bad = encode_contact_command(contact, 2)
    bad.param2 = 0.3  # not a unit normal
    result, texts = _command(rig, bad)
    assert result == D.MAV_RESULT_DENIED and any("normal" in t for t in texts)
    as_int = D.MAVLink_command_int_message(2, 1, 0, D.MAV_CMD_SKELETON_SET_CONTACT, 0, 0, 8.0, 0, 1, 0, 0, 0, 0)
    result, texts = _command(rig, as_int)
    assert result == D.MAV_RESULT_DENIED and any("COMMAND_LONG" in t for t in texts)
    result, _ = _command(rig, encode_contact_command(None, 2))
    assert result == D.MAV_RESULT_ACCEPTED and fw.contact is None

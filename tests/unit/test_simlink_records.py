"""The same-host simulator link's records (link_firmware_sim.vehicle.simlink): they carry exactly
what the MAVLink HIL frames carry, and a malformed packet is refused whole."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.vehicle.hil import (
    decode_actuators,
    decode_ahrs,
    decode_hil_baro_mag,
    decode_hil_gps,
    decode_hil_sensor,
    encode_hil_sensor,
)
from link_firmware_sim.vehicle.simlink import SIM_KINDS, FrameError, decode_packet, encode_packet

from ..hil_messages import ACTUATORS, SENSORS, D, random_messages
from ..mavlink_wire import over_mavlink


@pytest.mark.parametrize("seed", range(5))
def test_records_carry_what_mavlink_frames_carry(seed):
    """Every field of every kind, through the link and through a MAVLink frame: equal (both float32)."""
    msgs = random_messages(np.random.default_rng(seed))
    assert [m.get_type() for m in msgs] == sorted(SIM_KINDS, key=[m.get_type() for m in msgs].index)
    got = decode_packet(encode_packet(msgs))
    assert [r.get_type() for r in got] == [m.get_type() for m in msgs]
    for rec, msg in zip(got, msgs):
        ref = over_mavlink(msg)
        for name in ref.fieldnames:
            assert getattr(rec, name) == pytest.approx(getattr(ref, name), rel=0, abs=0), (msg.get_type(), name)
    # and the decoders read them alike
    origin = GeoOrigin()
    ref = [over_mavlink(m) for m in msgs]
    np.testing.assert_array_equal(decode_hil_gps(got[0], origin)[1], decode_hil_gps(ref[0], origin)[1])
    np.testing.assert_array_equal(decode_ahrs(got[1])[1], decode_ahrs(ref[1])[1])
    for a, b in zip(decode_hil_sensor(got[2])[1:], decode_hil_sensor(ref[2])[1:]):
        np.testing.assert_array_equal(a, b)
    a, b = decode_hil_baro_mag(got[2]), decode_hil_baro_mag(ref[2])
    assert a.baro_alt_m == b.baro_alt_m and a.rejected == b.rejected == ()
    np.testing.assert_array_equal(a.mag_flu_gauss, b.mag_flu_gauss)
    np.testing.assert_array_equal(decode_actuators(got[3], 8.0)[1], decode_actuators(ref[3], 8.0)[1])


def test_malformed_packets_are_refused_whole():
    good = encode_packet([encode_hil_sensor(1.0, np.zeros(3), np.zeros(3))])
    with pytest.raises(FrameError, match="empty"):
        decode_packet(b"")
    with pytest.raises(FrameError, match="cut short"):
        decode_packet(good[:-1])
    with pytest.raises(FrameError, match="cut short"):
        decode_packet(good + good[:5])
    with pytest.raises(FrameError, match="unknown record kind"):
        decode_packet(bytes([len(SIM_KINDS)]) + good[1:])
    with pytest.raises(FrameError, match="not accepted"):
        decode_packet(good, ACTUATORS)  # a sensor sample sent to the simulator's side
    with pytest.raises(FrameError, match="not a simulator-link message"):
        encode_packet([D.MAVLink_heartbeat_message(2, 0, 0, 0, 4, 3)])
    assert len(decode_packet(good + good, SENSORS)) == 2


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_decode_or_raise_frame_error(data):
    try:
        out = decode_packet(data, SENSORS)
    except FrameError:
        return
    assert out and all(r.get_type() in SENSORS for r in out)

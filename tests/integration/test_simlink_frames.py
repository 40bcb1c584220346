"""PX4's TCP simulator link in compiled code: a tick's MAVLink 2 frames give the same-host link's
records of the same messages and an answer record gives pymavlink's frame
(link_firmware_sim.kernels.mavlink_frames); every other read is left to pymavlink's parser; the
simulator's TCP port (SimulatorPort) reads answers as pymavlink's parser does."""

from __future__ import annotations

import socket
import time
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import quat_normalize
from companion.kernels.jit import ENABLED as COMPILED
from companion.mavlink.port import MavlinkPort
from companion.mavlink.transport import wait_readable
from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.kernels import mavlink_frames as frames
from link_firmware_sim.vehicle import simlink
from link_firmware_sim.vehicle.hil import encode_actuators, encode_ahrs, encode_hil_gps, encode_hil_sensor
from link_firmware_sim.vehicle.simlink import RECV_BYTES, SimulatorPort, encode_packet

from ..hil_messages import ACTUATORS, D
from ..vehicle_rig import LEVEL

#: the kernels compiled (or loaded) before a vehicle here runs against a deadline
pytestmark = pytest.mark.usefixtures("compiled_kernels")


# -- PX4's TCP link in the compiled lockstep loop: the ticks' MAVLink 2 frames ------------------

_SIM_SYS, _SIM_COMP = 255, 190


def _framing(seq_in: int = 255, sys_id: int = 2, comp: int = 1, seq_out: int = 0) -> np.ndarray:
    f = np.zeros(frames.FRAMING_SIZE, dtype=np.int64)
    f[:7] = (frames.FRAMES_TO_VEHICLE, _SIM_SYS, _SIM_COMP, seq_in, sys_id, comp, seq_out)
    return f


def _tick_frames(msgs, seq0: int = 0, sign_key: bytes | None = None) -> bytes:
    mav = D.MAVLink(None, srcSystem=_SIM_SYS, srcComponent=_SIM_COMP)
    mav.seq = seq0
    if sign_key is not None:
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.timestamp = sign_key, True, 1
    out = b""
    for m in msgs:
        out += m.pack(mav)
        mav.seq = (mav.seq + 1) % 256
    return out


def _frames_to_records(data: bytes, framing: np.ndarray) -> bytes | None:
    buf = np.zeros(RECV_BYTES, dtype=np.uint8)
    buf[:len(data)] = np.frombuffer(data, dtype=np.uint8)
    rec = np.zeros(RECV_BYTES, dtype=np.uint8)
    m = frames.frames_to_records(buf, len(data), rec, framing)
    return None if m < 0 else rec[:m].tobytes()


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**63), st.lists(st.floats(-3e4, 3e4, width=32), min_size=6, max_size=6),
       st.sampled_from([0.0, 1.0, -0.5]), st.booleans(), st.integers(0, 255))
def test_the_loops_frames_give_the_records_of_the_same_messages(t_us, imu, w, with_ahrs, seq0):
    """frames_to_records (the lockstep loop's reader over TCP) against the same-host link's encoder:
    a tick's frames packed by pymavlink (MAVLink 2 cuts the payloads' trailing zeros: here the
    unused fields) give the records of the same messages, byte for byte, and the newest frame's
    sequence number (numbered on across 255 -> 0)."""
    t = t_us * 1e-6
    sensor = encode_hil_sensor(t, np.array(imu[:3]), np.array(imu[3:]))
    msgs = [encode_ahrs(t, quat_normalize(np.array([1.0, w, 0.0, 0.0]))), sensor] if with_ahrs else [sensor]
    framing = _framing(seq_in=(seq0 - 1) % 256)
    assert _frames_to_records(_tick_frames(msgs, seq0), framing) == encode_packet(msgs)
    assert framing[frames.FRAMING["seq_read"]] == (seq0 + len(msgs) - 1) % 256


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**64 - 1), st.lists(st.sampled_from([0.0, 1.0, -1.0, 0.25, 1e-9]), min_size=8, max_size=8),
       st.sampled_from([0, D.MAV_MODE_FLAG_SAFETY_ARMED]), st.integers(0, 255), st.integers(1, 255))
def test_the_loops_answer_frame_is_pymavlinks(t_us, controls, mode, seq, sys_id):
    """record_to_frame (the lockstep loop's writer over TCP) against pymavlink: the same bytes for
    an answer record (trailing zeros cut, down to one byte when all are zero), and the link's
    sequence number moved on (255 -> 0)."""
    msg = D.MAVLink_hil_actuator_controls_message(t_us, controls + [0.0] * 8, mode, 0)
    record = np.frombuffer(encode_packet([msg]), dtype=np.uint8)
    framing = _framing(sys_id=sys_id, seq_out=seq)
    frame = np.zeros(frames.FRAME_BYTES, dtype=np.uint8)
    n = frames.record_to_frame(record, frame, framing)
    mav = D.MAVLink(None, srcSystem=sys_id, srcComponent=1)
    mav.seq = seq
    assert frame[:n].tobytes() == msg.pack(mav)
    assert framing[frames.FRAMING["seq_out"]] == (seq + 1) % 256


def _tick(t: float = 1.25) -> list:
    return [encode_ahrs(t, LEVEL), encode_hil_sensor(t, np.array([0.1, -0.2, 9.8]), np.array([0.01, 0.0, -0.02]))]


def test_the_loop_leaves_every_other_read_to_the_parser():
    """frames_to_records takes nothing but a tick's whole, unsigned, gap-free frames from the one
    sender: each of these reads is left to pymavlink's parser (-1), the sequence number untouched."""
    good = _tick_frames(_tick(), 10)
    assert _frames_to_records(good, _framing(seq_in=9)) is not None
    gps = encode_hil_gps(1.25, np.zeros(3), np.zeros(3), GeoOrigin())
    # a HIL_SENSOR frame with its 65 payload bytes and one more, the checksum right
    payload = encode_packet(_tick()[1:])[1:] + b"\x07"
    sensor = frames.MAV_HIL_SENSOR
    head = bytes([0xFD, len(payload), 0, 0, 10, _SIM_SYS, _SIM_COMP]) + sensor["msgid"].to_bytes(3, "little")
    body = np.frombuffer(head[1:] + payload + bytes([sensor["crc_extra"]]), dtype=np.uint8)
    longer = head + payload + int(frames.crc_mcrf4xx(body, 0, len(body), 0xFFFF)).to_bytes(2, "little")
    cases = {
        "a frame cut at the end": good[:-1],
        "a frame's start only at the end": good + good[:7],
        "noise before": b"\x00" + good,
        "a checksum wrong": good[:-1] + bytes([good[-1] ^ 1]),
        "a payload byte wrong": good[:20] + bytes([good[20] ^ 0x40]) + good[21:],
        "another sender's system": _tick_frames(_tick(), 10).replace(b"\xff\xbe", b"\xfe\xbe", 1),
        "a gap in the numbers": _tick_frames(_tick(), 11),
        "a frame repeated": _tick_frames(_tick(), 9),
        "signed": _tick_frames(_tick(), 10, sign_key=bytes(range(32))),
        "another message (HIL_GPS)": _tick_frames([gps] + _tick(), 10),
        "MAVLink 1's start byte": b"\xfe" + good[1:],
        "a payload longer than the message's": bytes(longer),
    }
    for name, data in cases.items():
        framing = _framing(seq_in=9)
        assert _frames_to_records(data, framing) is None, name
        assert framing[frames.FRAMING["seq_read"]] == 0, name
    # pymavlink's own parser agrees that the longer payload is a good frame (it is not noise)
    assert [m.get_type() for m in D.MAVLink(None).parse_buffer(bytearray(longer))] == ["HIL_SENSOR"]


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_any_byte_changed_in_a_ticks_frames_leaves_them_to_the_parser(data):
    """A tick's frames with any one byte changed (header, payload or checksum): never taken."""
    good = bytearray(_tick_frames(_tick(), 10))
    at = data.draw(st.integers(0, len(good) - 1))
    good[at] ^= data.draw(st.integers(1, 255))
    assert _frames_to_records(bytes(good), _framing(seq_in=9)) is None


def test_the_simulators_tcp_port_reads_answers_as_pymavlinks_parser_does():
    """The simulator's end of PX4's TCP link (SimulatorPort: a read of whole answer frames decoded
    from their records in compiled code) against a plain MavlinkPort on the same bytes: whole
    answers, an answer cut in two writes, noise, a gap and a repeat in the sequence numbers, a
    frame from another system, two answers in one write, a signed one. The same messages (every
    field), and the same counters and sequence numbers after each step; the compiled reader took
    the plain reads."""
    servers, ports, conns = [], [], []
    for cls in (SimulatorPort, MavlinkPort):
        server = socket.create_server(("127.0.0.1", 0))
        servers.append(server)
        ports.append(cls(f"tcpout://127.0.0.1:{server.getsockname()[1]}", 255, 190, accept=ACTUATORS))
        conns.append(server.accept()[0])
    fast, plain = ports
    taken = []
    frames_to_records = simlink.frames_to_records
    simlink.frames_to_records = lambda *a: taken.append(frames_to_records(*a)) or taken[-1]
    vehicle = D.MAVLink(None, srcSystem=2, srcComponent=1)
    other = D.MAVLink(None, srcSystem=3, srcComponent=1)
    signer = D.MAVLink(None, srcSystem=2, srcComponent=1)
    signer.signing.secret_key, signer.signing.sign_outgoing, signer.signing.timestamp = bytes(32), True, 1

    def answer(k: int, mav=vehicle) -> bytes:
        msg = encode_actuators(0.002 * k, np.linspace(-9.0, 9.0, 8) * np.cos(k), 8.0, k % 3 != 0)
        frame = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        return frame

    def fields(m) -> tuple:
        return m.get_type(), m.time_usec, tuple(m.controls), m.mode, m.flags

    def step(data: bytes, n_msgs: int) -> None:
        for conn in conns:
            conn.sendall(data)
        got = []
        for port in ports:
            msgs, deadline = [], time.monotonic() + 2.0
            while len(msgs) < n_msgs or (not n_msgs and time.monotonic() < deadline - 1.9):
                assert time.monotonic() < deadline, (type(port).__name__, len(msgs), n_msgs)
                wait_readable([port], 0.01)
                msgs += port.read()
            got.append([fields(m) for m in msgs])
        assert got[0] == got[1]
        assert replace(fast.stats, last_rx_wall_s=0.0) == replace(plain.stats, last_rx_wall_s=0.0)
        assert fast._last_seq == plain._last_seq

    try:
        for k in range(1, 6):
            step(answer(k), 1)
        cut = answer(6)
        step(cut[:30], 0)
        step(cut[30:], 1)
        step(b"\x00noise", 0)
        step(answer(7), 1)
        answer(8)  # lost on the way: a gap
        step(answer(9), 1)
        vehicle.seq = (vehicle.seq - 1) % 256
        step(answer(10), 1)  # numbered as the one before: a repeat
        step(answer(11) + answer(12), 2)
        signer.seq = vehicle.seq
        step(answer(13, signer), 1)
        vehicle.seq = signer.seq
        step(answer(14), 1)
        step(answer(15, other), 1)  # a second sender: from here on, the parser's
        step(answer(16), 1)
    finally:
        simlink.frames_to_records = frames_to_records
        for x in ports + conns + servers:
            x.close()
    st = plain.stats
    assert st.rx_messages == 15 and st.seq_lost >= 1 and st.dropped_frames >= 1 and st.per_type == {
        "HIL_ACTUATOR_CONTROLS": 15}, st
    if COMPILED:  # taken: answers 2-5, 7, 11 and 12 (one read), 14
        assert [m for m in taken if m > 0] == [82] * 5 + [164, 82], str(taken)


# -- the simulator's writer: a tick's records built and framed in compiled code ------------------

@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**40), st.lists(st.floats(-3e5, 3e5, allow_nan=False), min_size=9, max_size=9),
       st.booleans(), st.booleans(), st.integers(1, 4))
def test_the_harness_records_are_the_messages_records(t_us, xs, mag, baro, n):
    """hil_sensor_records (the sensor records of n links in one compiled call) against the
    records of encode_hil_sensors' messages: the same bytes, with and without a magnetometer and a
    barometer sample."""
    t = t_us * 1e-6
    v = np.array(xs).reshape(3, 3)
    accel, gyro, field = (np.tile(v[k], (n, 1)) * np.arange(1, n + 1)[:, None] for k in range(3))
    kwargs = dict(mag_flu_gauss=field * 1e-5 if mag else None, baro_alt_m=v[2, :1].repeat(n) * 1e-2 if baro else None)
    want = encode_packet(simlink.encode_hil_sensors(t, accel, gyro, **kwargs))
    assert simlink.hil_sensor_records(t, accel, gyro, **kwargs).tobytes() == want


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 255), st.integers(1, 255), st.booleans(), st.booleans())
def test_the_harness_frames_are_pymavlinks(seq, sys_id, with_ahrs, with_answer):
    """records_to_frames (the harness's writer over TCP) against pymavlink: the frames of a packet
    of records (an attitude reference, a sensor sample, an answer) are the bytes pymavlink packs,
    numbered on from the link's next number (255 -> 0); a packet that is not whole records of
    those kinds, or whose frames do not fit, gives -1 with no number used."""
    msgs = _tick()[0 if with_ahrs else 1:]
    if with_answer:
        msgs.append(encode_actuators(1.25, np.linspace(-8.0, 8.0, 8), 8.0, True))
    packet = np.frombuffer(encode_packet(msgs), dtype=np.uint8)
    framing = _framing(sys_id=sys_id, seq_out=seq)
    out = np.zeros(1024, dtype=np.uint8)
    n = frames.records_to_frames(packet, len(packet), out, framing)
    mav = D.MAVLink(None, srcSystem=sys_id, srcComponent=1)
    mav.seq = seq
    assert out[:n].tobytes() == b"".join(_pack_seq(m, mav) for m in msgs)
    assert framing[frames.FRAMING["seq_out"]] == (seq + len(msgs)) % 256
    gps = np.frombuffer(encode_packet([encode_hil_gps(1.25, np.zeros(3), np.zeros(3), GeoOrigin())]), dtype=np.uint8)
    for bad, room in ((packet[:-1], 1024), (np.concatenate((packet, gps)), 1024), (packet, n - 1)):
        framing = _framing(sys_id=sys_id, seq_out=seq)
        assert frames.records_to_frames(bad, len(bad), np.zeros(room, dtype=np.uint8), framing) == -1
        assert framing[frames.FRAMING["seq_out"]] == seq


def _pack_seq(msg, mav) -> bytes:
    frame = msg.pack(mav)
    mav.seq = (mav.seq + 1) % 256
    return frame


def test_the_simulators_tcp_port_sends_records_as_pymavlinks_frames():
    """SimulatorPort.send_records over TCP loopback: the harness's messages (a GPS fix, packed by
    pymavlink) then its records (framed in compiled code) reach a pymavlink parser whole, in order,
    numbered without a gap and counted; on a signed link it sends nothing and says so (the caller
    sends the messages, signed)."""
    server = socket.create_server(("127.0.0.1", 0))
    port = SimulatorPort(f"tcpout://127.0.0.1:{server.getsockname()[1]}", 255, 190, accept=ACTUATORS)
    conn = server.accept()[0]
    try:
        parser = D.MAVLink(None)
        got = []
        gps = encode_hil_gps(1.25, np.array([1.0, 2.0, 3.0]), np.zeros(3), GeoOrigin())
        port.mav.seq = 254
        for k in range(3):
            records = simlink.hil_sensor_records(1.25 + 0.002 * k, np.array([[0.1, -0.2, 9.8]]), np.zeros((1, 3)))
            assert port.send_records([gps] if k == 1 else [], records[0]) is COMPILED
            if not COMPILED:
                port.send_many(([gps] if k == 1 else []) + simlink.encode_hil_sensors(
                    1.25 + 0.002 * k, np.array([[0.1, -0.2, 9.8]]), np.zeros((1, 3))))
        deadline = time.monotonic() + 2.0
        while len(got) < 4 and time.monotonic() < deadline:
            data = conn.recv(4096)
            got += [m for m in parser.parse_buffer(data) or []]
        assert [m.get_type() for m in got] == ["HIL_SENSOR", "HIL_GPS", "HIL_SENSOR", "HIL_SENSOR"]
        assert [m.get_seq() for m in got] == [254, 255, 0, 1] and port.mav.seq == 2
        assert [m.time_usec for m in got if m.get_type() == "HIL_SENSOR"] == [1250000, 1252000, 1254000]
        assert port.stats.tx_messages == 4 and parser.total_receive_errors == 0
        port.mav.signing.secret_key, port.mav.signing.sign_outgoing, port.mav.signing.timestamp = bytes(32), True, 1
        assert port.send_records([gps], records[0]) is False and port.mav.seq == 2 and port.stats.tx_messages == 4
    finally:
        for x in (port, conn, server):
            x.close()

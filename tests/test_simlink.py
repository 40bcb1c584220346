"""The same-host simulator link (link_firmware_sim.simlink): its records carry exactly what the
MAVLink HIL frames carry, malformed packets are counted and dropped, the socket is private, and a
vehicle behind it answers the lockstep with the same thrusts as behind PX4's TCP link."""

from __future__ import annotations

import os
import shutil
import socket
import stat
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import quat_normalize
from companion.mavlink.dialect import load_dialect
from companion.mavlink.port import MavlinkPort
from companion.mavlink.sockets import TcpClient
from companion.mavlink.transport import PortError, wait_readable
from companion.messages import Correction, PoseTarget
from companion.kernels.jit import ENABLED as COMPILED
from link_firmware_sim import simlink
from link_firmware_sim.kernels import mavlink_frames as frames
from link_firmware_sim.kernels.lockstep import LOOP_PACKET, LOOP_TICKED
from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.hil import (
    decode_actuators,
    decode_ahrs,
    decode_hil_baro_mag,
    decode_hil_gps,
    decode_hil_sensor,
    encode_actuators,
    encode_ahrs,
    encode_hil_gps,
    encode_hil_sensor,
)
from link_firmware_sim.simlink import (
    RECV_BYTES,
    SIM_KINDS,
    FrameError,
    SimLinkPort,
    SimulatorPort,
    decode_packet,
    encode_packet,
    open_sim_port,
)
from sitl.fleet.harness import FleetHarness
from sitl.fleet.layout import FleetError
from sitl.fleet.processes import listening_unix_paths
from sitl.scenario import load_scenario

from .test_vehicle import LEVEL, Rig

D = load_dialect()
SENSORS = frozenset({"HIL_SENSOR", "HIL_GPS", "SKELETON_AHRS_REFERENCE"})
ACTUATORS = frozenset({"HIL_ACTUATOR_CONTROLS"})


def _over_mavlink(msg):
    """``msg`` after a MAVLink 2 frame and pymavlink's parser (what the TCP link delivers)."""
    frame = msg.pack(D.MAVLink(None, srcSystem=1, srcComponent=1))
    return D.MAVLink(None).parse_char(bytearray(frame))


def _messages(rng: np.random.Generator) -> list:
    origin = GeoOrigin()
    t = float(rng.uniform(0, 100))
    return [
        encode_hil_gps(t, rng.normal(size=3) * 50, rng.normal(size=3), origin),
        encode_ahrs(t, quat_normalize(rng.normal(size=4))),
        encode_hil_sensor(t, rng.normal(size=3) + [0, 0, 9.8], rng.normal(size=3),
                          mag_flu_gauss=rng.normal(size=3) * 0.3, baro_alt_m=float(rng.uniform(0, 500))),
        encode_actuators(t, rng.uniform(-10, 10, size=8), 8.0, bool(rng.integers(2))),
    ]


@pytest.mark.parametrize("seed", range(5))
def test_records_carry_what_mavlink_frames_carry(seed):
    """Every field of every kind, through the link and through a MAVLink frame: equal (both float32)."""
    msgs = _messages(np.random.default_rng(seed))
    assert [m.get_type() for m in msgs] == sorted(SIM_KINDS, key=[m.get_type() for m in msgs].index)
    got = decode_packet(encode_packet(msgs))
    assert [r.get_type() for r in got] == [m.get_type() for m in msgs]
    for rec, msg in zip(got, msgs):
        ref = _over_mavlink(msg)
        for name in ref.fieldnames:
            assert getattr(rec, name) == pytest.approx(getattr(ref, name), rel=0, abs=0), (msg.get_type(), name)
    # and the decoders read them alike
    origin = GeoOrigin()
    ref = [_over_mavlink(m) for m in msgs]
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


def _pair(tmp_path):
    url = f"unixin://{tmp_path / 'link1.sock'}"
    vehicle = SimLinkPort(url, accept=SENSORS)
    sim = SimLinkPort(f"unix://{tmp_path / 'link1.sock'}", accept=ACTUATORS, connect_timeout_s=2.0)
    return vehicle, sim


def _read(port, want: int = 1, timeout_s: float = 2.0) -> list:
    out, deadline = port.read(), time.monotonic() + timeout_s
    while len(out) < want and time.monotonic() < deadline:
        time.sleep(0.001)
        out += port.read()
    return out


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


def test_a_pair_exchanges_counts_drops_and_sees_the_peer_go(tmp_path):
    vehicle, sim = _pair(tmp_path)
    try:
        path = tmp_path / "link1.sock"
        assert stat.S_IMODE(path.stat().st_mode) == 0o600  # only this user can connect
        assert str(path) in listening_unix_paths()
        _read(vehicle, 0, 0.05)  # accepts
        assert vehicle.connected and sim.connected
        msgs = _messages(np.random.default_rng(3))
        sim.send_many(msgs[:3])
        got = _read(vehicle, 3)
        assert [m.get_type() for m in got] == ["HIL_GPS", "SKELETON_AHRS_REFERENCE", "HIL_SENSOR"]
        # hostile packets: counted and dropped whole, never raised; the next good one goes through
        raw = sim.conn
        raw.send(b"\xff" * 40)
        raw.send(encode_packet(msgs[:1])[:-3])
        raw.send(encode_packet(msgs[3:]))  # the simulator's kind, sent to the vehicle
        raw.send(encode_packet(msgs[2:3] * 20))  # whole records, but more than a packet may hold
        sim.send(msgs[2])
        got = _read(vehicle, 1)
        assert [m.get_type() for m in got] == ["HIL_SENSOR"]
        st_ = vehicle.stats
        assert st_.dropped_frames == 4 and st_.rx_messages == 4 and st_.per_type["HIL_SENSOR"] == 2
        vehicle.send(msgs[3])
        (answer,) = _read(sim, 1)
        assert decode_actuators(answer, 8.0)[0] == msgs[3].time_usec
        # the simulator goes: the vehicle waits for the next one, which it then serves
        sim.close()
        deadline = time.monotonic() + 2.0
        while vehicle.connected and time.monotonic() < deadline:
            vehicle.read()
        assert not vehicle.connected
        sim = SimLinkPort(f"unix://{path}", accept=ACTUATORS, connect_timeout_s=2.0)
        _read(vehicle, 0, 0.05)
        assert vehicle.connected
        sim.send(msgs[2])
        assert len(_read(vehicle, 1)) == 1
        # the vehicle goes: the simulator's end is closed for good
        vehicle.close()
        assert not path.exists()
        deadline = time.monotonic() + 2.0
        while sim.connected and time.monotonic() < deadline:
            sim.read()
        assert not sim.connected and sim.read() == []
        sim.send(msgs[2])  # nothing to send to: no error
    finally:
        vehicle.close()
        sim.close()


def test_stale_socket_files_are_replaced_live_ones_are_not(tmp_path):
    path = tmp_path / "link1.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    stale.bind(str(path))
    stale.close()  # a killed vehicle's file: nobody listens
    first = SimLinkPort(f"unixin://{path}", accept=SENSORS)
    try:
        with pytest.raises(PortError, match="another process listens"):
            SimLinkPort(f"unixin://{path}", accept=SENSORS)
        assert first.server is not None and path.exists()
    finally:
        first.close()


def test_bad_urls_and_absent_peers_are_clear_errors(tmp_path):
    with pytest.raises(PortError, match="ABSOLUTE"):
        SimLinkPort("unixin://relative/path.sock")
    with pytest.raises(PortError, match="at most 107 bytes"):
        SimLinkPort("unixin:///" + "x" * 120)
    with pytest.raises(PortError, match="cannot connect"):
        SimLinkPort(f"unix://{tmp_path / 'nobody.sock'}", connect_timeout_s=0.1)
    assert isinstance(open_sim_port("tcpin://127.0.0.1:0", 1), MavlinkPort)


def test_another_users_process_is_refused(tmp_path):
    if os.getuid() != 0:
        pytest.skip("needs root to connect as another user")
    # a folder and a socket file open to all (the fleet's are private: this checks the last line)
    folder = Path(tempfile.mkdtemp(prefix="simlink-peer-"))
    os.chmod(folder, 0o777)
    path = folder / "link1.sock"
    vehicle = SimLinkPort(f"unixin://{path}", accept=SENSORS)
    os.chmod(path, 0o666)
    pid = os.fork()
    if pid == 0:  # the child: another user
        try:
            os.setuid(65534)
            s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            s.connect(str(path))
            s.send(encode_packet([encode_hil_sensor(1.0, np.zeros(3), np.zeros(3))]))
            time.sleep(0.3)
        finally:
            os._exit(0)
    try:
        deadline = time.monotonic() + 2.0
        while vehicle.stats.rejected_peer == 0 and time.monotonic() < deadline:
            assert vehicle.read() == []
            time.sleep(0.005)
        assert vehicle.stats.rejected_peer == 1 and not vehicle.connected
    finally:
        os.waitpid(pid, 0)
        vehicle.close()
        shutil.rmtree(folder, ignore_errors=True)


@pytest.mark.parametrize("jit", [True, False], ids=["compiled", "numpy"])
def test_a_vehicle_answers_alike_over_both_links(tmp_path, jit):
    """The same ticks into a vehicle behind TCP and one behind the same-host link: the same thrusts
    and the same EKF state and link counters, bit for bit. Over the same-host link the ticks without
    a GPS fix (IMU only, or an attitude reference and the IMU sample: 49 in 50) go from the packet's
    bytes to the answer's in compiled code: the lockstep loop's (Vehicle._poll_loop: the wait, the
    packet, the tick and the answer's send in one call) or the record tick's
    (Vehicle._tick_record); the others through the decoders. Over TCP the lockstep loop takes the
    same ticks from their MAVLink 2 frames (the record tick is the same-host link's only); the
    others, and every tick without the compiled kernels, are decoded."""
    if jit and not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    thrusts, states, taken, loops = {}, {}, {}, {}
    for link in ("tcp", "unix"):
        (tmp_path / link).mkdir()
        rig = Rig(tmp_path / link, sim_link=link)
        v = rig.vehicle
        v.fw.fused_tick = jit
        records = taken[link] = []
        plain = v._tick_record
        v._tick_record = lambda data: records.append(plain(data)) or records[-1]
        looped = loops[link] = []
        plain_loop = v.fw.on_hil_loop
        v.fw.on_hil_loop = lambda *a, **k: looped.append(plain_loop(*a, **k)) or looped[-1]
        try:
            _armed_with_a_target(rig)
            thrusts[link] = np.array([rig.tick(gps=k % 50 == 0, ahrs=k % 10 == 0) for k in range(100)])
            states[link] = (v.fw.ekf.x.copy(), v.fw.ekf.P.copy(), v.fc_time_us, dict(v.sim.stats.per_type),
                            v.sim.stats.rx_messages, v.sim.stats.tx_messages)
        finally:
            rig.close()
    assert np.abs(thrusts["tcp"]).sum(axis=1).min() > 10.0  # armed: carrying its weight
    np.testing.assert_array_equal(thrusts["unix"], thrusts["tcp"])
    for a, b in zip(states["unix"], states["tcp"]):
        np.testing.assert_array_equal(a, b)
    assert not taken["tcp"]
    # the 100 armed ticks with a target: 98 without a GPS record go by a compiled call, the lockstep
    # loop's (Vehicle._poll_loop) or, when the loop leaves the packet, the record tick's; the AHRS
    # records among them (8 of 10) are counted on the link as the decoders count them (per_type above)
    by_loop = sum(r[1] for r in loops["unix"] if r is not None)
    assert sum(taken["unix"]) + by_loop == (98 if jit else 0), (sum(taken["unix"]), by_loop)
    assert (by_loop >= 88) if jit else not any(r is not None for r in loops["unix"]), by_loop
    # over TCP the loop takes those 98 from their frames (it never leaves a whole tick's frames)
    by_loop = sum(r[1] for r in loops["tcp"] if r is not None)
    assert by_loop == (98 if jit else 0), by_loop



def _plain_and_looped(tmp_path, link: str, fly) -> tuple[dict, dict]:
    """``fly(rig, loop)`` on a new rig over ``link`` with the vehicle's lockstep loop off (the
    record tick, or the decoders over TCP), then on: both flights."""
    flights = {}
    for loop in (False, True):
        (tmp_path / str(loop)).mkdir()
        rig = Rig(tmp_path / str(loop), sim_link=link)
        try:
            flights[loop] = fly(rig, loop)
        finally:
            rig.close()
    return flights[False], flights[True]


def _armed_with_a_target(rig) -> None:
    """``rig``'s vehicle started, armed (as MAV_CMD_COMPONENT_ARM_DISARM would, at a fixed tick) and
    given a hold target 0.2 m east, 0.1 m south and 0.3 m above its control estimate."""
    v = rig.vehicle
    rig.start(0.3)
    assert v.fw.arm(rig.t)
    p, _, q = v.fw.control_estimate(rig.t)
    v.fw.set_target(rig.t, PoseTarget.hold(p + np.array([0.2, -0.1, 0.3]), q))


def _poll_in_thread(vehicle):
    """``vehicle`` polling in its own thread, as its process does; returns the call that stops it."""
    stop = threading.Event()

    def fly():
        while not stop.is_set():
            vehicle.poll(0.05)

    thread = threading.Thread(target=fly, daemon=True)
    thread.start()

    def stop_polling() -> None:
        stop.set()
        thread.join(2.0)

    return stop_polling


def _lockstep_flight(rig, n_ticks: int, loop: bool, on_tick=None, after=None, rough_every: int = 0) -> dict:
    """``n_ticks`` lockstep ticks into ``rig``'s vehicle (armed, with a target and a correction that
    fades out and lifts the control estimate past the take-off height), the vehicle polling in its
    own thread as its process does, so that records arrive while it waits (the lockstep loop runs
    several ticks in one call); what the flight leaves, for a bit-for-bit comparison. ``on_tick(k)``
    runs after tick ``k``'s answer, ``after()`` after the last, the vehicle still polling.
    ``rough_every`` (TCP): every so many ticks the tick's frames are written in two pieces, cut
    inside a frame, with a pause between, and noise (bytes no parser takes for a frame) is written
    before the next tick's."""
    v = rig.vehicle
    v.fw.hil_loop = loop
    calls = []
    plain = v.fw.on_hil_loop
    v.fw.on_hil_loop = lambda *a, **k: calls.append(plain(*a, **k)) or calls[-1]
    _armed_with_a_target(rig)
    v.fw.on_correction(rig.t, Correction(0, rig.t, np.array([0.05, 0.0, 0.2]), np.zeros(3), np.zeros(3)))
    stop_polling = _poll_in_thread(v)
    thrusts = []
    try:
        for k in range(n_ticks):
            rig.t = round(rig.t + 0.002, 6)
            wave = np.sin(0.37 * k)
            msgs = [encode_hil_gps(rig.t, np.array([0.0, 0.0, rig.height_m]), rig.vel_m_s, GeoOrigin())] \
                if k % 50 == 0 else []
            if k % 10 == 0:
                msgs.append(encode_ahrs(rig.t, LEVEL))
            msgs.append(encode_hil_sensor(rig.t, np.array([0.1 * wave, -0.05, 9.80665]),
                                          np.array([0.02 * wave, 0.01, -0.03 * wave])))
            if rough_every and k % rough_every == rough_every - 1:
                data = b"".join(rig.sim._pack(m) for m in msgs)
                cut = len(data) - 20  # inside the HIL_SENSOR frame
                rig.sim.transport.send(data[:cut])
                time.sleep(0.003)  # the vehicle reads the first piece alone
                rig.sim.transport.send(data[cut:])
            elif rough_every and k % rough_every == 0 and k:
                rig.sim.transport.send(b"\x00noise\x01")
                rig.sim.send_many(msgs)
            else:
                rig.sim.send_many(msgs)
            deadline = time.monotonic() + 2.0
            answer = None
            while answer is None:
                assert time.monotonic() < deadline, f"no answer at tick {k}"
                wait_readable([rig.sim], 0.05)
                for msg in rig.sim.read():
                    t_us, answer = decode_actuators(msg, 8.0)
                    assert t_us == int(round(rig.t * 1e6))
            thrusts.append(answer)
            if on_tick is not None:
                on_tick(k)
        if after is not None:
            after()
    finally:
        stop_polling()
    fw, st = v.fw, v.sim.stats
    return {"thrusts": np.array(thrusts), "x": fw.ekf.x, "P": fw.ekf.P, "pos_int": fw.integrals.pos,
            "att_int": fw.integrals.att, "xi_pre": fw.allocator.xi_pre, "time": (fw.time_s, v.fc_time_us),
            "airborne": fw._airborne, "thrust_n": fw._thrust_total_n, "log_t": v._rows["t"],
            "log_p": v._rows["p_ctrl"], "counts": (dict(st.per_type), st.rx_messages, st.tx_messages, st.rx_bytes),
            "dropped": (st.dropped_frames, st.dropped_bytes, st.seq_lost), "seq": _seq_numbers(v.sim, rig.sim),
            "calls": [c for c in calls if c is not None]}


def _seq_numbers(vehicle_port, sim_port) -> tuple:
    """A MAVLink link's sequence numbers both ways (the vehicle's next one, the last it heard, the
    simulator's record of the vehicle's); ``()`` on the same-host link, which has none."""
    if not isinstance(vehicle_port, MavlinkPort):
        return ()
    return vehicle_port.mav.seq, dict(vehicle_port._last_seq), dict(sim_port._last_seq), sim_port.stats.seq_lost


@pytest.mark.parametrize("link", ["unix", "tcp"])
def test_the_lockstep_loop_flies_as_the_record_tick(tmp_path, link):
    """The vehicle's lockstep loop (Vehicle._poll_loop: the waits, the packets, the quiet ticks and
    their answers in one compiled call) against the record tick it stands for (over TCP: the
    decoders and pymavlink's frames), over 400 ticks with a fading correction, a take-off and AHRS
    and GPS ticks: the same answers, EKF state, integrals, allocation state, flight log and link
    counters (sequence numbers both ways included), bit for bit; and the loop did run many ticks in
    a call and handed back the ticks that need the vehicle (streams and log rows at 50 Hz, the
    take-off) and the packets that are not its (AHRS, GPS)."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    plain, looped = _plain_and_looped(tmp_path, link, lambda rig, loop: _lockstep_flight(rig, 400, loop))
    assert np.abs(plain["thrusts"]).sum(axis=1).min() > 10.0 and plain["airborne"]
    for key in plain:
        if key != "calls":
            np.testing.assert_equal(looped[key], plain[key], err_msg=key)
    assert not plain["calls"]
    calls = looped["calls"]
    ticks = sum(c[1] for c in calls)
    assert ticks >= 300 and max(c[1] for c in calls) >= 5, (ticks, max(c[1] for c in calls))
    statuses = {c[0] for c in calls}
    assert {LOOP_TICKED, LOOP_PACKET} <= statuses, statuses



def test_the_lockstep_loop_over_tcp_hands_cut_frames_and_noise_to_the_parser(tmp_path):
    """Over PX4's TCP link the lockstep loop takes only reads that are a tick's whole frames: with
    ticks written in two pieces (cut inside a frame) and noise between ticks, it hands those bytes
    to pymavlink's parser, which joins the frames and counts the noise, and takes the stream back
    once the parser holds no partial frame. The flight is the decoders' flight bit for bit, the
    noise counted alike, and the loop still took most ticks."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    plain, looped = _plain_and_looped(tmp_path, "tcp",
                                      lambda rig, loop: _lockstep_flight(rig, 300, loop, rough_every=7))
    for key in plain:
        if key != "calls":
            np.testing.assert_equal(looped[key], plain[key], err_msg=key)
    dropped_frames, dropped_bytes, seq_lost = plain["dropped"]
    assert dropped_frames == 42 and dropped_bytes == 42 * 7 and seq_lost == 0, plain["dropped"]
    ticks = sum(c[1] for c in looped["calls"])
    handed = sum(c[0] == LOOP_PACKET for c in looped["calls"])
    assert ticks >= 150 and handed >= 2 * 42, (ticks, handed)  # (each cut tick's first piece, the noise)


def _unread_flight(rig, n_ticks: int, loop: bool) -> dict:
    """``n_ticks`` ticks into ``rig``'s vehicle over TCP (armed, with a target; polling in its own
    thread), 2 ms apart, with the socket buffers as small as Linux allows and the simulator reading
    no answer until the last tick is sent: the vehicle's sends fill the buffers and are cut or
    refused (EAGAIN), and it waits in them until the simulator reads."""
    v = rig.vehicle
    v.fw.hil_loop = loop
    rests = []
    plain_rest = v._answer_rest
    v._answer_rest = lambda a: rests.append(int(v._hil.framing[frames.FRAMING["sent"]])) or plain_rest(a)
    # the simulator reconnects with the least receive buffer (set before connecting: TCP's window)
    rig.sim.close()
    while v.sim.connected:
        v.poll(0.01)
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1)
    sock.connect(("127.0.0.1", v.sim.transport.local_port()))
    sock.setblocking(False)
    transport = TcpClient.__new__(TcpClient)  # (its constructor connects with the default buffers)
    transport.sock, transport.closed = sock, False
    rig.sim = MavlinkPort("tcpout://127.0.0.1", system_id=250, component_id=1, transport=transport)
    while not v.sim.connected:
        v.poll(0.01)
    v.sim.transport.conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1)
    _armed_with_a_target(rig)
    stop_polling = _poll_in_thread(v)
    want = []
    answers = []
    try:
        for k in range(n_ticks):
            rig.t = round(rig.t + 0.002, 6)
            want.append(int(round(rig.t * 1e6)))
            msgs = [encode_ahrs(rig.t, LEVEL)] if k % 10 == 0 else []
            msgs.append(encode_hil_sensor(rig.t, np.array([0.1 * np.sin(0.3 * k), -0.05, 9.80665]),
                                          np.array([0.01, 0.0, -0.02])))
            rig.sim.send_many(msgs)
            time.sleep(0.002)
        deadline = time.monotonic() + 10.0
        while len(answers) < n_ticks:
            assert time.monotonic() < deadline, len(answers)
            wait_readable([rig.sim], 0.05)
            answers += [decode_actuators(m, 8.0) for m in rig.sim.read()]
    finally:
        stop_polling()
    assert [t for t, _ in answers] == want
    st = rig.sim.stats
    return {"thrusts": np.array([a for _, a in answers]), "rests": rests,
            "harness": (st.rx_messages, st.seq_lost, st.dropped_frames, st.dropped_bytes),
            "vehicle": (v.sim.stats.tx_messages, v.sim.stats.tx_errors, v.sim.mav.seq)}


def test_the_lockstep_loop_over_tcp_finishes_an_answer_its_send_cut(tmp_path):
    """Over TCP the lockstep loop's send of an answer frame may take part of it or nothing (a full
    socket buffer: the simulator not reading); the vehicle then writes the rest (Vehicle.
    _answer_rest) and waits until it goes. With the buffers at their least and the simulator
    reading nothing for 300 ticks: every answer arrives whole and in order, no frame lost or
    broken, the same thrusts and counters as the decoding path's."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    plain, looped = _plain_and_looped(tmp_path, "tcp", lambda rig, loop: _unread_flight(rig, 300, loop))
    np.testing.assert_array_equal(looped["thrusts"], plain["thrusts"])
    assert looped["harness"] == plain["harness"] and plain["harness"][1:] == (0, 0, 0), plain["harness"]
    assert looped["vehicle"] == plain["vehicle"] and plain["vehicle"][1] == 0
    assert not plain["rests"] and looped["rests"], looped["rests"]  # the loop's sends were cut

    # ... and a send that took part of the frame (rare on loopback: the buffer has room for some
    # of its 93 bytes): the rest follows it and the simulator reads one whole answer
    rig = Rig(tmp_path / "cut", sim_link="tcp")
    try:
        v = rig.vehicle
        answer = np.frombuffer(encode_packet([encode_actuators(0.5, np.arange(8.0), 8.0, True)]), dtype=np.uint8)
        framing = v._hil.framing
        framing[:7] = (frames.FRAMES_TO_VEHICLE, 250, 1, 0, v.system_id, 1, v.sim.mav.seq)
        length = frames.record_to_frame(answer, v._hil.frame, framing)
        framing[frames.FRAMING["length"]], framing[frames.FRAMING["sent"]] = length, 40
        v.sim.transport.conn.send(v._hil.frame[:40].tobytes())
        v._answer_rest(answer)
        deadline, got = time.monotonic() + 2.0, []
        while not got:
            assert time.monotonic() < deadline
            wait_readable([rig.sim], 0.05)
            got = rig.sim.read()
        assert decode_actuators(got[0], 8.0)[0] == 500_000 and rig.sim.stats.dropped_frames == 0
    finally:
        rig.close()


def test_the_lockstep_loop_hands_mavlink_input_over_at_once_and_while_the_simulator_is_silent(tmp_path):
    """In the lockstep loop a vehicle waits on its MAVLink ports too and hands a readable one to
    poll at once: a GCS request sent between two ticks is answered by the next tick; with the
    simulator silent (armed, flying, no tick coming) it is answered all the same."""
    if not COMPILED:
        pytest.skip("numba not installed (or SKELETON_JIT=0)")
    rig = Rig(tmp_path, sim_link="unix")
    request = D.MAVLink_param_request_read_message(2, 1, b"SKL_CORR_HOLD", -1)
    answered_at, asked = [], []

    def replies():
        return [m for m in rig.gcs.read() if m.get_type() == "PARAM_VALUE"]

    def on_tick(k):
        if replies() and asked and not answered_at:
            answered_at.append(k)
        if k == 150:
            assert rig.gcs.transport.connected  # the vehicle's streams reached it: it can reply
            rig.gcs.send(request)
            asked.append(k)

    def after():
        time.sleep(0.1)  # the simulator silent: no tick comes
        rig.gcs.read()
        rig.gcs.send(request)
        deadline = time.monotonic() + 1.0
        while not replies():
            assert time.monotonic() < deadline, "no PARAM_VALUE while the simulator is silent"
            time.sleep(0.005)

    try:
        flight = _lockstep_flight(rig, 200, True, on_tick, after)
    finally:
        rig.close()
    assert sum(c[1] for c in flight["calls"]) >= 100
    # replied while tick 151 is on its way: the feeder finds it after tick 151 (152: UDP's timing)
    assert answered_at and answered_at[0] <= 152, answered_at


def test_the_harness_decodes_a_ticks_answers_together_and_names_a_link_answering_nan(tmp_path):
    """The fleet harness over the same-host link with three fake vehicles: their answers become
    the rotor commands of the tick (decoded together, as each alone); a non-finite answer stops
    the lockstep with a FleetError naming that link."""
    sc = load_scenario(Path(__file__).resolve().parents[1] / "configs" / "sitl" / "chain" / "three_link.toml")
    folder = Path(tempfile.mkdtemp(prefix="skl-h-"))  # short: a socket path's limit
    vehicles = [SimLinkPort(f"unixin://{folder / f'l{i}.sock'}", accept=SENSORS) for i in range(3)]
    answers = np.array([[1.0, -2.0, 3.0, 0.5, 0.0, 2.0, 9.0, -9.0]]) * np.array([[1.0], [0.5], [0.25]])
    poisoned = threading.Event()
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            for i in range(3):
                v = vehicles[i]
                if v in wait_readable([v], 0.01) or not v.connected:
                    for msg in v.read():
                        if msg.get_type() == "HIL_SENSOR":
                            u = answers[i].copy()
                            if i == 1 and poisoned.is_set():
                                u[3] = np.nan
                            v.send(encode_actuators(msg.time_usec * 1e-6, u, sc.rotors.thrust_max_n, True))

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    harness = FleetHarness(sc, [f"unix://{folder / f'l{i}.sock'}" for i in range(3)])
    try:
        truth = harness.plant.begin_tick()
        thrust = harness._exchange(0.0, 0, truth)
        expected = np.array([decode_actuators(_over_mavlink(encode_actuators(0.0, a, sc.rotors.thrust_max_n, True)),
                                              sc.rotors.thrust_max_n)[1] for a in answers])
        np.testing.assert_array_equal(thrust, expected)
        poisoned.set()
        with pytest.raises(FleetError, match=r"link\(s\) \[2\] answered the simulator with a non-finite control"):
            harness._exchange(0.002, 2, truth)
    finally:
        stop.set()
        server.join(2.0)
        harness.close()
        for v in vehicles:
            v.close()
        shutil.rmtree(folder, ignore_errors=True)

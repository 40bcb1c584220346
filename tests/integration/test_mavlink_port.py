"""MAVLink ports: transports, accounting of bad input, peer learning, tlogs, serial reconnection."""

from __future__ import annotations

import os
import select
import socket
import struct
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink import mavutil

from companion.mavlink.dialect import load_dialect
from companion.mavlink.port import MAX_DATAGRAM_BYTES, MavlinkPort
from companion.mavlink.tlog import TlogWriter
from companion.mavlink.transport import PortError, wait_readable
from companion.mavlink.urls import open_transport
from companion.mavlink.signing import SignatureChecker, Verdict, signing_timestamp

from ..clocks import FakeClock
from ..waits import wait_for

D = load_dialect()


def _heartbeat():
    return D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_GENERIC, 0, 0, 3, 3)


def _read_until(port, n, timeout=2.0):
    out = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        wait_readable([port], 0.05)
        out += port.read()
    return out


def _read_until_disconnected(port, timeout=2.0) -> bool:
    """Read ``port`` until its transport notices the peer is gone; whether it did within ``timeout``."""
    deadline = time.monotonic() + timeout
    while port.transport.connected and time.monotonic() < deadline:
        wait_readable([port], 0.05)
        port.read()
    return not port.transport.connected


def _read_while_counting(port, counted, timeout=2.0) -> list:
    """What ``port`` reads until ``counted()`` says its counters have seen every datagram sent to it."""
    out = []
    wait_for(lambda: out.extend(port.read()) or counted(), timeout)
    return out


def _unknown_id_frame() -> bytes:
    """A well-formed MAVLink 2 frame of message id 60123, which the dialect does not define."""
    payload = b"\x01\x02\x03"
    header = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, 0, 7, 1, 60123 & 0xFFFF, 60123 >> 16)
    return header + payload + b"\x00\x00"


@pytest.fixture
def udp_pair():
    server = MavlinkPort("udpin://127.0.0.1:0", system_id=190, accept=frozenset({"HEARTBEAT"}), peer_system_id=7)
    client = MavlinkPort(f"udpout://127.0.0.1:{server.transport.local_port()}", system_id=7)
    yield server, client
    server.close()
    client.close()


def test_udp_round_trip_and_reply_to_the_learned_peer(udp_pair):
    server, client = udp_pair
    assert not server.transport.connected
    server.send(_heartbeat())  # nobody to talk to yet: nothing is sent, nothing breaks
    client.send(_heartbeat())
    got = _read_until(server, 1)
    assert [m.get_srcSystem() for m in got] == [7]
    server.send(_heartbeat())
    back = _read_until(client, 1)
    assert back and back[0].get_srcSystem() == 190
    assert server.stats.rx_messages == 1 and server.stats.per_type == {"HEARTBEAT": 1}


def test_every_frame_carries_the_next_sequence_number(udp_pair):
    """One counter per port, wrapping at 256, whether frames go one by one or in one write."""
    server, client = udp_pair
    for _ in range(200):
        client.send(_heartbeat())
    client.send_many([_heartbeat() for _ in range(100)])
    got = _read_until(server, 300)
    seqs = [m.get_seq() for m in got]
    assert len(seqs) == 300 and seqs == [k % 256 for k in range(300)]


@pytest.mark.parametrize("n", [1, 3, 69, 150])
def test_send_many_on_udp_packs_whole_frames_into_few_datagrams(tmp_path, n):
    """Messages sent together share datagrams of whole frames, none over MAX_DATAGRAM_BYTES (an
    Ethernet MTU's payload): one datagram while they fit, the fewest after; every frame counted,
    numbered in order and in the tlog."""
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.bind(("127.0.0.1", 0))
    raw.settimeout(2.0)
    tlog = TlogWriter(tmp_path / "out.tlog")
    port = MavlinkPort(f"udpout://127.0.0.1:{raw.getsockname()[1]}", system_id=7, tlog=tlog)
    msgs = [_heartbeat() if k % 3 else D.MAVLink_param_value_message(f"P{k}".encode(), float(k), 9, n, k)
            for k in range(n)]
    frames = [m.pack(D.MAVLink(None, srcSystem=7, srcComponent=1)) for m in msgs]  # the sizes to expect
    port.send_many(msgs)
    datagrams = []
    raw.settimeout(0.3)
    try:
        while True:
            datagrams.append(raw.recvfrom(65536)[0])
    except socket.timeout:
        pass
    raw.close()
    port.close()
    assert all(len(d) <= MAX_DATAGRAM_BYTES for d in datagrams)
    got = []
    for i, d in enumerate(datagrams):  # each datagram alone parses to whole frames, nothing left over
        parser = D.MAVLink(None)
        parser.robust_parsing = True
        out = parser.parse_buffer(bytearray(d)) or []
        assert parser.buf_len() == 0 and all(m.get_type() != "BAD_DATA" for m in out)
        got += out
        if i + 1 < len(datagrams):  # full: the next frame would not have fitted
            assert len(d) + len(frames[len(got)]) > MAX_DATAGRAM_BYTES
    assert len(datagrams) == 1 or sum(map(len, frames)) > MAX_DATAGRAM_BYTES
    assert [m.get_type() for m in got] == [m.get_type() for m in msgs]
    assert [m.get_seq() for m in got] == [k % 256 for k in range(n)]
    assert port.stats.tx_messages == n
    log = mavutil.mavlink_connection(str(tmp_path / "out.tlog"), dialect="common")
    assert sum(1 for _ in iter(lambda: log.recv_match(blocking=False), None)) == n


def test_bad_input_is_counted_never_delivered_and_cannot_steal_the_peer(udp_pair):
    server, client = udp_pair
    client.send(_heartbeat())
    _read_until(server, 1)
    rng = np.random.default_rng(3)
    intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    frame = _heartbeat().pack(D.MAVLink(None, srcSystem=7, srcComponent=1))
    addr = ("127.0.0.1", server.transport.local_port())
    for k in range(50):
        intruder.sendto(rng.bytes(700), addr)
        intruder.sendto(frame[: 2 + k % (len(frame) - 3)], addr)  # truncated
    intruder.sendto(_unknown_id_frame(), addr)
    other = D.MAVLink_heartbeat_message(0, 0, 0, 0, 0, 3).pack(D.MAVLink(None, srcSystem=99, srcComponent=1))
    intruder.sendto(other, addr)  # valid, but not from the peer system
    ping = D.MAVLink_system_time_message(0, 0).pack(D.MAVLink(None, srcSystem=7, srcComponent=1))
    intruder.sendto(ping, addr)  # from "the peer", but not whitelisted: not a reason to re-aim either
    got = _read_while_counting(server, lambda: server.stats.ignored >= 1)  # (the last datagram)
    st = server.stats
    assert [m.get_srcSystem() for m in got] == [99]  # the caller decides what to do with a stranger
    assert st.dropped_bytes >= 50 * 700 and st.dropped_frames >= 100
    assert st.dropped_unknown >= 1 and st.ignored == 1
    # replies still go to the real peer
    server.send(_heartbeat())
    assert _read_until(client, 1)
    intruder.settimeout(0.2)
    with pytest.raises(socket.timeout):
        intruder.recvfrom(1000)
    intruder.close()


def test_tcp_server_client_and_reconnect():
    server = MavlinkPort("tcpin://127.0.0.1:0", system_id=1)
    port = server.transport.local_port()
    for attempt in range(2):  # a second client after the first went away
        client = MavlinkPort(f"tcpout://127.0.0.1:{port}", system_id=250)
        server.read()  # accept
        client.send_many([_heartbeat(), _heartbeat()])
        got = _read_until(server, 2)
        assert len(got) == 2 and got[0].get_srcSystem() == 250
        server.send(_heartbeat())
        assert _read_until(client, 1)[0].get_srcSystem() == 1
        client.close()
        assert _read_until_disconnected(server)
    server.close()


@pytest.mark.parametrize("url, what", [
    ("udp://127.0.0.1:14550", "unknown scheme"),
    ("udpin://127.0.0.1", "expected HOST:PORT"),
    ("serial:///dev/ttyACM0", "expected serial:///dev/...:BAUD"),
])
def test_bad_urls_are_rejected_with_the_reason(url, what):
    with pytest.raises(PortError, match=what):
        open_transport(url)


def test_port_in_use_is_a_clear_error():
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.bind(("127.0.0.1", 0))
    with pytest.raises(PortError, match=rf"cannot bind UDP 127.0.0.1:{holder.getsockname()[1]}"):
        open_transport(f"udpin://127.0.0.1:{holder.getsockname()[1]}")
    holder.close()


def test_tlog_is_readable_by_pymavlink(tmp_path):
    tlog = TlogWriter(tmp_path / "x.tlog", wall_clock=lambda: 1_700_000_000.25)
    server = MavlinkPort("udpin://127.0.0.1:0", system_id=190, tlog=tlog)
    client = MavlinkPort(f"udpout://127.0.0.1:{server.transport.local_port()}", system_id=7)
    client.send(_heartbeat())
    _read_until(server, 1)
    server.send(D.MAVLink_system_time_message(123, 456))
    server.close()
    client.close()
    log = mavutil.mavlink_connection(str(tmp_path / "x.tlog"), dialect="common")
    msgs = []
    while (m := log.recv_match()) is not None:
        msgs.append((m.get_type(), m.get_srcSystem(), m._timestamp))
    log.close()
    assert msgs == [("HEARTBEAT", 7, 1_700_000_000.25), ("SYSTEM_TIME", 190, 1_700_000_000.25)]


def test_serial_device_missing_then_plugged_in_then_unplugged(tmp_path, caplog):
    """A by-id path that appears later (autopilot powered after the daemon), then goes away."""
    link = tmp_path / "usb-Hex_ProfiCNC_CubeOrange-if00"
    clock = FakeClock()
    port = MavlinkPort(f"serial://{link}:921600", system_id=190, clock=clock)  # retries once a second
    assert not port.transport.connected and port.read() == [] and port.fileno() < 0
    assert wait_readable([port], 0.01) == [port]  # a port waiting to reopen is polled
    port.send(_heartbeat())  # dropped, not raised
    assert str(link) in caplog.text and "cannot open" in caplog.text
    master, slave = os.openpty()
    os.symlink(os.ttyname(slave), link)
    port.read()
    assert not port.transport.connected  # not retried before its second
    clock.t += 1.05
    port.read()
    assert port.transport.connected
    os.write(master, _heartbeat().pack(D.MAVLink(None, srcSystem=3, srcComponent=1)))
    got = _read_until(port, 1)
    assert got and got[0].get_srcSystem() == 3
    port.send(_heartbeat())
    parser = D.MAVLink(None)
    assert select.select([master], [], [], 2.0)[0], "nothing written to the serial device"
    echoed = parser.parse_buffer(bytearray(os.read(master, 4096)))
    assert echoed and echoed[0].get_srcSystem() == 190
    os.close(slave)
    os.close(master)  # unplugged: the next read notices, the port reopens later
    os.unlink(link)
    assert _read_until_disconnected(port)
    port.close()


# -- signing and peer learning ------------------------------------------------------------------------

KEY = bytes(range(32))


def _signed_frame(msg, key=KEY, sysid=7, link_id=0, timestamp=None):
    mav = D.MAVLink(None, srcSystem=sysid, srcComponent=1)
    mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = key, True, link_id
    mav.signing.timestamp = signing_timestamp() if timestamp is None else timestamp
    return bytes(msg.pack(mav))


def test_signature_checker_accepts_the_key_and_rejects_replays_wrong_keys_and_old_streams():
    now = signing_timestamp()
    checker = SignatureChecker("required", KEY)
    hb = _heartbeat()
    first = _signed_frame(hb, timestamp=now)
    assert checker.check(first, "HEARTBEAT", now) is Verdict.SIGNED
    assert checker.check(first, "HEARTBEAT", now) is Verdict.REJECTED_REPLAY
    assert checker.check(_signed_frame(hb, timestamp=now + 1), "HEARTBEAT", now) is Verdict.SIGNED
    assert checker.check(_signed_frame(hb, key=bytes(32), timestamp=now + 5), "HEARTBEAT", now) is Verdict.REJECTED_SIGNATURE
    unsigned = bytes(hb.pack(D.MAVLink(None, srcSystem=7, srcComponent=1)))
    assert checker.check(unsigned, "HEARTBEAT", now) is Verdict.REJECTED_UNSIGNED
    assert checker.check(unsigned, "RADIO_STATUS", now) is Verdict.UNSIGNED  # PX4's unsigned exception
    # a new stream (other link id) more than a minute behind: a recorded frame, rejected
    old = _signed_frame(hb, link_id=3, timestamp=now - 61 * 100_000)
    assert checker.check(old, "HEARTBEAT", now) is Verdict.REJECTED_REPLAY
    # permissive: unsigned accepted, a bad signature still rejected; off: nothing checked
    assert SignatureChecker("permissive", KEY).check(unsigned, "HEARTBEAT", now) is Verdict.UNSIGNED
    assert (SignatureChecker("permissive", KEY).check(_signed_frame(hb, key=bytes(32)), "HEARTBEAT", now)
            is Verdict.REJECTED_SIGNATURE)
    assert SignatureChecker("off", None).check(unsigned, "HEARTBEAT", now) is Verdict.NOT_CHECKED


def test_a_forged_frame_with_a_future_timestamp_does_not_lock_out_the_owner():
    """pymavlink's parser records a stream's timestamp before comparing the signature; the
    checker compares first (as PX4 does), so a forgery cannot poison the replay state."""
    now = signing_timestamp()
    checker = SignatureChecker("required", KEY)
    forged = bytearray(_signed_frame(_heartbeat(), timestamp=now + 10**9))
    forged[-1] ^= 0xFF
    assert checker.check(bytes(forged), "HEARTBEAT", now) is Verdict.REJECTED_SIGNATURE
    assert checker.check(_signed_frame(_heartbeat(), timestamp=now), "HEARTBEAT", now) is Verdict.SIGNED


@settings(max_examples=200, deadline=None)
@given(position=st.integers(min_value=0), bit=st.integers(min_value=0, max_value=7))
def test_any_altered_bit_of_a_signed_frame_is_rejected(position, bit):
    now = signing_timestamp()
    frame = bytearray(_signed_frame(D.MAVLink_system_time_message(123456789, 42), timestamp=now))
    frame[2] &= 0xFF  # keep the frame a frame: flip a bit anywhere past the incompat flags
    k = 3 + position % (len(frame) - 3)
    frame[k] ^= 1 << bit
    assert SignatureChecker("required", KEY).check(bytes(frame), "SYSTEM_TIME", now) is not Verdict.SIGNED


def test_ports_sign_and_check_end_to_end_and_count_rejections():
    server = MavlinkPort("udpin://127.0.0.1:0", system_id=190, accept=frozenset({"HEARTBEAT"}), peer_system_id=7,
                         signing="required", key=KEY)
    addr = ("127.0.0.1", server.transport.local_port())
    client = MavlinkPort(f"udpout://127.0.0.1:{addr[1]}", system_id=7, signing="required", key=KEY, link_id=2)
    stranger = MavlinkPort(f"udpout://127.0.0.1:{addr[1]}", system_id=7)  # same system id, no key
    wrong = MavlinkPort(f"udpout://127.0.0.1:{addr[1]}", system_id=7, signing="required", key=bytes(32))
    try:
        for _ in range(3):
            stranger.send(_heartbeat())
            wrong.send(_heartbeat())
        got = _read_while_counting(server, lambda: server.stats.rejected_signing >= 6)
        assert got == [] and not server.transport.connected  # nothing learnt from them
        client.send(_heartbeat())
        got = _read_until(server, 1)
        assert len(got) == 1 and got[0].get_signed() is False  # (the port checked it; pymavlink has no key)
        st_ = server.stats
        assert (st_.signed, st_.rejected_unsigned, st_.rejected_signature) == (1, 3, 3)
        server.send(_heartbeat())
        back = _read_until(client, 1)
        assert back and client.stats.signed == 1  # the server's reply is signed with the key
    finally:
        for p in (server, client, stranger, wrong):
            p.close()


def test_a_valid_frame_from_another_address_does_not_re_aim_replies_while_the_peer_lives():
    clock = FakeClock()
    server = MavlinkPort("udpin://127.0.0.1:0", system_id=190, accept=frozenset({"HEARTBEAT"}), peer_system_id=7,
                         peer_hold_s=0.3, clock=clock)
    port = server.transport.local_port()
    peer = MavlinkPort(f"udpout://127.0.0.1:{port}", system_id=7)
    hijacker = MavlinkPort(f"udpout://127.0.0.1:{port}", system_id=7)  # carries the peer's system id
    try:
        peer.send(_heartbeat())
        _read_until(server, 1)
        for k in range(5):
            hijacker.send(_heartbeat())
            peer.send(_heartbeat())
            _read_while_counting(server, lambda: server.stats.rx_messages >= 3 + 2 * k)  # both frames
            server.send(_heartbeat())
        replies = _read_until(peer, 5)
        assert len(replies) == 5 and hijacker.read() == []
        assert server.stats.peer_kept == 5
        clock.t += 0.4  # the peer goes silent (a rebooted vehicle comes back from elsewhere)
        hijacker.send(_heartbeat())
        _read_until(server, 1)
        server.send(_heartbeat())
        assert _read_until(hijacker, 1)
    finally:
        for p in (server, peer, hijacker):
            p.close()


def test_empty_host_and_udpout_bind_are_loopback():
    server = MavlinkPort("udpin://:0", system_id=1)
    out = MavlinkPort("udpout://127.0.0.1:9?bind=0", system_id=1)
    try:
        assert server.transport.sock.getsockname()[0] == "127.0.0.1"
        assert out.transport.sock.getsockname()[0] == "127.0.0.1"
    finally:
        server.close()
        out.close()

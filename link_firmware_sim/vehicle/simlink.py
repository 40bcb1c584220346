"""The same-host simulator link: the HIL messages as binary records over a UNIX socket.

PX4's simulator API stays the default link between the physics and a vehicle: MAVLink
``HIL_SENSOR`` / ``HIL_GPS`` / ``SKELETON_AHRS_REFERENCE`` in, ``HIL_ACTUATOR_CONTROLS`` out,
over TCP 4560+i (``tcpin://`` on the vehicle, ``tcpout://`` in the simulator; :mod:`.hil`). When
both run on one host, this link carries the same messages without what only a network needs:

* URLs ``unixin:///PATH`` (the vehicle: binds and listens, like ``tcpin``) and ``unix:///PATH``
  (the simulator: connects, retrying while the vehicle starts, like ``tcpout``);
* a ``SOCK_SEQPACKET`` socket: the kernel keeps each packet whole and in order and reports the
  peer closing, as TCP does, without TCP's stack;
* one packet per tick and direction; a packet is a run of records, each a 1-byte kind and the
  message's MAVLink payload in wire order (the dialect's own layout, :attr:`unpacker`): no
  header, sequence number or checksum, since nothing is lost, reordered or corrupted between
  two processes on one kernel.

A sender passes the :mod:`.hil` encoders' pymavlink messages; a receiver gets read-only records
with the same field names (an array field as a tuple) and ``get_type()``, for the :mod:`.hil`
decoders: units, frames and value checks are the same code on both links, only the framing
differs (``python -m sitl.bench sitl`` measures both). One exception, with the same bytes and
numbers: a vehicle takes a packet that is one IMU-only HIL_SENSOR record (its common tick), or a
SKELETON_AHRS_REFERENCE record and one (the attitude reference's ticks), to its answer record in
one compiled call (:meth:`.lockstep.Lockstep.tick_record`,
:func:`~link_firmware_sim.kernels.tick.hil_tick_kernel`), at the offsets
:data:`~link_firmware_sim.kernels.hil_records.HIL_SENSOR_RECORD` / ``HIL_AHRS_RECORD`` /
``HIL_ACTUATOR_RECORD``, which this module checks against the dialect when it is imported; every
other packet goes through the decoders. A run of such ticks, with the waits and the socket calls
between them, is one compiled call too (:meth:`.lockstep.Lockstep.run_loop`,
:func:`~link_firmware_sim.kernels.lockstep.hil_loop_kernel`: it receives into a buffer of
:data:`RECV_BYTES`, as :meth:`SimLinkPort.recv` does, and leaves any other packet to the decoders).

The records are the frames' payloads, so PX4's TCP link uses them too: the vehicle's lockstep
loop turns a read that is exactly a tick's whole MAVLink 2 frames into its records
(:func:`~link_firmware_sim.kernels.mavlink_frames.frames_to_records`; the message ids, CRC extras
and payload sizes of :data:`~link_firmware_sim.kernels.mavlink_frames.MAV_HIL_SENSOR` /
``MAV_HIL_AHRS`` / ``MAV_HIL_ACTUATOR`` are checked against the dialect here too) and its answer
record into the frame pymavlink packs; the harness reads the answers so (:class:`SimulatorPort`),
and builds every link's sensor records of a tick in one compiled call (:func:`hil_sensor_records`)
and writes them so (:meth:`SimulatorPort.send_records`, :meth:`SimLinkPort.send_records`). Every
other read goes through pymavlink's parser.

Trust: the socket file is created mode 0600 (its folder should be private too: the fleet
launcher makes one with :func:`tempfile.mkdtemp`), and the listener accepts only a peer process
of its own user (``SO_PEERCRED``); others are counted (``PortStats.rejected_peer``) and closed.
A packet with an unknown kind, a kind this side does not accept, a length that is not a whole
number of records, or more than 1024 bytes is dropped whole and counted (``dropped_frames``,
``dropped_bytes``); it never raises. A stale socket file (a killed vehicle's) is replaced; a
live one (another vehicle listening there) is a :class:`PortError`.
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import stat
import struct
import time
from collections import namedtuple
from operator import attrgetter
from pathlib import Path
from urllib.parse import urlparse

import numpy as np

from companion.mavlink.codec import usec
from companion.mavlink.dialect import load_dialect
from companion.mavlink.port import CountedPort, MavlinkPort, PortStats
from companion.mavlink.transport import PortError, send_all
from companion.mavlink.urls import open_transport
from companion.kernels.jit import ENABLED as _COMPILED

from ..kernels.hil_records import HIL_ACTUATOR_RECORD, HIL_AHRS_RECORD, HIL_SENSOR_RECORD, sensor_records
from ..kernels.mavlink_frames import (FRAMES_TO_SIMULATOR, FRAMING, FRAMING_SIZE, MAV2_HEADER, MAV_HIL_ACTUATOR,
                                     MAV_HIL_AHRS, MAV_HIL_SENSOR, frames_to_records, records_to_frames)
from .hil import encode_hil_sensors, hil_sensor_values

__all__ = ["SIM_KINDS", "FrameError", "encode_packet", "decode_packet", "hil_sensor_records", "SimLinkPort",
           "SimulatorPort", "open_sim_port", "is_simlink_url"]

log = logging.getLogger(__name__)

#: the message kinds of the link, by record tag (the tag is the index)
SIM_KINDS = ("HIL_SENSOR", "HIL_GPS", "SKELETON_AHRS_REFERENCE", "HIL_ACTUATOR_CONTROLS")
_SCHEMES = ("unix", "unixin")
#: the longest packet taken: far above what a tick carries (GPS, AHRS and the IMU sample: 131 bytes)
_MAX_PACKET = 1024
#: one receive's buffer: a longer packet is cut, and seen as too long
RECV_BYTES = _MAX_PACKET + 1
#: a UNIX socket path's limit (sun_path is 108 bytes with its terminating NUL on Linux)
_MAX_PATH = 107


class FrameError(ValueError):
    """A packet that is not a run of whole records of accepted kinds."""


class _Layout:
    """One kind's record: its tag, the pymavlink class, and the payload's struct in wire order."""

    def __init__(self, tag: int, cls):
        self.name = cls.msgname
        self.struct: struct.Struct = cls.unpacker
        self.size = 1 + self.struct.size
        self.head = bytes([tag])
        self.fields = tuple(cls.ordered_fieldnames)
        self.lengths = tuple(cls.array_lengths)
        self.flat = not any(self.lengths)
        self._get = attrgetter(*self.fields)
        # what a receiver gets: a read-only record with the message's field names and get_type(),
        # all the .hil decoders use (cheaper to build than a pymavlink message)
        name = self.name

        class Record(namedtuple(f"{cls.__name__}_record", self.fields)):
            __slots__ = ()

            def get_type(self) -> str:
                return name

        self.record = Record
        # where each field sits in the unpacked values: an index, or a slice for an array field
        keys, i = [], 0
        for n in self.lengths:
            keys.append(slice(i, i + n) if n else i)
            i += n or 1
        self._keys = tuple(keys)

    def pack(self, msg) -> bytes:
        values = self._get(msg)
        if not self.flat:
            out = []
            for v, n in zip(values, self.lengths):
                if n:
                    if len(v) != n:
                        raise FrameError(f"{self.name}: an array field of {len(v)} values, expected {n}")
                    out.extend(v)
                else:
                    out.append(v)
            values = out
        try:
            return self.head + self.struct.pack(*values)
        except struct.error as exc:
            raise FrameError(f"{self.name}: {exc}") from None

    def unpack(self, data: bytes, offset: int):
        values = self.struct.unpack_from(data, offset + 1)
        if self.flat:
            return tuple.__new__(self.record, values)
        return tuple.__new__(self.record, [values[k] for k in self._keys])  # an array field: a tuple


def _layouts() -> dict[str, _Layout]:
    D = load_dialect()
    by_name = {cls.msgname: cls for cls in D.mavlink_map.values()}
    return {name: _Layout(tag, by_name[name]) for tag, name in enumerate(SIM_KINDS)}


_LAYOUTS = _layouts()
_BY_TAG = tuple(_LAYOUTS[name] for name in SIM_KINDS)


def _check_compiled_layouts() -> None:
    """The compiled record tick (:func:`~link_firmware_sim.kernels.tick.hil_tick_kernel`) reads and
    writes the records at fixed offsets: they must be this dialect's (a changed message definition
    fails here, at import, not as wrong numbers in flight). Checked on records this module packs,
    each field a distinct value read back at the kernel's offset."""
    D = load_dialect()
    t_us, flags, bits, mode = 0x0102030405060708, 0x1112131415161718, 0x89ABCDEF, 0x5A
    imu = tuple(float(k) for k in range(1, 7))  # xacc..zacc, xgyro..zgyro (exact in float32)
    controls = tuple(float(k) for k in range(101, 117))
    s, a, r = HIL_SENSOR_RECORD, HIL_ACTUATOR_RECORD, HIL_AHRS_RECORD
    sensor = _LAYOUTS["HIL_SENSOR"].pack(D.MAVLink_hil_sensor_message(
        t_us, *imu, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, fields_updated=bits, id=0))
    ahrs = _LAYOUTS["SKELETON_AHRS_REFERENCE"].pack(D.MAVLink_skeleton_ahrs_reference_message(t_us, imu[:4]))
    answer = _LAYOUTS["HIL_ACTUATOR_CONTROLS"].pack(D.MAVLink_hil_actuator_controls_message(
        t_us, controls, mode, flags))
    checks = [
        ("HIL_SENSOR size", len(sensor), s["size"]),
        ("HIL_SENSOR kind", sensor[0], s["kind"]),
        ("HIL_SENSOR.time_usec", struct.unpack_from("<Q", sensor, s["time_usec"])[0], t_us),
        ("HIL_SENSOR acc and gyro", struct.unpack_from("<6f", sensor, s["acc"]), imu),
        ("HIL_SENSOR gyro", struct.unpack_from("<3f", sensor, s["gyro"]), imu[3:]),
        ("HIL_SENSOR.fields_updated", struct.unpack_from("<I", sensor, s["fields_updated"])[0], bits),
        ("HIL_SENSOR's floats, from acc", struct.unpack_from(f"<{s['floats']}f", sensor, s["acc"]),
         imu + (0.0,) * (s["floats"] - 6)),
        ("HIL_SENSOR's floats end at fields_updated", s["acc"] + 4 * s["floats"], s["fields_updated"]),
        ("HIL_SENSOR.id, the last byte", s["id"], s["size"] - 1),
        ("SKELETON_AHRS_REFERENCE size", len(ahrs), r["size"]),
        ("SKELETON_AHRS_REFERENCE kind", ahrs[0], r["kind"]),
        ("SKELETON_AHRS_REFERENCE.time_usec", struct.unpack_from("<Q", ahrs, r["time_usec"])[0], t_us),
        ("SKELETON_AHRS_REFERENCE.q", struct.unpack_from("<4f", ahrs, r["q"]), imu[:4]),
        ("HIL_ACTUATOR_CONTROLS size", len(answer), a["size"]),
        ("HIL_ACTUATOR_CONTROLS kind", answer[0], a["kind"]),
        ("HIL_ACTUATOR_CONTROLS.time_usec", struct.unpack_from("<Q", answer, a["time_usec"])[0], t_us),
        ("HIL_ACTUATOR_CONTROLS.flags", struct.unpack_from("<Q", answer, a["flags"])[0], flags),
        ("HIL_ACTUATOR_CONTROLS.controls", struct.unpack_from("<16f", answer, a["controls"]), controls),
        ("HIL_ACTUATOR_CONTROLS.mode", answer[a["mode"]], mode),
    ]
    by_name = {cls.msgname: cls for cls in D.mavlink_map.values()}
    for name, frame in (("HIL_SENSOR", MAV_HIL_SENSOR), ("SKELETON_AHRS_REFERENCE", MAV_HIL_AHRS),
                        ("HIL_ACTUATOR_CONTROLS", MAV_HIL_ACTUATOR)):  # ... and over TCP, their frames
        cls = by_name[name]
        checks += [(f"{name}'s message id", cls.id, frame["msgid"]),
                   (f"{name}'s CRC extra", cls.crc_extra, frame["crc_extra"]),
                   (f"{name}'s payload size", cls.unpacker.size, frame["size"])]
    for name, have, want in checks:
        if have != want:
            raise RuntimeError(f"the kernels' simulator-link records do not match the dialect: "
                               f"{name} reads {have}, expected {want}")


_check_compiled_layouts()


def encode_packet(msgs) -> bytes:
    """One packet of ``msgs`` (pymavlink messages of :data:`SIM_KINDS`)."""
    try:
        return b"".join(_LAYOUTS[m.get_type()].pack(m) for m in msgs)
    except KeyError as exc:
        raise FrameError(f"{exc.args[0]} is not a simulator-link message ({', '.join(SIM_KINDS)})") from None


def hil_sensor_records(t_s: float, accel_flu_m_s2, gyro_flu_rad_s, *, mag_flu_gauss=None,
                       baro_alt_m=None) -> np.ndarray:
    """The HIL_SENSOR records of ``n`` links (uint8, ``(n, size)``, the arguments of
    :func:`~.hil.hil_sensor_values`): the bytes :func:`encode_packet` gives for
    :func:`~.hil.encode_hil_sensors`' messages, link by link, in one compiled call
    (:func:`~link_firmware_sim.kernels.hil_records.sensor_records`; without the compiled kernels, or
    for a value pymavlink refuses to pack, through those two)."""
    values, bits = hil_sensor_values(accel_flu_m_s2, gyro_flu_rad_s, mag_flu_gauss=mag_flu_gauss,
                                     baro_alt_m=baro_alt_m)
    t_us = usec(t_s)
    out = np.empty((len(values), HIL_SENSOR_RECORD["size"]), dtype=np.uint8)
    if not (_COMPILED and 0 <= t_us < 2 ** 63 and sensor_records(t_us, values, bits, out)):
        msgs = encode_hil_sensors(t_s, accel_flu_m_s2, gyro_flu_rad_s, mag_flu_gauss=mag_flu_gauss,
                                  baro_alt_m=baro_alt_m)
        out[:] = np.frombuffer(encode_packet(msgs), dtype=np.uint8).reshape(out.shape)
    return out


def decode_packet(data: bytes, accept: frozenset[str] | None = None) -> list:
    """The messages of one packet; :class:`FrameError` (nothing decoded) unless it is a run of
    whole records whose kinds are in ``accept`` (``None``: every kind)."""
    out, i, n = [], 0, len(data)
    if n == 0:
        raise FrameError("an empty packet")
    while i < n:
        tag = data[i]
        if tag >= len(_BY_TAG):
            raise FrameError(f"unknown record kind {tag} at byte {i}")
        layout = _BY_TAG[tag]
        if accept is not None and layout.name not in accept:
            raise FrameError(f"{layout.name} is not accepted on this side of the link")
        if i + layout.size > n:
            raise FrameError(f"a {layout.name} record cut short: {n - i} of {layout.size} bytes")
        out.append(layout.unpack(data, i))
        i += layout.size
    return out


def is_simlink_url(url: str) -> bool:
    return urlparse(url).scheme in _SCHEMES


def _path_of(url: str) -> tuple[str, Path]:
    parsed = urlparse(url)
    if parsed.scheme not in _SCHEMES or parsed.netloc or not parsed.path.startswith("/"):
        raise PortError(f"{url}: expected unixin:///ABSOLUTE/PATH or unix:///ABSOLUTE/PATH")
    if len(os.fsencode(parsed.path)) > _MAX_PATH:
        raise PortError(f"{url}: a UNIX socket path is at most {_MAX_PATH} bytes")
    return parsed.scheme, Path(parsed.path)


class SimLinkPort(CountedPort):
    """One end of a same-host simulator link; reads never block, like :class:`MavlinkPort`'s.

    ``accept``: the kinds this end takes (the vehicle: the sensor messages; the simulator: the
    actuator controls). The interface is the part of :class:`MavlinkPort` a simulator link uses:
    ``read``, ``send``, ``send_many``, ``fileno``, ``connected``, ``stats``, ``url``, ``close``.
    """

    def __init__(self, url: str, accept: frozenset[str] | None = None, connect_timeout_s: float = 10.0):
        self.url = url
        self.accept = accept
        self.stats = PortStats()
        self._warned_s = -float("inf")
        scheme, self.path = _path_of(url)
        self.listening = scheme == "unixin"
        self.server: socket.socket | None = None
        self.conn: socket.socket | None = None
        if self.listening:
            self._listen()
        else:
            self.conn = self._connect(connect_timeout_s)

    def _listen(self) -> None:
        try:
            stale = stat.S_ISSOCK(self.path.lstat().st_mode)
        except FileNotFoundError:
            stale = False
        if stale:  # a killed vehicle's socket is ours to replace; a live one's is not
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            try:
                probe.connect(str(self.path))
            except OSError:
                self.path.unlink()
            else:
                raise PortError(f"cannot bind {self.url}: another process listens there")
            finally:
                probe.close()
        s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        old = os.umask(0o177)  # the socket file: 0600
        try:
            s.bind(str(self.path))
        except OSError as exc:
            s.close()
            raise PortError(f"cannot bind {self.url}: {exc.strerror}") from None
        finally:
            os.umask(old)
        s.listen(1)
        s.setblocking(False)
        self.server = s

    def _connect(self, timeout_s: float) -> socket.socket:
        deadline = time.monotonic() + timeout_s
        while True:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            try:
                s.connect(str(self.path))
                s.setblocking(False)
                return s
            except OSError as exc:
                s.close()
                if exc.errno not in (errno.ENOENT, errno.ECONNREFUSED, errno.EAGAIN) or time.monotonic() > deadline:
                    raise PortError(f"cannot connect to {self.url}: {exc.strerror}") from None
            time.sleep(0.05)

    def fileno(self) -> int:
        sock = self.conn or self.server
        return sock.fileno() if sock is not None else -1

    @property
    def connected(self) -> bool:
        return self.conn is not None

    def _accept(self) -> None:
        try:
            conn, _ = self.server.accept()
        except (BlockingIOError, InterruptedError):
            return
        pid, uid, _gid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12))
        if uid != os.getuid():
            conn.close()
            self.stats.rejected_peer += 1
            self._warn(f"refused a simulator connection from process {pid} of user {uid}")
            return
        conn.setblocking(False)
        self.conn = conn

    def _warn(self, text: str) -> None:
        now = time.monotonic()
        if now - self._warned_s >= 5.0:  # the first, then at most one every 5 s
            self._warned_s = now
            log.warning("%s: %s (dropped so far: %d packets)", self.url, text, self.stats.dropped_frames)

    def _lost_peer(self) -> None:
        """The peer went: a listener accepts the next one; a connecting end stays unconnected."""
        self.conn.close()
        self.conn = None

    def read(self) -> list:
        """The accepted messages of the next packet (``[]`` if none is waiting, or it was dropped).

        One packet per call: the lockstep has at most one in flight per direction, so a second
        ``recv`` would only hear EAGAIN; a backlog (a flood) makes the socket readable again and
        the next calls read it, the caller's other ports served in between.
        """
        data = self.recv()
        return [] if data is None else self.decode(data)

    def recv(self) -> bytes | None:
        """:meth:`read`'s first half: the next packet's bytes, undecoded (``None`` if none is
        waiting); counted in ``rx_bytes``. Its messages are counted by :meth:`decode`, or by
        :meth:`count` for a packet the caller takes as it is (the vehicle's record tick)."""
        if self.conn is None:
            if self.listening:
                self._accept()
            return None
        try:
            data = self.conn.recv(RECV_BYTES)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError:
            data = b""  # reset by the peer
        if not data:  # the peer closed (a listener waits for the next one)
            self._lost_peer()
            return None
        self.received(len(data))
        return data

    def decode(self, data: bytes) -> list:
        """:meth:`read`'s second half: the accepted messages of the packet ``data``, counted;
        ``[]`` for a packet dropped whole (counted, warned about)."""
        st = self.stats
        try:
            if len(data) > _MAX_PACKET:
                raise FrameError(f"a packet of more than {_MAX_PACKET} bytes")
            msgs = decode_packet(data, self.accept)
        except FrameError as exc:
            st.dropped_frames += 1
            st.dropped_bytes += len(data)
            self._warn(f"dropped a packet: {exc}")
            return []
        for m in msgs:
            self.count(m.get_type())
        return msgs

    def send(self, msg) -> None:
        self.send_many((msg,))

    def send_many(self, msgs) -> None:
        """Send ``msgs`` as one packet (nothing while no peer is connected)."""
        msgs = list(msgs)
        self.send_packet(encode_packet(msgs), len(msgs))

    def send_records(self, msgs, records: np.ndarray, n_records: int = 1) -> bool:
        """Send ``msgs`` (pymavlink messages) and then ``records`` (uint8: ``n_records`` whole
        records, e.g. a row of :func:`hil_sensor_records`) as one packet; True (sent, or nothing
        sent while no peer is connected), as :meth:`SimulatorPort.send_records` when it may."""
        self.send_packet((encode_packet(msgs) if msgs else b"") + records.tobytes(), len(msgs) + n_records)
        return True

    def send_packet(self, data, n_messages: int = 1) -> None:
        """Send one packet already encoded (bytes, or a uint8 array: the vehicle's record tick
        answers from its buffer) holding ``n_messages`` records."""
        if self.conn is None:
            return
        try:
            send_all(self.conn, data)
        except (BrokenPipeError, ConnectionResetError):
            self._lost_peer()
            return
        except OSError:
            self.stats.tx_errors += 1
            return
        self.stats.tx_messages += n_messages

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None
        if self.server is not None:
            self.server.close()
            self.server = None
            try:
                self.path.unlink()
            except OSError:
                pass


class SimulatorPort(MavlinkPort):
    """The simulator's end of PX4's TCP link, reading the vehicles' answers: a read that is exactly
    whole HIL_ACTUATOR_CONTROLS frames (unsigned, from the one vehicle heard, numbered on without a
    gap, checksums good: :func:`~link_firmware_sim.kernels.mavlink_frames.frames_to_records`) is
    decoded from its records, as the same-host link's are (the same field values: the records are
    the frames' payloads); any other read, and every read while the port may not hand its stream
    over (:meth:`MavlinkPort.handover`) or without the compiled kernels, goes through pymavlink's
    parser with its checks and counters."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._buf = np.zeros(RECV_BYTES, dtype=np.uint8)
        self._records = np.zeros(RECV_BYTES, dtype=np.uint8)
        self._framing = np.zeros(FRAMING_SIZE, dtype=np.int64)
        self._out_framing = np.zeros(FRAMING_SIZE, dtype=np.int64)  # (this end's numbering, for send_records)
        self._frames = np.zeros(_SEND_BYTES, dtype=np.uint8)

    def send_records(self, msgs, records: np.ndarray, n_records: int = 1) -> bool:
        """Send ``msgs`` (pymavlink messages) and then the messages of ``records`` (uint8:
        ``n_records`` whole records of the same-host link, e.g. a row of
        :func:`hil_sensor_records`) in one write, the records framed in one compiled call
        (:func:`~link_firmware_sim.kernels.mavlink_frames.records_to_frames`: the frames pymavlink
        packs, numbered on from this link's sequence). False (nothing sent) where this link may not
        frame them so (no compiled kernels, signing on, a tlog, not a stream): the caller sends
        the messages."""
        if not _COMPILED or self.mav.signing.sign_outgoing or self.tlog is not None or self.transport.datagram:
            return False
        seq = self.mav.seq
        frames = [self._pack(m) for m in msgs]
        framing = self._out_framing
        framing[_OUT_SYS], framing[_OUT_COMP], framing[_OUT_SEQ] = self.mav.srcSystem, self.mav.srcComponent, self.mav.seq
        n = records_to_frames(records, len(records), self._frames, framing)
        if n < 0:
            self.mav.seq = seq  # (nothing sent: the numbers not used)
            return False
        self.mav.seq = int(framing[_OUT_SEQ])
        frames.append(self._frames[:n].tobytes())
        self._write(frames, len(msgs) + n_records)
        return True

    def read(self) -> list:
        handover = self.handover() if _COMPILED else None
        if handover is None:
            return super().read()
        fd, sender, last_seq = handover
        try:
            n = os.readv(fd, [self._buf])
        except BlockingIOError:
            return []
        except OSError:
            n = 0
        if n == 0:  # the peer closed, or an error: the transport's own read sees it
            return super().read()
        framing = self._framing
        framing[:4] = (FRAMES_TO_SIMULATOR, *sender, last_seq)
        m = frames_to_records(self._buf, n, self._records, framing)
        if m < 0:
            return self.parse(self._buf[:n].tobytes())
        msgs = decode_packet(self._records[:m].tobytes(), self.accept)
        self.received(n)
        self.count("HIL_ACTUATOR_CONTROLS", len(msgs))
        self.resume(sender, int(framing[_SEQ_READ]), self.mav.seq)
        return msgs


_SEQ_READ = FRAMING["seq_read"]
_OUT_SYS, _OUT_COMP, _OUT_SEQ = FRAMING["sys"], FRAMING["comp"], FRAMING["seq_out"]
#: the frames :meth:`SimulatorPort.send_records` writes at once: a tick's records, framed
_SEND_BYTES = 4 * (MAV2_HEADER + 2) + _MAX_PACKET


def open_sim_port(url: str, system_id: int, component_id: int = 1, accept: frozenset[str] | None = None,
                  connect_timeout_s: float = 10.0, simulator: bool = False):
    """The simulator link of ``url``: a :class:`SimLinkPort` for ``unix``/``unixin`` URLs, else a
    :class:`MavlinkPort` (PX4's simulator API over TCP, the default; the simulator's end,
    ``simulator``, a :class:`SimulatorPort`). A connecting end retries for ``connect_timeout_s``
    while the other end starts."""
    if is_simlink_url(url):
        return SimLinkPort(url, accept, connect_timeout_s)
    return (SimulatorPort if simulator else MavlinkPort)(url, system_id, component_id, accept=accept,
                                                         transport=open_transport(url, connect_timeout_s))

"""MAVLink ports: a transport (UDP, TCP or serial) plus parsing, accounting and a .tlog.

A :class:`MavlinkPort` owns its socket or serial device, so it sees every byte: frames that fail
to parse (bad CRC, truncated, random bytes) are counted as dropped bytes, frames with a message
id the dialect does not know are counted as unknown, and well-formed messages not in the port's
whitelist are counted as ignored; only whitelisted messages reach the caller. Reads never block
(the caller waits with :func:`wait_readable` or its own ``select``).

Transports (URL syntax as MAVSDK / MAVProxy users expect; an empty HOST means 127.0.0.1, so
nothing is reachable from off the machine unless a URL names an interface or 0.0.0.0):

* ``udpin://HOST:PORT``: bind and listen; replies go to the sender of the last valid frame
  from the expected system (see :class:`MavlinkPort`);
* ``udpout://HOST:PORT`` (optionally ``?bind=PORT`` or ``?bind=HOST:PORT``): send to
  ``HOST:PORT`` from a local port (fixed with ``bind``, like PX4 SITL's local ports 14580+i;
  the local address is 127.0.0.1 when HOST is a loopback address, else 0.0.0.0);
* ``tcpin://HOST:PORT`` (a server: the first client is the peer) / ``tcpout://HOST:PORT``;
* ``serial:///dev/serial/by-id/...:BAUD``.

A tlog (``.tlog``: 8-byte big-endian UNIX time in microseconds, then the raw frame, per message;
readable by pymavlink and MAVExplorer) records what the port sends and accepts.

MAVLink 2 signing (:mod:`companion.mavlink.signing`) is per port: with a mode other than
``off`` every frame sent is signed, and incoming frames are checked before anything else sees
them; rejected frames (unsigned where signing is required, a bad signature, a replay) are
counted in :class:`PortStats` and logged (the first of each kind, then at most every 5 s).
"""

from __future__ import annotations

import errno
import logging
import os
import select
import socket
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import parse_qs, urlparse

from .dialect import load_dialect
from .signing import UNSIGNED_ALLOWED, SignatureChecker, SigningMode, Verdict, signing_timestamp

__all__ = ["PortStats", "Transport", "open_transport", "CountedPort", "MavlinkPort", "TlogWriter", "wait_readable",
           "PortError", "send_all"]

log = logging.getLogger(__name__)

_READ_CHUNK = 65536
# The most MAVLink bytes one UDP datagram carries when several frames are sent together: an
# Ethernet MTU (1500) less the IPv4 and UDP headers, so a batch is never fragmented on a real link.
MAX_DATAGRAM_BYTES = 1472


class PortError(ValueError):
    """A port URL that cannot be opened (bad syntax, missing device, port in use)."""


@dataclass
class PortStats:
    rx_bytes: int = 0
    rx_messages: int = 0  # accepted (whitelisted) messages
    dropped_bytes: int = 0  # bytes that never reached the application (noise, bad CRC, truncated, unknown id)
    dropped_frames: int = 0  # runs of such bytes
    dropped_unknown: int = 0  # well-formed frames with an unknown message id
    ignored: int = 0  # known messages not acted on (not whitelisted)
    tx_messages: int = 0
    tx_errors: int = 0
    signed: int = 0  # accepted with a good signature
    unsigned: int = 0  # accepted unsigned (signing permissive, or an allowed message)
    rejected_unsigned: int = 0  # unsigned where signing is required
    rejected_signature: int = 0  # wrong key or altered frame
    rejected_replay: int = 0  # a signed frame's timestamp not newer than its stream's last
    rejected_peer: int = 0  # connections refused: another user's process (the same-host simulator link)
    peer_kept: int = 0  # valid frames from another address while the peer was alive (not re-aimed)
    seq_lost: int = 0  # gaps in the senders' sequence numbers (frames lost on the way), as MAVProxy counts
    last_rx_wall_s: float = 0.0
    per_type: dict[str, int] = field(default_factory=dict)

    @property
    def dropped(self) -> int:
        """Frames that never reached the application: unparseable runs and unknown ids."""
        return self.dropped_frames + self.dropped_unknown

    @property
    def rejected_signing(self) -> int:
        """Frames rejected by the signing checks."""
        return self.rejected_unsigned + self.rejected_signature + self.rejected_replay


class Transport:
    """Byte transport; subclasses implement ``recv_all`` (non-blocking) and ``send``.

    ``recv_chunks`` returns what arrived as ``(bytes, sender)`` pieces: one per datagram on UDP
    (frames never span datagrams there), one piece with sender ``None`` on streams.
    """

    datagram = False

    def fileno(self) -> int:
        raise NotImplementedError

    def recv_all(self) -> bytes:
        raise NotImplementedError

    def recv_chunks(self) -> list[tuple[bytes, tuple | None]]:
        data = self.recv_all()
        return [(data, None)] if data else []

    def learn_peer(self, addr) -> None:
        """Reply to ``addr`` from now on (UDP listeners only)."""

    def local_port(self) -> int | None:
        """The bound local port (sockets), for URLs given with port 0."""
        return None

    def send(self, data: bytes) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    @property
    def connected(self) -> bool:
        return True


class _Udp(Transport):
    datagram = True

    def __init__(self, bind: tuple[str, int] | None, remote: tuple[str, int] | None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        try:
            self.sock.bind(bind or (_local_host(remote), 0))
        except OSError as exc:
            self.sock.close()
            raise PortError(f"cannot bind UDP {bind[0]}:{bind[1]}: {exc.strerror}") from None
        self.sock.setblocking(False)
        self.remote = remote
        self._fixed_remote = remote is not None

    def fileno(self) -> int:
        return self.sock.fileno()

    def recv_chunks(self) -> list[tuple[bytes, tuple | None]]:
        chunks = []
        while True:
            try:
                data, addr = self.sock.recvfrom(_READ_CHUNK)
            except BlockingIOError:
                break
            except ConnectionRefusedError:  # ICMP from an earlier send to a closed port
                continue
            chunks.append((data, addr))
        return chunks

    def recv_all(self) -> bytes:
        return b"".join(data for data, _ in self.recv_chunks())

    def learn_peer(self, addr) -> None:
        if not self._fixed_remote:
            self.remote = addr

    def local_port(self) -> int:
        return self.sock.getsockname()[1]

    def send(self, data: bytes) -> None:
        if self.remote is None:
            return  # udpin before the first datagram: nobody to talk to yet
        try:
            self.sock.sendto(data, self.remote)
        except (ConnectionRefusedError, BlockingIOError):
            pass  # nobody listening (yet), or a full buffer: UDP semantics

    def close(self) -> None:
        self.sock.close()

    @property
    def connected(self) -> bool:
        return self.remote is not None


class _TcpServer(Transport):
    def __init__(self, bind: tuple[str, int]):
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.server.bind(bind)
        except OSError as exc:
            self.server.close()
            raise PortError(f"cannot bind TCP {bind[0]}:{bind[1]}: {exc.strerror}") from None
        self.server.listen(1)
        self.server.setblocking(False)
        self.conn: socket.socket | None = None

    def fileno(self) -> int:
        return (self.conn or self.server).fileno()

    def local_port(self) -> int:
        return self.server.getsockname()[1]

    def _accept(self) -> None:
        try:
            conn, _ = self.server.accept()
        except BlockingIOError:
            return
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.setblocking(False)
        self.conn = conn

    def recv_all(self) -> bytes:
        if self.conn is None:
            self._accept()
            return b""
        chunks = []
        while True:
            try:
                data = self.conn.recv(_READ_CHUNK)
            except BlockingIOError:
                break
            except OSError:
                data = b""  # reset by the peer
            if not data:  # peer closed: wait for the next one
                self.conn.close()
                self.conn = None
                break
            chunks.append(data)
            if len(data) < _READ_CHUNK:  # drained: no second recv only to hear EAGAIN (one syscall a read)
                break
        return b"".join(chunks)

    def send(self, data: bytes) -> None:
        if self.conn is not None:
            send_all(self.conn, data)

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
        self.server.close()

    @property
    def connected(self) -> bool:
        return self.conn is not None


def send_all(sock: socket.socket, data: bytes) -> None:
    """Write all of ``data`` to a non-blocking stream (or packet) socket, waiting while its buffer is full."""
    view = memoryview(data)
    while view:
        try:
            n = sock.send(view)
        except BlockingIOError:
            select.select([], [sock], [], 1.0)
            continue
        view = view[n:]


class _TcpClient(Transport):
    def __init__(self, remote: tuple[str, int], timeout_s: float):
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.sock = socket.create_connection(remote, timeout=1.0)
                break
            except OSError as exc:
                if time.monotonic() > deadline:
                    raise PortError(f"cannot connect to TCP {remote[0]}:{remote[1]}: {exc.strerror or exc}") from None
                time.sleep(0.05)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.setblocking(False)
        self.closed = False

    def fileno(self) -> int:
        return self.sock.fileno()

    def recv_all(self) -> bytes:
        chunks = []
        while not self.closed:
            try:
                data = self.sock.recv(_READ_CHUNK)
            except BlockingIOError:
                break
            except (ConnectionResetError, OSError):
                data = b""  # reset by the peer: closed
            if not data:
                self.closed = True
                break
            chunks.append(data)
            if len(data) < _READ_CHUNK:  # drained (a later arrival makes the socket readable again)
                break
        return b"".join(chunks)

    def send(self, data: bytes) -> None:
        if not self.closed:
            try:
                send_all(self.sock, data)
            except (BrokenPipeError, ConnectionResetError):
                self.closed = True

    def close(self) -> None:
        self.sock.close()

    @property
    def connected(self) -> bool:
        return not self.closed


class _Serial(Transport):
    """A serial device, e.g. a Pixhawk's USB or TELEM2 port by id.

    A missing device, one that fails to open, or one that errors (a USB autopilot rebooting) is
    not fatal: the port logs what and where, stays disconnected (reads return nothing, writes
    are dropped) and tries to reopen the device every ``retry_s`` seconds.
    """

    def __init__(self, device: str, baud: int, retry_s: float = 1.0):
        import serial  # pyserial: only hardware links need it

        self._serial = serial
        self.device = device
        self.baud = baud
        self.retry_s = retry_s
        self.port = None
        self._next_try = 0.0
        self._reported = False
        self._open()

    def _open(self) -> None:
        now = time.monotonic()
        if now < self._next_try:
            return
        self._next_try = now + self.retry_s
        try:
            if not os.path.exists(self.device):
                raise OSError(errno.ENOENT, "no such device")
            self.port = self._serial.Serial(self.device, baudrate=self.baud, timeout=0, write_timeout=0.1)
        except (self._serial.SerialException, OSError) as exc:
            if not self._reported:
                log.warning("serial %s (%d baud): cannot open: %s; retrying every %.0f s", self.device, self.baud,
                            getattr(exc, "strerror", None) or exc, self.retry_s)
                self._reported = True
            return
        log.info("serial %s open at %d baud", self.device, self.baud)
        self._reported = False

    def _lost(self, exc: Exception) -> None:
        log.warning("serial %s: %s; reopening", self.device, exc)
        try:
            self.port.close()
        except (self._serial.SerialException, OSError):
            pass
        self.port = None
        self._next_try = time.monotonic() + self.retry_s

    def fileno(self) -> int:
        return self.port.fileno() if self.port is not None else -1

    def recv_all(self) -> bytes:
        if self.port is None:
            self._open()
            return b""
        try:
            n = self.port.in_waiting
            data = self.port.read(n) if n else b""
        except (self._serial.SerialException, OSError) as exc:
            self._lost(exc)
            return b""
        if not n and not data and self._hung_up():
            self._lost(OSError(errno.EIO, "device hung up"))
        return data

    def _hung_up(self) -> bool:
        """select() said readable but nothing is waiting: the device went away."""
        ready, _, _ = select.select([self.port.fileno()], [], [], 0)
        return bool(ready)

    def send(self, data: bytes) -> None:
        if self.port is None:
            return
        try:
            self.port.write(data)
        except self._serial.SerialTimeoutException:
            pass  # a congested link: drop, like UDP
        except (self._serial.SerialException, OSError) as exc:
            self._lost(exc)

    def close(self) -> None:
        if self.port is not None:
            self.port.close()
            self.port = None

    @property
    def connected(self) -> bool:
        return self.port is not None


def _host_port(netloc: str, url: str) -> tuple[str, int]:
    host, sep, port = netloc.rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise PortError(f"{url}: expected HOST:PORT")
    return host or "127.0.0.1", int(port)


def _local_host(remote: tuple[str, int] | None) -> str:
    """The local address to send from: loopback for a loopback peer (nothing else can reach us)."""
    if remote is not None and (remote[0] == "localhost" or remote[0].startswith("127.")):
        return "127.0.0.1"
    return "0.0.0.0"


def open_transport(url: str, connect_timeout_s: float = 10.0) -> Transport:
    """Open a transport from a URL (see the module docstring)."""
    parsed = urlparse(url)
    scheme = parsed.scheme
    if scheme == "serial":
        path, sep, baud = (parsed.netloc + parsed.path).rpartition(":")
        if not sep or not baud.isdigit():
            raise PortError(f"{url}: expected serial:///dev/...:BAUD")
        return _Serial(path, int(baud))
    if scheme not in ("udpin", "udpout", "tcpin", "tcpout"):
        raise PortError(f"{url}: unknown scheme {scheme!r} (udpin, udpout, tcpin, tcpout, serial)")
    host, port = _host_port(parsed.netloc, url)
    if scheme == "udpin":
        return _Udp((host, port), None)
    if scheme == "udpout":
        bind = parse_qs(parsed.query).get("bind")
        local = None
        if bind:
            bind_host, sep, bind_port = bind[0].rpartition(":")
            if not bind_port.isdigit() or int(bind_port) > 65535:
                raise PortError(f"{url}: bind must be PORT or HOST:PORT")
            local = (bind_host if sep and bind_host else _local_host((host, port)), int(bind_port))
        return _Udp(local, (host, port))
    if scheme == "tcpin":
        return _TcpServer((host, port))
    return _TcpClient((host, port), connect_timeout_s)


class TlogWriter:
    """Append MAVLink frames to a .tlog file (MAVProxy / MAVExplorer format)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "ab", buffering=1 << 16)

    def write(self, frame: bytes) -> None:
        self._fh.write(struct.pack(">Q", int(time.time() * 1e6)) + frame)

    def close(self) -> None:
        self._fh.close()


class CountedPort:
    """A port's counters (``stats``, :class:`PortStats`) for what others receive and send in its
    place: the vehicle's compiled lockstep loop (:meth:`MavlinkPort.handover`, the same-host link)."""

    stats: PortStats

    def received(self, n_bytes: int) -> None:
        """Count ``n_bytes`` received."""
        st = self.stats
        st.rx_bytes += n_bytes
        st.last_rx_wall_s = time.monotonic()

    def count(self, kind: str, n: int = 1) -> None:
        """Count ``n`` accepted messages of ``kind`` received."""
        st = self.stats
        st.rx_messages += n
        st.per_type[kind] = st.per_type.get(kind, 0) + n

    def sent(self, n_messages: int) -> None:
        """Count ``n_messages`` sent."""
        self.stats.tx_messages += n_messages


class MavlinkPort(CountedPort):
    """A MAVLink link with a whitelist of message types it acts on.

    Args:
        url: transport URL (see :func:`open_transport`).
        system_id, component_id: our identity on this link (for sending).
        accept: message type names delivered to the caller; ``None`` delivers every known one.
        tlog: optional :class:`TlogWriter`.
        peer_system_id: the system this link talks to: a UDP listener learns where to reply only
            from its valid frames.
        signing, key, link_id: MAVLink 2 signing mode, 32-byte key and our link id.
        unsigned_allowed: message names accepted unsigned when signing is required.
        peer_hold_s: a learnt peer is kept while its frames keep coming; another address takes
            over only after this long without a valid frame from it.
    """

    def __init__(self, url: str, system_id: int, component_id: int = 1, accept: frozenset[str] | None = None,
                 tlog: TlogWriter | None = None, transport: Transport | None = None, peer_system_id: int | None = None,
                 signing: SigningMode = "off", key: bytes | None = None, link_id: int = 0,
                 unsigned_allowed=UNSIGNED_ALLOWED, peer_hold_s: float = 2.0):
        D = load_dialect()
        self.url = url
        self.checker = SignatureChecker(signing, key, unsigned_allowed)
        self.transport = transport or open_transport(url)
        self.mav = D.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self.parser = D.MAVLink(None)
        self.parser.robust_parsing = True
        self.accept = accept
        self.tlog = tlog
        self.peer_system_id = peer_system_id
        self.peer_hold_s = peer_hold_s
        self._peer_seen_s = -float("inf")
        self.stats = PortStats()
        self._last_seq: dict[tuple[int, int], int] = {}  # per sender (system, component)
        self._header_len = D.HEADER_LEN_V1
        self._warned: dict[str, float] = {}
        self.set_signing(signing, key, link_id)

    def set_signing(self, mode: SigningMode, key: bytes | None, link_id: int | None = None) -> None:
        """Sign outgoing frames and check incoming ones with ``key`` (``mode = "off"``: neither)."""
        self.checker.set_key(mode, key)
        sig = self.mav.signing
        sig.secret_key = key if mode != "off" else None
        sig.sign_outgoing = mode != "off"
        if link_id is not None:
            sig.link_id = link_id

    @property
    def signing_mode(self) -> SigningMode:
        return self.checker.mode

    @property
    def system_id(self) -> int:
        return self.mav.srcSystem

    def fileno(self) -> int:
        return self.transport.fileno()

    @property
    def connected(self) -> bool:
        """The transport has its peer (a TCP connection, a UDP peer learnt or given, a serial device open)."""
        return self.transport.connected

    def read(self) -> list:
        """Messages received since the last call that are whitelisted (never blocks).

        A UDP listener learns where to reply only from a datagram that carried a whitelisted
        message (from ``peer_system_id`` when set), so stray datagrams cannot redirect its replies.
        """
        out = []
        for data, sender in self.transport.recv_chunks():
            valid_from_peer = self._parse(data, out)
            if self.transport.datagram:
                self._drop_partial_frame()
                if sender is not None and valid_from_peer:
                    self._learn_peer(sender)
        return out

    def parse(self, data: bytes) -> list:
        """:meth:`read`'s second half for bytes of this link's stream received by someone else (the
        vehicle's compiled lockstep loop hands back what it does not take): the whitelisted
        messages, with every check and counter of :meth:`read`."""
        out: list = []
        self._parse(data, out)
        return out

    def handover(self) -> tuple[int, tuple[int, int], int] | None:
        """What a compiled reader needs to take whole frames from this link's stream in the parser's
        place (the vehicle's lockstep loop over PX4's TCP simulator link): ``(descriptor, (system,
        component) of the one sender heard, its last sequence number)``. ``None`` when it may not:
        not a connected stream, a frame begun in the parser, a tlog to write, signing on, no sender
        or several heard. The reader gives its counts back (:class:`CountedPort`, :meth:`resume`)."""
        t = self.transport
        if (not isinstance(t, (_TcpServer, _TcpClient)) or not t.connected or self.tlog is not None
                or self.checker.mode != "off"
                or self.parser.buf_len() or len(self._last_seq) != 1):
            return None
        fd = t.fileno()
        if fd < 0:
            return None
        (sender, last), = self._last_seq.items()
        return fd, sender, last

    def send_frame(self, frame: bytes) -> None:
        """Write ``frame``, packed already with this link's next sequence number (by a compiled
        writer, or the part of its frame its send did not take), counted as :meth:`send` counts."""
        self._write([frame])

    def resume(self, sender: tuple[int, int], last_seq: int, next_seq: int) -> None:
        """Take over from a compiled reader and writer: ``sender``'s last sequence number and this
        link's next one."""
        self._last_seq[sender] = last_seq
        self.mav.seq = next_seq

    def _learn_peer(self, sender) -> None:
        """Reply to ``sender`` (it sent a valid frame from the peer): the first one, the same one, or
        another once the current peer has been silent ``peer_hold_s`` (a rebooted peer)."""
        now = time.monotonic()
        current = getattr(self.transport, "remote", None)
        if current is None or current == sender or now - self._peer_seen_s > self.peer_hold_s:
            if current is not None and current != sender:
                log.info("%s: peer moved from %s:%d to %s:%d", self.url, *current, *sender)
            self.transport.learn_peer(sender)
            self._peer_seen_s = now
        else:
            self.stats.peer_kept += 1
            self._warn("peer", f"valid frames from {sender[0]}:{sender[1]} while the peer "
                               f"{current[0]}:{current[1]} is alive: replies stay with the peer")

    def _warn(self, kind: str, text: str) -> None:
        """Log a rejection: the first of each kind, then at most one per kind every 5 s."""
        now = time.monotonic()
        if now - self._warned.get(kind, -float("inf")) >= 5.0:
            self._warned[kind] = now
            st = self.stats
            log.warning("%s: %s (so far: unsigned %d, bad signature %d, replayed %d, peer kept %d)", self.url, text,
                        st.rejected_unsigned, st.rejected_signature, st.rejected_replay, st.peer_kept)

    def _drop_partial_frame(self) -> None:
        """Discard a frame left incomplete at the end of a datagram (frames never span datagrams)."""
        p = self.parser
        left = p.buf_len()
        if left:
            self.stats.dropped_bytes += left
            self.stats.dropped_frames += 1
        # Reset the parser's buffer state (the attributes MAVLink.__init__ sets).
        p.buf = bytearray()
        p.buf_index = 0
        p.expected_length = self._header_len + 2
        p.have_prefix_error = False

    def _parse(self, data: bytes, out: list) -> bool:
        st = self.stats
        st.rx_bytes += len(data)
        st.last_rx_wall_s = time.monotonic()
        try:
            msgs = self.parser.parse_buffer(bytearray(data)) or []
        except Exception as exc:  # the parser should not raise with robust parsing; never crash
            log.warning("%s: parser error %s", self.url, exc)
            st.dropped_bytes += len(data)
            st.dropped_frames += 1
            self._drop_partial_frame()
            return False
        valid_from_peer = False
        stamp = signing_timestamp() if self.checker.mode != "off" else 0
        for m in msgs:
            kind = m.get_type()
            if kind == "BAD_DATA":
                st.dropped_bytes += len(m.get_msgbuf())
                st.dropped_frames += 1
                continue
            if kind.startswith("UNKNOWN_"):
                st.dropped_bytes += len(m.get_msgbuf())
                st.dropped_unknown += 1
                continue
            verdict = self.checker.check(bytes(m.get_msgbuf()), kind, stamp)
            if not verdict.accepted:
                setattr(st, verdict.value, getattr(st, verdict.value) + 1)
                self._warn(verdict.value, f"{verdict.value.replace('_', ' ')}: {kind} from system "
                                          f"{m.get_srcSystem()}")
                continue
            if verdict is Verdict.SIGNED:
                st.signed += 1
            elif verdict is Verdict.UNSIGNED:
                st.unsigned += 1
            src = (m.get_srcSystem(), m.get_srcComponent())
            last = self._last_seq.get(src)
            if last is not None:
                gap = (m.get_seq() - last - 1) % 256
                if gap < 128:  # larger: a duplicate, reordering or a restarted sender, not loss
                    st.seq_lost += gap
            self._last_seq[src] = m.get_seq()
            if self.accept is not None and kind not in self.accept:
                st.ignored += 1
                continue
            if self.peer_system_id is None or m.get_srcSystem() == self.peer_system_id:
                valid_from_peer = True
            st.rx_messages += 1
            st.per_type[kind] = st.per_type.get(kind, 0) + 1
            if self.tlog is not None:
                self.tlog.write(bytes(m.get_msgbuf()))
            out.append(m)
        return valid_from_peer

    def _pack(self, msg) -> bytes:
        """The frame of ``msg`` with this link's next sequence number (one counter per port, as
        pymavlink's ``send`` keeps it: stock tools count the gaps as lost frames), signed when
        signing is on (timestamp: the signing clock, strictly increasing)."""
        sig = self.mav.signing
        if sig.sign_outgoing:
            sig.timestamp = max(sig.timestamp, signing_timestamp())
        frame = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return frame

    def send(self, msg) -> None:
        self._write([self._pack(msg)])

    def send_many(self, msgs) -> None:
        """Send several messages in as few writes as the transport allows: one segment on a stream,
        datagrams of whole frames of at most :data:`MAX_DATAGRAM_BYTES` on UDP (MAVLink's UDP
        links carry several frames per datagram, as PX4 sends them; every stock parser reads them).
        Fewer writes mean fewer wake-ups of the peer: a vehicle's streams due on one tick, a
        companion's target and correction for one link."""
        frames = [self._pack(m) for m in msgs]
        if not frames:
            return
        if not self.transport.datagram:
            self._write(frames)
            return
        batch, size = [], 0
        for frame in frames:
            if batch and size + len(frame) > MAX_DATAGRAM_BYTES:
                self._write(batch)
                batch, size = [], 0
            batch.append(frame)
            size += len(frame)
        self._write(batch)

    def _write(self, frames: list[bytes]) -> None:
        """One transport write of ``frames``; a failure is counted (UDP semantics: not retried)."""
        try:
            self.transport.send(frames[0] if len(frames) == 1 else b"".join(frames))
        except OSError as exc:
            self.stats.tx_errors += 1
            if exc.errno not in (errno.ENOBUFS, errno.EAGAIN):
                log.debug("%s: send failed: %s", self.url, exc)
            return
        self.stats.tx_messages += len(frames)
        if self.tlog is not None:
            for frame in frames:
                self.tlog.write(frame)

    def close(self) -> None:
        self.transport.close()
        if self.tlog is not None:
            self.tlog.close()


def wait_readable(ports, timeout_s: float) -> list:
    """The ports (objects with ``fileno``) that have data, waiting at most ``timeout_s``.

    Ports without a file descriptor (``fileno() < 0``: a serial device waiting to reappear) are
    always returned, so that reading them gives them their chance to reopen.
    """
    live: dict[int, list] = {}  # descriptor -> its ports (each port's fileno asked once: a hot loop's cost)
    idle = []
    for p in ports:
        fd = p.fileno()
        if fd >= 0:
            live.setdefault(fd, []).append(p)
        else:
            idle.append(p)
    if not live:
        time.sleep(max(timeout_s, 0.0))
        return idle
    ready, _, _ = select.select(list(live), [], [], max(timeout_s, 0.0))
    return [p for fd in ready for p in live[fd]] + idle

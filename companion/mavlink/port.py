"""MAVLink ports: a transport plus parsing, accounting, signing checks and a .tlog.

A :class:`MavlinkPort` owns its transport (:mod:`companion.mavlink.transport`; opened from a URL
by :func:`companion.mavlink.urls.open_transport`: UDP, TCP or serial), so it sees every byte:
frames that fail to parse (bad CRC, truncated, random bytes) are counted as dropped bytes,
frames with a message id the dialect does not know are counted as unknown, and well-formed
messages not in the port's whitelist are counted as ignored; only whitelisted messages reach the
caller. Reads never block (the caller waits with
:func:`~companion.mavlink.transport.wait_readable` or its own ``select``). What the port sends
and accepts can go to a :class:`~companion.mavlink.tlog.TlogWriter`.

MAVLink 2 signing (:mod:`companion.mavlink.signing`) is per port: with a mode other than
``off`` every frame sent is signed, and incoming frames are checked before anything else sees
them; rejected frames (unsigned where signing is required, a bad signature, a replay) are
counted in :class:`PortStats` and logged (the first of each kind, then at most every 5 s).

Time: a port reads the clocks it is given (the system's by default): ``clock``, monotonic
seconds, for its receive stamps, its peer hold and its log rate limits (and a serial transport's
reopen retries); ``wall_clock``, UNIX seconds, for signing timestamps.
"""

from __future__ import annotations

import errno
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from .dialect import load_dialect
from .signing import UNSIGNED_ALLOWED, SignatureChecker, SigningMode, Verdict, signing_timestamp
from .sockets import TcpClient, TcpServer
from .tlog import TlogWriter
from .transport import Transport
from .urls import open_transport

__all__ = ["PortStats", "CountedPort", "MavlinkPort", "MAX_DATAGRAM_BYTES"]

log = logging.getLogger(__name__)

# The most MAVLink bytes one UDP datagram carries when several frames are sent together: an
# Ethernet MTU (1500) less the IPv4 and UDP headers, so a batch is never fragmented on a real link.
MAX_DATAGRAM_BYTES = 1472


@dataclass
class PortStats:
    """A port's counters since it opened (``last_rx_wall_s``: its clock at the last bytes received)."""

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


class CountedPort:
    """A port's counters (``stats``, :class:`PortStats`) for what others receive and send in its
    place: the vehicle's compiled lockstep loop (:meth:`MavlinkPort.handover`, the same-host link).
    ``clock`` (monotonic seconds) stamps what is received (``last_rx_wall_s``)."""

    stats: PortStats
    clock: Callable[[], float] = staticmethod(time.monotonic)

    def received(self, n_bytes: int) -> None:
        """Count ``n_bytes`` received."""
        st = self.stats
        st.rx_bytes += n_bytes
        st.last_rx_wall_s = self.clock()

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
        url: transport URL (see :func:`~companion.mavlink.urls.open_transport`).
        system_id, component_id: our identity on this link (for sending).
        accept: message type names delivered to the caller; ``None`` delivers every known one.
        tlog: optional :class:`~companion.mavlink.tlog.TlogWriter`.
        transport: an open transport to use instead of opening ``url``.
        peer_system_id: the system this link talks to: a UDP listener learns where to reply only
            from its valid frames.
        signing, key, link_id: MAVLink 2 signing mode, 32-byte key and our link id.
        unsigned_allowed: message names accepted unsigned when signing is required.
        peer_hold_s: a learnt peer is kept while its frames keep coming; another address takes
            over only after this long without a valid frame from it.
        clock: monotonic seconds: receive stamps, the peer hold, log rate limits (and a serial
            transport's reopen retries).
        wall_clock: UNIX seconds: the signing timestamps of frames sent and checked.
    """

    def __init__(self, url: str, system_id: int, component_id: int = 1, accept: frozenset[str] | None = None,
                 tlog: TlogWriter | None = None, transport: Transport | None = None, peer_system_id: int | None = None,
                 signing: SigningMode = "off", key: bytes | None = None, link_id: int = 0,
                 unsigned_allowed=UNSIGNED_ALLOWED, peer_hold_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, wall_clock: Callable[[], float] = time.time):
        D = load_dialect()
        self.url = url
        self.clock = clock
        self.wall_clock = wall_clock
        self.checker = SignatureChecker(signing, key, unsigned_allowed)
        self.transport = transport or open_transport(url, clock=clock)
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
        if (not isinstance(t, (TcpServer, TcpClient)) or not t.connected or self.tlog is not None
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
        now = self.clock()
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
        now = self.clock()
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
        st.last_rx_wall_s = self.clock()
        try:
            msgs = self.parser.parse_buffer(bytearray(data)) or []
        except Exception as exc:  # the parser should not raise with robust parsing; never crash
            log.warning("%s: parser error %s", self.url, exc)
            st.dropped_bytes += len(data)
            st.dropped_frames += 1
            self._drop_partial_frame()
            return False
        valid_from_peer = False
        stamp = signing_timestamp(self.wall_clock()) if self.checker.mode != "off" else 0
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
            sig.timestamp = max(sig.timestamp, signing_timestamp(self.wall_clock()))
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

    def _write(self, frames: list[bytes], n_messages: int | None = None) -> None:
        """One transport write of ``frames`` (``n_messages`` messages: one per frame unless given);
        a failure is counted (UDP semantics: not retried)."""
        try:
            self.transport.send(frames[0] if len(frames) == 1 else b"".join(frames))
        except OSError as exc:
            self.stats.tx_errors += 1
            if exc.errno not in (errno.ENOBUFS, errno.EAGAIN):
                log.debug("%s: send failed: %s", self.url, exc)
            return
        self.stats.tx_messages += len(frames) if n_messages is None else n_messages
        if self.tlog is not None:
            for frame in frames:
                self.tlog.write(frame)

    def close(self) -> None:
        self.transport.close()
        if self.tlog is not None:
            self.tlog.close()

"""UDP and TCP transports (IPv4, non-blocking) for MAVLink ports.

* :class:`UdpTransport`: a bound socket; with no fixed remote (``udpin``) it replies to the peer
  its port learns (:meth:`~UdpTransport.learn_peer`), with one (``udpout``) it always sends there;
* :class:`TcpServer`: listens, and the first client to connect is the peer (a client that goes
  away makes room for the next);
* :class:`TcpClient`: connects, retrying while the server starts.
"""

from __future__ import annotations

import socket
import time

from .transport import READ_CHUNK, PortError, Transport, send_all

__all__ = ["UdpTransport", "TcpServer", "TcpClient", "local_host"]


def local_host(remote: tuple[str, int] | None) -> str:
    """The local address to send from: loopback for a loopback peer (nothing else can reach us)."""
    if remote is not None and (remote[0] == "localhost" or remote[0].startswith("127.")):
        return "127.0.0.1"
    return "0.0.0.0"


class UdpTransport(Transport):
    """A UDP socket bound to ``bind`` (default: an ephemeral port on :func:`local_host` of
    ``remote``), sending to ``remote`` (``None``: to the peer learnt, none before)."""

    datagram = True

    def __init__(self, bind: tuple[str, int] | None, remote: tuple[str, int] | None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        try:
            self.sock.bind(bind or (local_host(remote), 0))
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
                data, addr = self.sock.recvfrom(READ_CHUNK)
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


class TcpServer(Transport):
    """A listening TCP socket on ``bind``; its first client is the peer (``conn``)."""

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
                data = self.conn.recv(READ_CHUNK)
            except BlockingIOError:
                break
            except OSError:
                data = b""  # reset by the peer
            if not data:  # peer closed: wait for the next one
                self.conn.close()
                self.conn = None
                break
            chunks.append(data)
            if len(data) < READ_CHUNK:  # drained: no second recv only to hear EAGAIN (one syscall a read)
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


class TcpClient(Transport):
    """A TCP connection to ``remote``, retried for ``timeout_s`` of real time while the server
    starts (it waits on the network, so it reads the system's monotonic clock)."""

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
                data = self.sock.recv(READ_CHUNK)
            except BlockingIOError:
                break
            except (ConnectionResetError, OSError):
                data = b""  # reset by the peer: closed
            if not data:
                self.closed = True
                break
            chunks.append(data)
            if len(data) < READ_CHUNK:  # drained (a later arrival makes the socket readable again)
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

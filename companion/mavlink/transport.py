"""Byte transports under a MAVLink port: the interface, its error, and waiting on several.

A :class:`Transport` moves bytes and nothing else; :class:`~companion.mavlink.port.MavlinkPort`
parses and counts them. The concrete transports are in :mod:`companion.mavlink.sockets` (UDP,
TCP) and :mod:`companion.mavlink.serialport`; :func:`companion.mavlink.urls.open_transport` opens
one from a URL.
"""

from __future__ import annotations

import select
import socket
import time

__all__ = ["PortError", "Transport", "send_all", "wait_readable", "READ_CHUNK"]

#: The most bytes one read asks a socket or device for.
READ_CHUNK = 65536


class PortError(ValueError):
    """A port URL that cannot be opened (bad syntax, missing device, port in use)."""


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

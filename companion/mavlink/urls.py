"""Transport URLs: parse one and open its transport.

The syntax is the one MAVSDK / MAVProxy users expect; an empty HOST means 127.0.0.1, so nothing
is reachable from off the machine unless a URL names an interface or 0.0.0.0:

* ``udpin://HOST:PORT``: bind and listen; replies go to the sender of the last valid frame
  from the expected system (see :class:`~companion.mavlink.port.MavlinkPort`);
* ``udpout://HOST:PORT`` (optionally ``?bind=PORT`` or ``?bind=HOST:PORT``): send to
  ``HOST:PORT`` from a local port (fixed with ``bind``, like PX4 SITL's local ports 14580+i;
  the local address is 127.0.0.1 when HOST is a loopback address, else 0.0.0.0);
* ``tcpin://HOST:PORT`` (a server: the first client is the peer) / ``tcpout://HOST:PORT``;
* ``serial:///dev/serial/by-id/...:BAUD``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from urllib.parse import parse_qs, urlparse

from .serialport import SerialTransport
from .sockets import TcpClient, TcpServer, UdpTransport, local_host
from .transport import PortError, Transport

__all__ = ["open_transport"]


def _host_port(netloc: str, url: str) -> tuple[str, int]:
    host, sep, port = netloc.rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise PortError(f"{url}: expected HOST:PORT")
    return host or "127.0.0.1", int(port)


def open_transport(url: str, connect_timeout_s: float = 10.0,
                   clock: Callable[[], float] = time.monotonic) -> Transport:
    """Open a transport from a URL (see the module docstring). ``connect_timeout_s``: how long a
    TCP client retries; ``clock`` (monotonic seconds): when a serial device is retried."""
    parsed = urlparse(url)
    scheme = parsed.scheme
    if scheme == "serial":
        path, sep, baud = (parsed.netloc + parsed.path).rpartition(":")
        if not sep or not baud.isdigit():
            raise PortError(f"{url}: expected serial:///dev/...:BAUD")
        return SerialTransport(path, int(baud), clock=clock)
    if scheme not in ("udpin", "udpout", "tcpin", "tcpout"):
        raise PortError(f"{url}: unknown scheme {scheme!r} (udpin, udpout, tcpin, tcpout, serial)")
    host, port = _host_port(parsed.netloc, url)
    if scheme == "udpin":
        return UdpTransport((host, port), None)
    if scheme == "udpout":
        bind = parse_qs(parsed.query).get("bind")
        local = None
        if bind:
            bind_host, sep, bind_port = bind[0].rpartition(":")
            if not bind_port.isdigit() or int(bind_port) > 65535:
                raise PortError(f"{url}: bind must be PORT or HOST:PORT")
            local = (bind_host if sep and bind_host else local_host((host, port)), int(bind_port))
        return UdpTransport(local, (host, port))
    if scheme == "tcpin":
        return TcpServer((host, port))
    return TcpClient((host, port), connect_timeout_s)

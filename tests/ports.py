"""Ports for tests on loopback."""

import socket


def free_ports(k: int, udp: bool = False) -> list[int]:
    """``k`` distinct ports the kernel just handed out on 127.0.0.1 (free when this returns)."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM if udp else socket.SOCK_STREAM) for _ in range(k)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()

"""Ports (and processes) for tests on loopback."""

import socket
from pathlib import Path


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


def children_of(pid: int) -> list[int]:
    """The pids whose parent is ``pid`` (from /proc: a test's processes left behind)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:  # the field after the state is the ppid
                out.append(int(entry.name))
    return out

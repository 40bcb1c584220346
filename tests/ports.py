"""Ports (and processes) for tests on loopback, and the PX4-style ports of a test's fleet."""

from __future__ import annotations

import os
import socket
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from sitl.fleet.lease import hold_instances


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


def udp_free(port: int) -> bool:
    """Whether UDP ``port`` can be bound on every interface now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def tcp_free(port: int) -> bool:
    """Whether TCP ``port`` can be bound on 127.0.0.1 now (a socket in TIME_WAIT does not count)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


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


#: PX4 SITL's layout has room for 40 instances (companion ports 14540-14579); a test's fleet takes
#: one of these slots of 20 instance offsets, so two fleets run side by side on one host
SLOT_WIDTH = 20
N_SLOTS = 2


@dataclass(frozen=True)
class FleetPorts:
    """The ports of a fleet launched with instance offset ``k`` (sitl.fleet.layout): link ``i``
    (0-based) is PX4 SITL instance k + i; ``gcs_port``: where its vehicles send their ground-station
    traffic (a port of this test's own, free to listen on)."""

    k: int
    gcs_port: int

    def shifted(self, extra: int) -> FleetPorts:
        """The same slot's fleet at instance offset ``k + extra``."""
        assert 0 <= extra and (self.k % SLOT_WIDTH) + extra < SLOT_WIDTH
        return FleetPorts(self.k + extra, self.gcs_port)

    @property
    def launch_kwargs(self) -> dict:
        """``launch``'s arguments for these ports."""
        return {"instance_offset": self.k, "gcs_port": self.gcs_port}

    @property
    def cli_args(self) -> list[str]:
        """``python -m sitl launch``'s options for these ports."""
        return ["--instance-offset", str(self.k), "--gcs-port", str(self.gcs_port)]

    def sim(self, i: int) -> int:
        """Link ``i``'s simulator TCP port."""
        return 4560 + self.k + i

    def companion(self, i: int) -> int:
        """The companion's UDP port for link ``i`` (PX4's onboard port)."""
        return 14540 + self.k + i

    def vehicle(self, i: int) -> int:
        """Link ``i``'s own onboard UDP port."""
        return 14580 + self.k + i

    def gcs_from(self, i: int) -> int:
        """The UDP port link ``i`` sends its ground-station traffic from."""
        return 18570 + self.k + i

    def wire(self, i: int) -> tuple[int, int]:
        """The impaired wire's ports for link ``i``: the vehicle's side, the companion's side."""
        return 15540 + self.k + i, 15580 + self.k + i

    def zenoh(self, g: int, base_port: int = 7460) -> int:
        """Group ``g``'s companion Zenoh port (the default base port moved by the offset)."""
        return base_port + self.k + g

    def unreleased(self, n: int) -> list[str]:
        """Those of the first ``n`` links' ports still bound (empty once the fleet has let go)."""
        out = [f"TCP {self.sim(i)}" for i in range(n) if not tcp_free(self.sim(i))]
        return out + [f"UDP {p}" for i in range(n) for p in (self.companion(i), self.vehicle(i), self.gcs_from(i))
                      if not udp_free(p)]


def assert_ports_released(ports: FleetPorts, n: int) -> None:
    """Every port of the first ``n`` links of the fleet on ``ports`` is free again."""
    assert not ports.unreleased(n), f"still bound: {ports.unreleased(n)}"


@contextmanager
def fleet_slot(preferred: int = 0, timeout_s: float = 1800.0) -> Iterator[int]:
    """Hold one of the host's fleet slots (its instances' lock files, as a campaign's fleets lease
    theirs: :func:`sitl.fleet.lease.hold_instances`; so pytest-xdist's workers, a second test run
    and a campaign on this host each get their own): yields its first instance offset. Tries
    ``preferred`` first, then the others, until one is free or ``timeout_s`` passed."""
    order = [(preferred + j) % N_SLOTS for j in range(N_SLOTS)]
    deadline = time.monotonic() + timeout_s
    while True:
        for slot in order:
            with hold_instances(slot * SLOT_WIDTH, SLOT_WIDTH) as held:
                if held:
                    yield slot * SLOT_WIDTH
                    return
        assert time.monotonic() < deadline, f"no fleet slot free in {timeout_s:.0f} s"
        time.sleep(0.2)


def worker_index() -> int:
    """pytest-xdist's worker number (``gw3``: 3); 0 without xdist."""
    name = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    return int(name[2:]) if name[2:].isdigit() else 0

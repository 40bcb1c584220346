"""An impaired UDP wire between a vehicle and its companion (``[faults.mavlink]``, fleet mode).

    python -m sitl.fleet.wire --pair VEHICLE_SIDE:COMPANION_PORT:LOCAL_PORT [--pair ...]
        --loss P [--delay-ms D] [--jitter-ms J] [--seed S] [--stats FILE] [--sim-time FILE]

For each pair the proxy listens on UDP ``VEHICLE_SIDE`` (where the vehicle sends its onboard
traffic), forwards every datagram to the companion's UDP ``COMPANION_PORT`` from its own port
``LOCAL_PORT``, and sends what the companion answers there back to the vehicle (at the address
the vehicle last sent from). Each datagram is dropped with probability ``P`` and otherwise held
for ``D`` plus a uniform ``[0, J]`` milliseconds (so jitter can reorder datagrams, as on a real
network): simulated milliseconds with ``--sim-time`` (the fleet's lockstep time, :mod:`.sim_time`,
which the launcher passes, so that the delay the vehicles and the companion see does not grow with
the pace of an unpaced fleet), else wall-clock ones. Everything stays on loopback. Counters per pair and direction (forwarded,
dropped) go to ``--stats`` as JSON every second and at exit (SIGTERM / Ctrl-C).

The impairment itself (:class:`Impairment`) is pure: it takes the random generator and the time.
"""

from __future__ import annotations

import argparse
import heapq
import json
import logging
import selectors
import signal
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .sim_time import SimTimeClock

__all__ = ["SIM_POLL_S", "Impairment", "WirePair", "WireProxy", "main"]

log = logging.getLogger(__name__)
HOST = "127.0.0.1"
#: On simulated time, the longest wall-clock wait between looks at the held datagrams [s]: an
#: unpaced fleet at a few times real time releases them within a few simulated ms of their time.
SIM_POLL_S = 0.0005


@dataclass
class Impairment:
    """Loss and delay of one direction of a wire; ``decide`` returns the release time or ``None``."""

    loss: float
    delay_s: float
    jitter_s: float
    rng: np.random.Generator
    forwarded: int = 0
    dropped: int = 0

    def decide(self, now_s: float) -> float | None:
        if self.loss > 0 and self.rng.random() < self.loss:
            self.dropped += 1
            return None
        self.forwarded += 1
        return now_s + self.delay_s + (self.rng.random() * self.jitter_s if self.jitter_s > 0 else 0.0)


@dataclass
class WirePair:
    """One vehicle-companion wire: its sockets and both directions' impairments."""

    vehicle_side: int
    companion_port: int
    local_port: int
    up: Impairment  # vehicle -> companion
    down: Impairment  # companion -> vehicle
    vehicle_addr: tuple | None = None
    sockets: list = field(default_factory=list)


class WireProxy:
    """The wire's pairs and their held datagrams. ``clock`` [s] times the delays; ``poll_s``: the
    longest wait between looks at a held datagram (``None``: the clock is the wall clock, so the
    wait until the next release is known)."""

    def __init__(self, pairs: list[tuple[int, int, int]], loss: float, delay_ms: float, jitter_ms: float,
                 seed: int = 0, clock=time.monotonic, poll_s: float | None = None):
        self.clock = clock
        self.poll_s = poll_s
        rng = np.random.default_rng(seed)
        self.pairs: list[WirePair] = []
        self.sel = selectors.DefaultSelector()
        self._queue: list = []  # (release time, order, socket, data, address)
        self._order = 0
        try:
            for vside, cport, lport in pairs:
                mk = lambda: Impairment(loss, delay_ms * 1e-3, jitter_ms * 1e-3, np.random.default_rng(rng.integers(2**63)))
                pair = WirePair(vside, cport, lport, mk(), mk())
                for port, role in ((vside, "vehicle"), (lport, "companion")):
                    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
                    s.bind((HOST, port))
                    s.setblocking(False)
                    pair.sockets.append(s)
                    self.sel.register(s, selectors.EVENT_READ, (pair, role))
                self.pairs.append(pair)
        except OSError:
            self.close()
            raise
        self._stop = False

    def _on_readable(self, pair: WirePair, role: str, now_s: float) -> None:
        vsock, csock = pair.sockets
        sock = vsock if role == "vehicle" else csock
        while True:
            try:
                data, addr = sock.recvfrom(65536)
            except (BlockingIOError, ConnectionRefusedError):
                return
            if role == "vehicle":
                pair.vehicle_addr = addr
                release, out, dest = pair.up.decide(now_s), csock, (HOST, pair.companion_port)
            else:
                if pair.vehicle_addr is None:
                    continue  # nobody to answer yet
                release, out, dest = pair.down.decide(now_s), vsock, pair.vehicle_addr
            if release is not None:
                self._order += 1
                heapq.heappush(self._queue, (release, self._order, out, data, dest))

    def _release(self, now_s: float) -> None:
        while self._queue and self._queue[0][0] <= now_s:
            _, _, sock, data, dest = heapq.heappop(self._queue)
            try:
                sock.sendto(data, dest)
            except (ConnectionRefusedError, BlockingIOError):
                pass

    def stats(self) -> dict:
        return {f"{p.vehicle_side}<->{p.companion_port}": {
            "vehicle_to_companion": {"forwarded": p.up.forwarded, "dropped": p.up.dropped},
            "companion_to_vehicle": {"forwarded": p.down.forwarded, "dropped": p.down.dropped}} for p in self.pairs}

    def stop(self, *_args) -> None:
        self._stop = True

    def run(self, stats_path: Path | None = None) -> None:
        next_stats = 0.0
        while not self._stop:
            now = self.clock()
            timeout = 0.2 if not self._queue else max(self._queue[0][0] - now, 0.0)
            if self._queue and self.poll_s is not None:
                timeout = min(timeout, self.poll_s)
            for key, _ in self.sel.select(min(timeout, 0.2)):
                pair, role = key.data
                self._on_readable(pair, role, self.clock())
            now = self.clock()
            self._release(now)
            if stats_path is not None and now >= next_stats:
                next_stats = now + 1.0
                _write_json(stats_path, self.stats())
        if stats_path is not None:
            _write_json(stats_path, self.stats())

    def close(self) -> None:
        for p in self.pairs:
            for s in p.sockets:
                self.sel.unregister(s)
                s.close()
        self.sel.close()


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    tmp.replace(path)


def _pair(text: str) -> tuple[int, int, int]:
    try:
        a, b, c = (int(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected VEHICLE_SIDE:COMPANION_PORT:LOCAL_PORT") from None
    if not all(1 <= x <= 65535 for x in (a, b, c)):
        raise argparse.ArgumentTypeError(f"{text!r}: ports are 1..65535")
    return a, b, c


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m sitl.fleet.wire", description=__doc__.split("\n\n")[0])
    p.add_argument("--pair", type=_pair, action="append", required=True, metavar="V:C:L",
                   help="listen for the vehicle on UDP V, forward to the companion's UDP C from local UDP L")
    p.add_argument("--loss", type=float, default=0.0, metavar="P", help="drop probability per datagram, [0, 1)")
    p.add_argument("--delay-ms", type=float, default=0.0, metavar="D", help="fixed delay [ms]")
    p.add_argument("--jitter-ms", type=float, default=0.0, metavar="J", help="extra uniform delay up to J [ms]")
    p.add_argument("--seed", type=int, default=0, help="random seed of the losses and delays")
    p.add_argument("--stats", metavar="FILE", help="counters as JSON (every second and at exit)")
    p.add_argument("--sim-time", metavar="FILE",
                   help="time the delays on the simulated time in FILE (written by the fleet launcher); "
                        "default: wall-clock time")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s wire %(levelname)s %(message)s")
    if not 0.0 <= args.loss < 1.0 or args.delay_ms < 0 or args.jitter_ms < 0:
        print("error: --loss must be in [0, 1), --delay-ms and --jitter-ms >= 0", file=sys.stderr)
        return 2
    clock, poll_s = time.monotonic, None
    if args.sim_time:
        clock, poll_s = SimTimeClock(Path(args.sim_time)), SIM_POLL_S
    try:
        proxy = WireProxy(args.pair, args.loss, args.delay_ms, args.jitter_ms, args.seed, clock, poll_s)
    except OSError as exc:
        print(f"error: cannot bind: {exc.strerror}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, proxy.stop)
    signal.signal(signal.SIGINT, proxy.stop)
    log.info("wire up: %d pair(s), loss %.2f, delay %.1f ms + jitter %.1f ms (%s)", len(proxy.pairs), args.loss,
             args.delay_ms, args.jitter_ms, "simulated time" if args.sim_time else "wall-clock time")
    try:
        proxy.run(Path(args.stats) if args.stats else None)
    finally:
        proxy.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())

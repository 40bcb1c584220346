"""The fleet's processes and the host around them: starting, checking and stopping the vehicles,
companions and helpers; Linux's SCHED_BATCH for an unpaced fleet; which ports and UNIX sockets
listen (from /proc/net), to know when a process is ready.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import subprocess
import threading
import time
from contextlib import contextmanager
from pathlib import Path

from .layout import FleetError

__all__ = ["Processes", "STOP_GRACE_S", "STOP_GRACE_PER_FLIGHT_S", "STARTUP_TIMEOUT_S", "enter_batch_scheduling", "restore_scheduling",
           "bound_ports", "listening_unix_paths", "wait_udp_listening", "last_error",
           "check_ports_free", "interrupted_once"]

log = logging.getLogger(__name__)

STOP_GRACE_S = 10.0
#: ... and this much more per simulated second flown: a long flight's processes have long logs to
#: write at the end (a companion's step log and its MCAP: a minute for an hour's flight)
STOP_GRACE_PER_FLIGHT_S = 1.0 / 60.0
STARTUP_TIMEOUT_S = 30.0


def die_with_parent() -> None:
    """In a child before its exec (Linux): SIGTERM when the launcher dies (PR_SET_PDEATHSIG)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


@contextmanager
def interrupted_once():
    """Within the block, the first Ctrl-C (SIGINT) or SIGTERM raises :class:`KeyboardInterrupt`;
    a later one, or any once the block has called the function it yields (the flight is over), is
    logged and ignored. So the fleet's orderly stop and its metrics are not cut short: a key
    pressed twice, or ``timeout``, which signals the process and then its group, would otherwise
    end the run without them (the stop's own grace times bound how long it takes). Outside the
    main thread (where signals are not delivered) it changes nothing."""
    stopping: list[bool] = []
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return

    def on_signal(signum, _frame):
        if not stopping:
            stopping.append(True)
            raise KeyboardInterrupt
        log.warning("%s ignored: the fleet is stopping and its metrics are being written",
                    signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield lambda: stopping.append(True)
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def enter_batch_scheduling() -> int | None:
    """Put the calling thread under Linux's SCHED_BATCH, and so every process it starts from now
    (the policy is inherited across fork and exec); returns the policy to restore
    (:func:`restore_scheduling`), or ``None`` where SCHED_BATCH is missing (not Linux) or refused.

    An unpaced fleet is a throughput job: each tick the harness wakes seven vehicles, they wake
    it and their companions, and under the default policy every woken process preempts the one
    that woke it. SCHED_BATCH keeps the same CPU shares (nice values) but a woken process waits
    for the running one to block or use up its slice instead of preempting it (sched(7)), which
    spares the context switches and the caches they cost."""
    policy = getattr(os, "SCHED_BATCH", None)
    if policy is None:
        return None
    try:
        before = os.sched_getscheduler(0)
        os.sched_setscheduler(0, policy, os.sched_param(0))
    except OSError as exc:
        log.info("SCHED_BATCH refused (%s): the default scheduling policy stays", exc)
        return None
    return before


def restore_scheduling(before: int | None) -> None:
    if before is not None:
        try:
            os.sched_setscheduler(0, before, os.sched_param(0))
        except OSError as exc:  # (back to SCHED_OTHER is allowed unprivileged)
            log.warning("could not restore the scheduling policy: %s", exc)


class Processes:
    """The fleet's processes: started in their own sessions (a Ctrl-C reaches the launcher only),
    each dying with the launcher, checked for exits, killed on purpose for a scripted fault, and
    stopped together (SIGTERM, then SIGKILL after :data:`STOP_GRACE_S`)."""

    def __init__(self):
        self.procs: list[tuple[str, subprocess.Popen]] = []
        self.logs: dict[str, Path] = {}  # name -> its console log (the newest process of that name)
        self.killed: set[str] = set()
        self._next_check_s = -float("inf")

    def start(self, name: str, argv: list[str], log_path: Path, stdin_pipe: bool = False,
              env: dict | None = None) -> None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(log_path, "wb")
        # Own session: a Ctrl-C in the terminal reaches the launcher only, which stops the fleet in order.
        proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, preexec_fn=die_with_parent,
                                start_new_session=True, stdin=subprocess.PIPE if stdin_pipe else subprocess.DEVNULL,
                                env=env)
        fh.close()
        self.procs.append((name, proc))
        self.logs[name] = log_path

    def release(self, name: str) -> None:
        """Start a process waiting in ``--standby`` (one line on its stdin)."""
        for pname, proc in self.procs:
            if pname == name and proc.stdin is not None:
                proc.stdin.write(b"start\n")
                proc.stdin.flush()

    def kill(self, name: str) -> None:
        """SIGKILL a process on purpose (a scripted fault): it is no longer checked."""
        for pname, proc in self.procs:
            if pname == name and proc.poll() is None:
                proc.kill()
                proc.wait()
        self.killed.add(name)

    def check(self, every_s: float = 0.0) -> None:
        """:class:`FleetError` if a process exited (not one killed on purpose); with ``every_s``, at
        most once per that much wall time (the lockstep calls it every tick: ten waitpid calls)."""
        if every_s > 0.0:
            now = time.monotonic()
            if now < self._next_check_s:
                return
            self._next_check_s = now + every_s
        for name, proc in self.procs:
            if name not in self.killed and proc.poll() is not None:
                path = self.logs.get(name)
                words = last_error(path) if path is not None else None
                raise FleetError(f"{name} exited with code {proc.returncode}" + (f": {words}" if words else "")
                                 + (f" (console log: {path})" if path is not None else ""))

    def stop(self, flown_s: float = 0.0, first: tuple[str, ...] = ()) -> None:
        """SIGTERM to every process, SIGKILL to those still up :data:`STOP_GRACE_S` later, plus
        :data:`STOP_GRACE_PER_FLIGHT_S` per simulated second ``flown_s``. The processes named in
        ``first`` are stopped (and waited for) before the others: what they send on their way out
        still has someone to receive it."""
        if first:
            self._stop([(n, p) for n, p in self.procs if n in first], flown_s)
        self._stop(self.procs, flown_s)

    def _stop(self, procs: list[tuple[str, subprocess.Popen]], flown_s: float) -> None:
        for _, proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        grace = STOP_GRACE_S + STOP_GRACE_PER_FLIGHT_S * max(flown_s, 0.0)
        deadline = time.monotonic() + grace
        for name, proc in procs:
            try:
                proc.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s: killing it", name, grace)
                proc.kill()
                proc.wait()


def last_error(path: Path, limit: int = 300) -> str | None:
    """What a process said last before it exited: the last line of its console log ``path`` that
    starts with ``error:`` (the CLIs' form), else its last line; ``None`` when it said nothing."""
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return None
    if not lines:
        return None
    errors = [ln for ln in lines if ln.startswith("error:")]
    return (errors[-1] if errors else lines[-1])[:limit]


def bound_ports(kind: str) -> set[int]:
    """Local ports with a bound UDP socket (``kind = "udp"``) or a listening TCP one (``"tcp"``),
    from Linux's /proc/net tables (IPv4 and IPv6)."""
    ports = set()
    for table in (f"/proc/net/{kind}", f"/proc/net/{kind}6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            cols = line.split()  # local address "0100007F:38B4", state at [3] ("0A": LISTEN)
            if kind == "udp" or cols[3] == "0A":
                ports.add(int(cols[1].rsplit(":", 1)[1], 16))
    return ports


def listening_unix_paths() -> set[str]:
    """Paths of listening UNIX sockets, from Linux's /proc/net/unix (flag 0x10000: accepting)."""
    paths = set()
    try:
        lines = Path("/proc/net/unix").read_text().splitlines()[1:]
    except OSError:
        return paths
    for line in lines:
        cols = line.split(None, 7)  # Num RefCount Protocol Flags Type St Inode [Path (may hold spaces)]
        if len(cols) >= 8 and int(cols[3], 16) & 0x10000:
            paths.add(cols[7])
    return paths


def check_ports_free(ports: dict[tuple[str, int], str]) -> None:
    """:class:`FleetError` naming the ports of ``ports`` (:func:`~.layout.fleet_ports`) that a
    process already holds (a TCP listener, a bound UDP socket): a fleet started on them would
    fail, or its harness would talk to another fleet's vehicle."""
    held = {kind: bound_ports(kind) for kind in ("tcp", "udp")}
    taken = [f"{kind.upper()} {port} ({who})" for (kind, port), who in sorted(ports.items()) if port in held[kind]]
    if taken:
        raise FleetError(f"ports in use by another process (another fleet, PX4 SITL?): {', '.join(taken[:4])}"
                         + (f" and {len(taken) - 4} more" if len(taken) > 4 else "")
                         + "; run this fleet on other ports with --instance-offset K (see --help)")


def wait_udp_listening(ports: list[int], procs: Processes, who: str = "the companion") -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while not set(ports) <= bound_ports("udp"):
        procs.check()
        if time.monotonic() > deadline:
            raise FleetError(f"{who} did not open UDP {ports} within {STARTUP_TIMEOUT_S:.0f} s")
        time.sleep(0.05)

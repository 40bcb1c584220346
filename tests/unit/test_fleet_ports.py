"""Before a fleet starts, the ports it binds are checked free; a process of the fleet that exits is
reported with what it said last (sitl.fleet.layout.fleet_ports, sitl.fleet.processes)."""

from __future__ import annotations

import socket
import sys
import time

import pytest

from sitl.fleet.layout import FleetError, fleet_ports
from sitl.fleet.processes import Processes, check_ports_free, last_error


def test_the_ports_a_fleet_binds():
    ports = fleet_ports(2, 3, tcp_sim=True, companion=True, wired=[1])
    assert ports == {
        ("tcp", 4563): "link 1's simulator link", ("tcp", 4564): "link 2's simulator link",
        ("udp", 18573): "link 1's ground-station link", ("udp", 18574): "link 2's ground-station link",
        ("udp", 14583): "link 1's onboard link", ("udp", 14584): "link 2's onboard link",
        ("udp", 14543): "the companion's port for link 1", ("udp", 14544): "the companion's port for link 2",
        ("udp", 15544): "the impaired wire of link 2", ("udp", 15584): "the impaired wire of link 2",
    }
    # the same-host simulator link takes no TCP port; no companion, no companion port
    bare = fleet_ports(2, 3, tcp_sim=False, companion=False)
    assert {kind for kind, _ in bare} == {"udp"} and ("udp", 14543) not in bare


@pytest.mark.parametrize("kind", ["tcp", "udp"])
def test_a_port_another_process_holds_is_named_with_the_way_out(kind):
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM if kind == "tcp" else socket.SOCK_DGRAM)
    try:
        sock.bind(("127.0.0.1", 0))
        if kind == "tcp":
            sock.listen(1)
        port = sock.getsockname()[1]
        with pytest.raises(FleetError, match=rf"{kind.upper()} {port} \(link 1's x\).*--instance-offset"):
            check_ports_free({(kind, port): "link 1's x"})
    finally:
        sock.close()
    check_ports_free({(kind, port): "link 1's x"})  # free again


def test_last_error_prefers_the_error_line(tmp_path):
    log = tmp_path / "console.log"
    assert last_error(log) is None  # no log
    log.write_text("")
    assert last_error(log) is None
    log.write_text("INFO starting\nerror: cannot bind TCP 127.0.0.1:4590: Address already in use\nbye\n\n")
    assert last_error(log) == "error: cannot bind TCP 127.0.0.1:4590: Address already in use"
    log.write_text("Traceback (most recent call last):\nValueError: bad\n")
    assert last_error(log) == "ValueError: bad"


def test_a_process_that_exits_is_reported_with_what_it_said(tmp_path):
    procs = Processes()
    code = "import sys; print('error: cannot bind TCP 127.0.0.1:4590: Address already in use'); sys.exit(2)"
    procs.start("link 1", [sys.executable, "-c", code], tmp_path / "link1" / "console.log")
    try:
        deadline = time.monotonic() + 10.0
        while procs.procs[0][1].poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        with pytest.raises(FleetError, match=r"link 1 exited with code 2: error: cannot bind TCP 127\.0\.0\.1:4590: "
                                             r"Address already in use \(console log: .*link1/console\.log\)"):
            procs.check()
    finally:
        procs.stop()


def test_only_the_first_interruption_cuts_a_fleet_run_short(caplog):
    """Ctrl-C pressed twice, or ``timeout`` (which signals the process and then its group): the
    first interrupts the flight, the rest must not cut short the stop and the metrics; once the
    flight is over, none interrupts (sitl.fleet.processes.interrupted_once)."""
    import signal

    from sitl.fleet.processes import interrupted_once

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with interrupted_once() as flown:
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGINT)  # (the second: logged, ignored)
        signal.raise_signal(signal.SIGTERM)
    assert sum("ignored" in r.getMessage() for r in caplog.records) == 2
    with interrupted_once() as flown:
        flown()  # the flight is over: the stop and the metrics follow
        signal.raise_signal(signal.SIGTERM)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before

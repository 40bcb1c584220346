"""The same-host simulator link's sockets (link_firmware_sim.vehicle.simlink): a pair exchanges
packets, counts and drops hostile ones and sees its peer go; the socket is private (its file 0600,
another user's process refused), a stale socket file is replaced and a live one is not; and the
fleet harness reads a tick's answers over it."""

from __future__ import annotations

import os
import shutil
import socket
import stat
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from companion.mavlink.port import MavlinkPort
from companion.mavlink.transport import PortError, wait_readable
from link_firmware_sim.vehicle.hil import decode_actuators, encode_actuators, encode_hil_sensor
from link_firmware_sim.vehicle.simlink import SimLinkPort, encode_packet, open_sim_port
from sitl.fleet.harness import FleetHarness
from sitl.fleet.layout import FleetError
from sitl.fleet.processes import listening_unix_paths
from sitl.scenario import load_scenario

from ..paths import ROOT
from ..hil_messages import ACTUATORS, SENSORS, random_messages
from ..mavlink_wire import over_mavlink


def _pair(tmp_path):
    url = f"unixin://{tmp_path / 'link1.sock'}"
    vehicle = SimLinkPort(url, accept=SENSORS)
    sim = SimLinkPort(f"unix://{tmp_path / 'link1.sock'}", accept=ACTUATORS, connect_timeout_s=2.0)
    return vehicle, sim


def _read(port, want: int = 1, timeout_s: float = 2.0) -> list:
    out, deadline = port.read(), time.monotonic() + timeout_s
    while len(out) < want and time.monotonic() < deadline:
        time.sleep(0.001)
        out += port.read()
    return out


def test_a_pair_exchanges_counts_drops_and_sees_the_peer_go(tmp_path):
    vehicle, sim = _pair(tmp_path)
    try:
        path = tmp_path / "link1.sock"
        assert stat.S_IMODE(path.stat().st_mode) == 0o600  # only this user can connect
        assert str(path) in listening_unix_paths()
        _read(vehicle, 0, 0.05)  # accepts
        assert vehicle.connected and sim.connected
        msgs = random_messages(np.random.default_rng(3))
        sim.send_many(msgs[:3])
        got = _read(vehicle, 3)
        assert [m.get_type() for m in got] == ["HIL_GPS", "SKELETON_AHRS_REFERENCE", "HIL_SENSOR"]
        # hostile packets: counted and dropped whole, never raised; the next good one goes through
        raw = sim.conn
        raw.send(b"\xff" * 40)
        raw.send(encode_packet(msgs[:1])[:-3])
        raw.send(encode_packet(msgs[3:]))  # the simulator's kind, sent to the vehicle
        raw.send(encode_packet(msgs[2:3] * 20))  # whole records, but more than a packet may hold
        sim.send(msgs[2])
        got = _read(vehicle, 1)
        assert [m.get_type() for m in got] == ["HIL_SENSOR"]
        st_ = vehicle.stats
        assert st_.dropped_frames == 4 and st_.rx_messages == 4 and st_.per_type["HIL_SENSOR"] == 2
        vehicle.send(msgs[3])
        (answer,) = _read(sim, 1)
        assert decode_actuators(answer, 8.0)[0] == msgs[3].time_usec
        # the simulator goes: the vehicle waits for the next one, which it then serves
        sim.close()
        deadline = time.monotonic() + 2.0
        while vehicle.connected and time.monotonic() < deadline:
            vehicle.read()
        assert not vehicle.connected
        sim = SimLinkPort(f"unix://{path}", accept=ACTUATORS, connect_timeout_s=2.0)
        _read(vehicle, 0, 0.05)
        assert vehicle.connected
        sim.send(msgs[2])
        assert len(_read(vehicle, 1)) == 1
        # the vehicle goes: the simulator's end is closed for good
        vehicle.close()
        assert not path.exists()
        deadline = time.monotonic() + 2.0
        while sim.connected and time.monotonic() < deadline:
            sim.read()
        assert not sim.connected and sim.read() == []
        sim.send(msgs[2])  # nothing to send to: no error
    finally:
        vehicle.close()
        sim.close()


def test_stale_socket_files_are_replaced_live_ones_are_not(tmp_path):
    path = tmp_path / "link1.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    stale.bind(str(path))
    stale.close()  # a killed vehicle's file: nobody listens
    first = SimLinkPort(f"unixin://{path}", accept=SENSORS)
    try:
        with pytest.raises(PortError, match="another process listens"):
            SimLinkPort(f"unixin://{path}", accept=SENSORS)
        assert first.server is not None and path.exists()
    finally:
        first.close()


def test_bad_urls_and_absent_peers_are_clear_errors(tmp_path):
    with pytest.raises(PortError, match="ABSOLUTE"):
        SimLinkPort("unixin://relative/path.sock")
    with pytest.raises(PortError, match="at most 107 bytes"):
        SimLinkPort("unixin:///" + "x" * 120)
    with pytest.raises(PortError, match="cannot connect"):
        SimLinkPort(f"unix://{tmp_path / 'nobody.sock'}", connect_timeout_s=0.1)
    assert isinstance(open_sim_port("tcpin://127.0.0.1:0", 1), MavlinkPort)


def test_another_users_process_is_refused(tmp_path):
    if os.getuid() != 0:
        pytest.skip("needs root to connect as another user")
    # a folder and a socket file open to all (the fleet's are private: this checks the last line)
    folder = Path(tempfile.mkdtemp(prefix="simlink-peer-"))
    os.chmod(folder, 0o777)
    path = folder / "link1.sock"
    vehicle = SimLinkPort(f"unixin://{path}", accept=SENSORS)
    os.chmod(path, 0o666)
    pid = os.fork()
    if pid == 0:  # the child: another user
        try:
            os.setuid(65534)
            s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            s.connect(str(path))
            s.send(encode_packet([encode_hil_sensor(1.0, np.zeros(3), np.zeros(3))]))
            s.settimeout(2.0)
            s.recv(64)  # until the vehicle closes the connection (b""), at most 2 s
        finally:
            os._exit(0)
    try:
        deadline = time.monotonic() + 2.0
        while vehicle.stats.rejected_peer == 0 and time.monotonic() < deadline:
            assert vehicle.read() == []
            time.sleep(0.005)
        assert vehicle.stats.rejected_peer == 1 and not vehicle.connected
    finally:
        os.waitpid(pid, 0)
        vehicle.close()
        shutil.rmtree(folder, ignore_errors=True)


def test_the_harness_decodes_a_ticks_answers_together_and_names_a_link_answering_nan(tmp_path):
    """The fleet harness over the same-host link with three fake vehicles: their answers become
    the rotor commands of the tick (decoded together, as each alone); a non-finite answer stops
    the lockstep with a FleetError naming that link."""
    sc = load_scenario(ROOT / "configs" / "sitl" / "chain" / "three_link.toml")
    folder = Path(tempfile.mkdtemp(prefix="skl-h-"))  # short: a socket path's limit
    vehicles = [SimLinkPort(f"unixin://{folder / f'l{i}.sock'}", accept=SENSORS) for i in range(3)]
    answers = np.array([[1.0, -2.0, 3.0, 0.5, 0.0, 2.0, 9.0, -9.0]]) * np.array([[1.0], [0.5], [0.25]])
    poisoned = threading.Event()
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            for i in range(3):
                v = vehicles[i]
                if v in wait_readable([v], 0.01) or not v.connected:
                    for msg in v.read():
                        if msg.get_type() == "HIL_SENSOR":
                            u = answers[i].copy()
                            if i == 1 and poisoned.is_set():
                                u[3] = np.nan
                            v.send(encode_actuators(msg.time_usec * 1e-6, u, sc.rotors.thrust_max_n, True))

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    harness = FleetHarness(sc, [f"unix://{folder / f'l{i}.sock'}" for i in range(3)])
    try:
        truth = harness.plant.begin_tick()
        thrust = harness._exchange(0.0, 0, truth)
        expected = np.array([decode_actuators(over_mavlink(encode_actuators(0.0, a, sc.rotors.thrust_max_n, True)),
                                              sc.rotors.thrust_max_n)[1] for a in answers])
        np.testing.assert_array_equal(thrust, expected)
        poisoned.set()
        with pytest.raises(FleetError, match=r"link\(s\) \[2\] answered the simulator with a non-finite control"):
            harness._exchange(0.002, 2, truth)
    finally:
        stop.set()
        server.join(2.0)
        harness.close()
        for v in vehicles:
            v.close()
        shutil.rmtree(folder, ignore_errors=True)

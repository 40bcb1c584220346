"""The harness's faults (sitl.fleet.faults) on a stand-in fleet, and the fault socket
(sitl.fleet.fault_socket) on a real UNIX socket: when each fault acts, the restarts' processes
and folders, what is refused, the outage windows, hostile requests."""

from __future__ import annotations

import json
import socket
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from sitl.fleet.fault_socket import MAX_BYTES, FaultSocket, send_request
from sitl.fleet.faults import HarnessFault, FleetFaults, restart_folder, scripted_faults
from sitl.fleet.launcher import Fleet
from sitl.scenario import LinkRebootFault, load_scenario

from ..paths import THREE_LINK


class StandInFleet:
    """What FleetFaults uses of a Fleet, recording what it is asked to do."""

    companion_name = staticmethod(Fleet.companion_name)
    companion_folder = staticmethod(Fleet.companion_folder)

    def __init__(self, sc, companion=True):
        self.sc, self.n, self.companion = sc, sc.skeleton.n_links, companion
        self.calls = []
        self.listening = set()
        self.procs = SimpleNamespace(kill=lambda name: self.calls.append(("kill", name)),
                                     release=lambda name: self.calls.append(("release", name)))
        self.harness = SimpleNamespace(detach=lambda i: self.calls.append(("detach", i)),
                                       attach=lambda i, url: self.calls.append(("attach", i)))
        self.plant = SimpleNamespace(rotors=SimpleNamespace(command_n=np.zeros(8 * self.n)))

    def start_vehicle(self, i, name, folder, standby=False):
        self.calls.append(("start vehicle", name, folder, standby))

    def start_companion(self, group, folder, name=None):
        self.calls.append(("start companion", name, folder))

    def sim_listening(self, i):
        return i in self.listening

    def sim_url(self, i, side):
        return f"tcp://{i}"


@pytest.fixture
def sc():
    return load_scenario(THREE_LINK, duration_s=30.0)


def _run(faults, fleet, t0, t1, dt=0.002):
    for k in range(int(round(t0 / dt)), int(round(t1 / dt))):
        faults.tick(k * dt)


def test_a_vehicle_switched_off_and_on_again_twice(sc):
    fleet = StandInFleet(sc)
    faults = FleetFaults(fleet)
    tl = faults.add(HarnessFault("vehicle_off", 2, restart_after_s=1.0, at_s=5.0, source="request"), 1.0)
    _run(faults, fleet, 1.0, 5.5)
    assert tl["killed_at_s"] == 5.0 and fleet.calls == [
        ("kill", "link 2"), ("detach", 1), ("start vehicle", "link 2 (restarted)", "link2-restart", False)]
    _run(faults, fleet, 5.5, 6.5)
    assert tl["restarted_at_s"] == 6.0 and "rejoined_at_s" not in tl  # its process still starting
    fleet.listening.add(1)
    _run(faults, fleet, 6.5, 6.6)
    assert tl["rejoined_at_s"] == 6.5 and fleet.calls[-1] == ("attach", 1)
    with pytest.raises(ValueError, match="link 2 has a fault in play"):
        faults.add(HarnessFault("vehicle_off", 2, source="request"), 6.6)
    fleet.plant.rotors.command_n[8:16] = 1.0
    _run(faults, fleet, 6.6, 6.7)
    assert tl["rotors_on_at_s"] == 6.6
    fleet.calls.clear()
    second = faults.add(HarnessFault("vehicle_off", 2, restart_after_s=0.5, source="request"), 8.0)
    _run(faults, fleet, 8.0, 8.1)
    assert fleet.calls[:3] == [("kill", "link 2 (restarted)"), ("detach", 1),
                               ("start vehicle", "link 2 (restart 2)", "link2-restart2", False)]
    _run(faults, fleet, 8.1, 9.0)
    assert [w["start_s"] for w in faults.windows(20.0)] == [5.0, 8.0]
    assert [w["end_s"] for w in faults.windows(20.0)] == [6.5, second["rejoined_at_s"]]
    assert faults.refused == 1


def test_the_scenarios_faults_go_through_the_same_interface(sc):
    sc = replace(sc, faults=replace(sc.faults, link=LinkRebootFault(kill=1, kill_at_s=9.0, restart_after_s=1.0)))
    fleet = StandInFleet(sc)
    faults = FleetFaults(fleet)
    for f in scripted_faults(sc):
        faults.add(f, 0.0)
    # the scripted restart's process is loaded with the fleet and released at the kill
    assert fleet.calls == [("start vehicle", "link 1 (restarted)", "link1-restart", True)]
    _run(faults, fleet, 8.9, 9.1)
    assert fleet.calls[1:] == [("kill", "link 1"), ("detach", 0), ("release", "link 1 (restarted)")]
    assert faults.first("vehicle_off", "scenario")["killed_at_s"] == 9.0


def test_a_companion_off_for_good_and_the_refusals(sc):
    fleet = StandInFleet(sc)
    faults = FleetFaults(fleet)
    faults.add(HarnessFault("companion_off", 1, source="request"), 10.0)
    faults.tick(10.0)
    assert fleet.calls == [("kill", "companion")]
    assert faults.windows(30.0) == [{"kind": "companion_down", "start_s": 10.0, "end_s": 30.0, "links": [1, 2, 3]}]
    for fault, why in ((HarnessFault("companion_off", 1), "off for good"),
                       (HarnessFault("companion_off", 2), "companions 1..1"),
                       (HarnessFault("vehicle_off", 4), "links 1..3")):
        with pytest.raises(ValueError, match=why):
            faults.add(fault, 11.0)
    with pytest.raises(ValueError, match="runs no companion"):
        FleetFaults(StandInFleet(sc, companion=False)).add(HarnessFault("companion_off", 1), 0.0)


@pytest.mark.parametrize("request_, why", [
    ([1, 2], "a JSON object"), ({"kind": "vehicle_off"}, "needs kind and target"),
    ({"kind": "reboot", "target": 1}, "kind 'reboot'"), ({"kind": "vehicle_off", "target": 0}, "target must be"),
    ({"kind": "vehicle_off", "target": True}, "target must be"),
    ({"kind": "vehicle_off", "target": 1, "restart_after_s": float("nan")}, "restart_after_s must be"),
    ({"kind": "vehicle_off", "target": 1, "restart_after_s": 1e9}, "restart_after_s must be"),
    ({"kind": "vehicle_off", "target": 1, "at_s": -1}, "at_s must be"),
    ({"kind": "vehicle_off", "target": 1, "now": 1}, "unknown keys: now"),
])
def test_a_bad_request_is_refused_with_a_reason(request_, why):
    with pytest.raises(ValueError, match=why):
        HarnessFault.from_request(request_)


def test_restart_folders():
    assert [restart_folder("link2", k) for k in (1, 2, 3)] == ["link2-restart", "link2-restart2", "link2-restart3"]


def test_the_fault_socket_answers_every_datagram_and_counts_the_bad_ones(tmp_path):
    path = tmp_path / "faults.sock"
    fs = FaultSocket(path)
    assert path.stat().st_mode & 0o777 == 0o600
    seen = []

    def handle(request, t_s):
        seen.append(request)
        return {"accepted": request.get("ok", False)}

    client = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    client.bind(f"\0test-fault-client-{id(client)}")
    client.settimeout(2.0)
    try:
        for data in (b'{"ok": true}', b'{"ok": false}', b"\xff\xfe", b"{" * (MAX_BYTES + 10), b"not json"):
            client.sendto(data, str(path))
            fs._next_s = 0.0
            fs.serve(handle, 1.0)
            reply = json.loads(client.recv(65536))
            assert reply["accepted"] == (data == b'{"ok": true}'), (data[:20], reply)
        fs.serve(handle, 1.0)  # nothing waiting: returns at once
    finally:
        client.close()
    assert seen == [{"ok": True}, {"ok": False}]
    assert fs.counts == {"accepted": 1, "refused": 1, "malformed": 3}
    fs.close()
    assert not path.exists()
    with pytest.raises(ConnectionError, match="no running fleet listens"):
        send_request(path, {"kind": "vehicle_off", "target": 1}, timeout_s=0.5)

"""Fleet mode end to end: vehicle processes, the companion daemon and the harness over loopback
sockets, against batch mode and under attack: garbage at the ports, the simulator links over UNIX
sockets, distributed companions failing over, a signed fleet and an unkeyed process, crafted
states at the companion.

Each test launches a real fleet (``sitl.fleet.launcher.launch``: one OS process per link plus the
companion) on the PX4-style ports of its own instance offset, with a ground-station port of its own
(the ``fleet_ports`` fixture), so that two tests run side by side (``pytest -n 2``); each checks
that every port is free again afterwards. Faults and interruptions: test_fleet_faults.py; standard
MAVLink clients and messages: test_fleet_interop.py.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from companion.mavlink.dialect import load_dialect, tool_environment
from companion.mavlink.port import MavlinkPort
from companion.mavlink.transport import wait_readable
from companion.mavlink.signing import load_key, new_key_file
from sitl.fleet.layout import LOCKSTEP_ENDED, LOCKSTEP_STARTED
from sitl.fleet.launcher import launch
from sitl.scenarios.chain.flight import fly
from sitl.scenario import load_scenario

from ..ports import FleetPorts, assert_ports_released, children_of, tcp_free
from ..waits import wait_for
from ..paths import ROOT, THREE_LINK

D = load_dialect()


class HeartbeatListener(threading.Thread):
    """A plain pymavlink GCS on UDP ``port`` (what QGroundControl or MAVProxy would listen on on
    14550): the systems it heard, the kinds of messages and the latest time_boot_ms of each."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=254, dialect="common")
        self.sysids: set[int] = set()
        self.types: set[str] = set()
        self.boot_s: dict[int, float] = {}
        self.stop = threading.Event()

    def run(self):
        while not self.stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.2)
            if msg is None:
                continue
            self.types.add(msg.get_type())
            if msg.get_type() == "HEARTBEAT":
                self.sysids.add(msg.get_srcSystem())
            if getattr(msg, "time_boot_ms", None) is not None:
                self.boot_s[msg.get_srcSystem()] = msg.time_boot_ms * 1e-3

    def close(self):
        self.stop.set()
        self.join(2.0)
        self.conn.close()


def _garbage(port: int, rng: np.random.Generator) -> int:
    """1 MB of random datagrams and 400 truncated MAVLink 2 frames, paced so the kernel keeps them."""
    frame = D.MAVLink_heartbeat_message(2, 0, 0, 0, 4, 3).pack(D.MAVLink(None, srcSystem=1, srcComponent=1))
    sent = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for k in range(1024):
            s.sendto(rng.bytes(1024), ("127.0.0.1", port))
            s.sendto(frame[: 3 + k % (len(frame) - 4)], ("127.0.0.1", port))
            sent += 1024
            if k % 64 == 63:
                time.sleep(0.02)
    return sent


def _launch_under(sc, tmp_path, ports: FleetPorts, attack, speed: float = 1.0, join_s: float = 30.0,
                  **options) -> dict:
    """Fly ``sc`` in fleet mode on ``ports`` (and :func:`launch`'s ``options``) while ``attack(stop)``
    runs in a thread of this process; ``stop`` (a threading.Event) is set when the flight ends.
    Returns the metrics."""
    stop = threading.Event()
    worker = threading.Thread(target=attack, args=(stop,), daemon=True)
    worker.start()
    try:
        return launch(sc, tmp_path, speed=speed, **ports.launch_kwargs, **options)
    finally:
        stop.set()
        worker.join(join_s)


@pytest.fixture(scope="module")
def batch_reference():
    sc = load_scenario(THREE_LINK, duration_s=16.0)
    return fly(sc, None, plots=False)


def test_fleet_flies_under_garbage_like_batch_mode(tmp_path, batch_reference, fleet_ports):
    """Three links end to end through sockets, a GCS listening, 1 MB of noise at a link and the companion."""
    sc = load_scenario(THREE_LINK, duration_s=16.0)
    listener = HeartbeatListener(fleet_ports.gcs_port)
    listener.start()
    flooded = {}

    def flood():
        # the links up (4 s into the flight by their clocks), the companion stepping; the burst is
        # sent before the metrics window (from the end of the take-off, 7 s)
        wait_for(lambda: listener.sysids == {1, 2, 3} and min(listener.boot_s.values(), default=0.0) >= 4.0, 60.0)
        rng = np.random.default_rng(7)
        flooded["link2"] = _garbage(fleet_ports.vehicle(1), rng)  # link 2's onboard port
        flooded["companion"] = _garbage(fleet_ports.companion(1), rng)  # the companion's port for link 2

    try:
        # (the companion as an onboard computer without numba runs it: the numpy path)
        m = _launch_under(sc, tmp_path, fleet_ports, lambda stop: flood(), speed=0.0, companion_kernels="numpy")
    finally:
        listener.close()
    assert not children_of(os.getpid()), "vehicle or companion processes left behind"
    assert_ports_released(fleet_ports, 3)

    assert flooded == {"link2": 1 << 20, "companion": 1 << 20}
    assert listener.sysids == {1, 2, 3}
    assert {"ATTITUDE", "GLOBAL_POSITION_INT", "SYS_STATUS"} <= listener.types

    # the garbage was counted and dropped where it arrived
    link2 = json.loads((tmp_path / "link2" / "link2_ports.json").read_text())
    onboard = next(v for k, v in link2.items() if k.startswith(f"udpout://127.0.0.1:{fleet_ports.companion(1)}"))
    assert onboard["dropped_bytes"] > 900_000 and onboard["dropped_frames"] >= 1024
    # the companion stood in for an onboard computer without numba: the numpy path
    assert "numpy path (no compiled kernels)" in (tmp_path / "companion" / "console.log").read_text()
    assert m["companion_kernels"] == "numpy"
    comp = json.loads((tmp_path / "companion" / "companion_summary.json").read_text())
    assert comp["links"]["2"]["dropped_bytes"] > 900_000 and comp["links"]["2"]["dropped_frames"] >= 1024
    assert comp["links"]["1"]["dropped_bytes"] == 0
    assert comp["links"]["2"]["rejected"] == 0 and comp["links"]["2"]["states"] > 600

    # the flight: unaffected, and within 20 % of batch mode on tracking and constraint error
    assert not m["crashed"] and m["mode"] == "fleet" and not m["interrupted"]
    ref = batch_reference
    for key in ("rms_track_est_m", "rms_track_true_m"):
        np.testing.assert_allclose(m[key], ref[key], rtol=0.2, err_msg=key)
    for key in ("constraint_pos_p95_m", "constraint_vel_p95_m_s"):
        assert m[key]["after"] == pytest.approx(ref[key]["after"], rel=0.2), key
        assert m[key]["after"] < 0.05 * m[key]["before"], key
    assert m["correction_latency_ms"]["p99"] <= 30.0 and m["correction_latency_ms"]["samples"] > 300
    # The companion's figure covers the whole run, the 1 MB burst being drained included, in
    # simulated ms at --speed 0: a wall-clock delay counts times the run's real-time factor. Within
    # one 20 Hz period of wall time.
    assert comp["correction_latency_ms"]["p99"] <= 50.0 * max(1.0, m["realtime_factor"])

    # artefacts: metrics, plots and a tlog per link that pymavlink reads back
    assert json.loads((tmp_path / "metrics.json").read_text())["rms_track_true_m"] == m["rms_track_true_m"]
    assert (tmp_path / "tracking.png").stat().st_size > 0
    tlog = tmp_path / "link2" / "link2.tlog"
    plain = mavutil.mavlink_connection(str(tlog), dialect="common")  # any pymavlink: the standard messages
    kinds = set()
    while (msg := plain.recv_match()) is not None:
        kinds.add(msg.get_type())
    plain.close()
    assert {"HEARTBEAT", "ATTITUDE", "LOCAL_POSITION_NED", "SET_POSITION_TARGET_LOCAL_NED", "COMMAND_ACK"} <= kinds
    env = dict(os.environ, **tool_environment())  # `python -m companion dialect`: the custom messages too
    dump = subprocess.run([sys.executable, str(Path(sys.executable).parent / "mavlogdump.py"), "--dialect",
                           "aerial_skeleton", "--types", "SKELETON_LINK_STATE,SKELETON_CORRECTION", str(tlog)],
                          env=env, capture_output=True, text=True, timeout=120)
    assert dump.returncode == 0, dump.stderr[-2000:]
    lines = dump.stdout.splitlines()
    assert sum("SKELETON_LINK_STATE {" in x for x in lines) > 600
    assert sum("SKELETON_CORRECTION {" in x for x in lines) > 200

    # sequence numbers: every sender's frames on every link numbered without a gap (a loss-free run)
    for path, sysid in ((tlog, 2), (tmp_path / "link2" / "link2_gcs.tlog", 2),
                        (tmp_path / "companion" / "companion_link2.tlog", 190)):
        assert _sequence_gaps(path, sysid) == 0, path


def test_fleet_over_the_same_host_link_flies_like_batch_mode(tmp_path, batch_reference, caplog, fleet_ports):
    """``sim_link="unix"``: the vehicles' simulator links over UNIX sockets in a private folder
    (link_firmware_sim.vehicle.simlink); the flight is batch mode's, and the folder goes with the fleet.
    Unpaced, the harness and every process of the fleet run under SCHED_BATCH; the launching
    thread gets its policy back."""
    sc = load_scenario(THREE_LINK, duration_s=16.0)
    with pytest.raises(ValueError, match="sim_link 'shm'"):
        launch(sc, tmp_path / "bad", sim_link="shm", **fleet_ports.launch_kwargs)
    result, policies = {}, {}

    def fleet() -> None:
        result["metrics"] = launch(sc, tmp_path, speed=0.0, plots=False, sim_link="unix", **fleet_ports.launch_kwargs)
        result["policy_after"] = os.sched_getscheduler(0)

    with caplog.at_level(logging.INFO, logger="sitl.fleet"):
        runner = threading.Thread(target=fleet)
        runner.start()
        while runner.is_alive():
            for pid in children_of(os.getpid()):
                try:
                    policies[pid] = os.sched_getscheduler(pid)
                except OSError:
                    pass  # gone meanwhile
            time.sleep(0.2)
        runner.join()
    m = result["metrics"]
    assert len(policies) >= 4 and set(policies.values()) == {os.SCHED_BATCH}, policies  # 3 vehicles, the companion
    assert m["scheduling"] == "batch" and result["policy_after"] == os.SCHED_OTHER
    assert not children_of(os.getpid()), "vehicle or companion processes left behind"
    # the loop's start and end, as bench sitl finds them in the harness's log
    lines = [r.getMessage() for r in caplog.records if r.name == "sitl.fleet.harness"]
    assert any(x.startswith(LOCKSTEP_STARTED + " 3 vehicle(s) from t = 0.000 s") for x in lines), lines
    assert any(x.startswith(LOCKSTEP_ENDED + " at t = 16.000 s") for x in lines), lines
    assert_ports_released(fleet_ports, 3)
    assert m["sim_link"] == "unix" and not m["crashed"] and not m["aborted"]
    # the companion's compiled kernels (the default where numba is installed), loaded before the lockstep
    assert m["companion_kernels"] == "compiled"
    console = (tmp_path / "companion" / "console.log").read_text()
    assert "compiled kernels ready in" in console and "; compiled kernels" in console
    for key in ("rms_track_est_m", "rms_track_true_m"):
        np.testing.assert_allclose(m[key], batch_reference[key], rtol=0.2, err_msg=key)
    for key in ("constraint_pos_p95_m", "constraint_vel_p95_m_s"):
        assert m[key]["after"] == pytest.approx(batch_reference[key]["after"], rel=0.2), key
    folders = set()
    for i in (1, 2, 3):
        ports = json.loads((tmp_path / f"link{i}" / f"link{i}_ports.json").read_text())
        url, sim = next((k, v) for k, v in ports.items() if k.startswith("unixin:///"))
        folders.add(Path(url[len("unixin://"):]).parent)
        # one HIL_SENSOR per 2 ms tick, none dropped, none refused
        assert sim["per_type"]["HIL_SENSOR"] >= 0.95 * 16.0 / 0.002, sim
        assert sim["dropped_frames"] == 0 and sim["rejected_peer"] == 0 and sim["tx_messages"] > 7000, sim
    (folder,) = folders
    assert folder.name.startswith("skeleton-sim-") and not folder.exists()
    assert all(m["mavlink"][f"link{i}"]["sim_dropped_frames"] == 0 == m["mavlink"][f"link{i}"]["sim_rejected_peer"]
               for i in (1, 2, 3))


def _sequence_gaps(path: Path, sysid: int) -> int:
    """Frames of ``sysid`` lost by their sequence numbers in a tlog, as MAVProxy counts them (every
    frame of the tlog: 8-byte time stamp, then a MAVLink 2 frame, whatever its message)."""
    data, k = path.read_bytes(), 0
    last, lost, frames = None, 0, 0
    while k + 8 + 12 <= len(data):
        frame = data[k + 8:]
        assert frame[0] == 0xFD, f"not a MAVLink 2 frame at byte {k + 8}"
        size = 10 + frame[1] + 2 + (13 if frame[2] & 1 else 0)
        if frame[5] == sysid:
            if last is not None:
                lost += (frame[4] - last - 1) % 256
            last, frames = frame[4], frames + 1
        k += 8 + size
    assert k == len(data) and frames > 100
    return lost


def test_distributed_companions_fail_over_and_hand_back(tmp_path, fleet_ports):
    """One companion per group over Zenoh; the leader's companion is killed and comes back."""
    sc = load_scenario(THREE_LINK, duration_s=15.0)
    sc = replace(sc, companion=replace(sc.companion, groups=((1,), (2, 3)), distributed=True),
                 faults=replace(sc.faults, kill_companion_group=1, kill_at_s=8.5, restart_after_s=2.5))
    m = launch(sc, tmp_path, speed=1.0, **fleet_ports.launch_kwargs)
    assert not m["crashed"]
    d = m["distributed"]
    fault = d["fault"]
    assert [f["to_group"] for f in fault["failover"]] == [2]  # group 2 noticed and took over
    assert fault["failover_s_max"] < 1.0 and fault["failover"][0]["cycles_without_global_step"] <= 2
    comps = d["companions"]
    assert set(comps) == {"companion-g1-restart", "companion-g2"}  # SIGKILLed: the first g1 left no summary
    leaders = [g for _, g in comps["companion-g2"]["global_step"]["leaders"]]
    # group 1 leads, group 2 takes over, hands back to the returning group 1 (group 2 may lead the
    # first cycles too, if group 1's companion came up later: then it hands over at once)
    assert leaders in ([1, 2, 1], [2, 1, 2, 1])
    # one leader per cycle through the hand-back (a returning group that lags a cycle behind used
    # to lead before the agreed hand-over cycle: test_fleetnet_election's lagging-group test).
    # Before the take-off two companions that found each other late (each led alone, a partition
    # that healed) may both have led a cycle: the lower-ranked one yielded.
    for c in comps.values():
        gs = c["global_step"]
        assert gs["duplicate_shift"] == len(gs["duplicates"]), gs
        assert all(dup["cycle_s"] < sc.flight_start_s and dup["second_live"] for dup in gs["duplicates"]), gs
    cp = m["constraint_pos_p95_m"]
    assert cp["after_between_groups"] <= max(cp["after_within_groups"], 0.01)
    # Every cycle of the window counts, those of the outage too (group 2 alone has no global step
    # to take part in): the global step is off only from the kill (less the killed companion's
    # last unflushed second of log) until the restarted group 1 is back, 1.5-2 s after its restart.
    outs = m["outages"]["windows"]
    down = [w for w in outs if w["kind"] == "companion_down"]
    assert [{k: w[k] for k in ("kind", "start_s", "end_s", "links")} for w in down] == [
        {"kind": "companion_down", "start_s": fault["killed_at_s"], "end_s": fault["restarted_at_s"], "links": [1]}]
    assert down[0]["corrected_fraction"][0] is None  # the window's own link: not counted
    gaps = [w for w in outs if w["kind"] == "no_global_step"]
    first_s, back_s = fault["killed_at_s"] - 1.1 - 1e-6, fault["restarted_at_s"] + 3.0
    outage = [w for w in gaps if w["start_s"] >= first_s and w["end_s"] <= back_s]
    # one window covers the outage: from the kill's cycle (or the next one, when the kill came
    # after the cycle's global step had settled) to the restart
    period_s = 1.0 / sc.companion.rate_hz
    assert any(w["start_s"] <= fault["killed_at_s"] + period_s + 1e-6 and w["end_s"] >= fault["restarted_at_s"]
               for w in outage), gaps
    # Outside it, at most a few stray cycles whose shift missed the 20 ms deadline on a busy host
    # (seen with two CPU hogs beside the fleet on 2 cores, after the outage and once 1.1 s before
    # the kill): counted, never a run of them.
    stray = [w for w in gaps if w not in outage]
    assert len(stray) <= 3 and all(w["end_s"] - w["start_s"] <= 0.1 for w in stray), gaps
    # The fraction of cycles with the global step (from the take-off) is the cycles outside these
    # windows, to a cycle; it is at least what the windows' bounds above leave (the outage's window
    # starts with the killed companion's last unflushed second of log and ends 1.5-2 s after the
    # restart: 0.33 with 5.25 s of 8 s of cycles in windows, 0.35 or more when less of it was lost)
    def cycle(t_s: float) -> int:
        return int(round((t_s - sc.flight_start_s) / period_s))

    n_cycles = cycle(sc.duration_s)
    out_cycles = {k for w in gaps for k in range(max(cycle(w["start_s"]), 0), min(cycle(w["end_s"]) + 1, n_cycles))}
    fraction = d["cycles_with_global_step_fraction"]
    assert abs(fraction - (1.0 - len(out_cycles) / n_cycles)) <= 1.0 / n_cycles + 1e-9, (fraction, gaps)
    allowed = (back_s - first_s) + sum(w["end_s"] - w["start_s"] + period_s for w in stray)
    assert fraction >= 1.0 - allowed / (sc.duration_s - sc.flight_start_s) - 1.0 / n_cycles, (fraction, gaps)
    assert_ports_released(fleet_ports, 3)
    assert tcp_free(fleet_ports.zenoh(0)) and tcp_free(fleet_ports.zenoh(1))


def _unkeyed_attacks(sent: dict, stop: threading.Event, ports: FleetPorts) -> None:
    """The spoofs of an unkeyed process on this host, at link 2 (system 2) of the fleet on ``ports`` during the flight:
    SKELETON_CORRECTION dp = 5 m at 100 Hz, a (forced) disarm flood at its GCS port, a position
    target 0.35 m off, and a HEARTBEAT flood with its system id at the companion's port for it."""
    D = load_dialect()
    mav = D.MAVLink(None, srcSystem=255, srcComponent=190)
    as_link2 = D.MAVLink(None, srcSystem=2, srcComponent=1)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    from companion.mavlink.codec import encode_correction
    from companion.messages import Correction

    def send(frame_msg, packer, port, key):
        raw.sendto(frame_msg.pack(packer), ("127.0.0.1", port))
        sent[key] = sent.get(key, 0) + 1

    for k in range(200):  # 2 s at 100 Hz
        if stop.is_set():
            break
        corr = Correction(1, 0.0, np.array([5.0, 0, 0]), np.zeros(3), np.zeros(3), seq=k)
        send(encode_correction(corr, target_system=2), mav, ports.vehicle(1), "correction")
        if k % 2 == 0:
            send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0),
                 mav, ports.gcs_from(1), "disarm")
            send(D.MAVLink_set_position_target_local_ned_message(0, 2, 1, D.MAV_FRAME_LOCAL_NED, 0b110111111000,
                                                                  0.35, 0.0, -2.5, 0, 0, 0, 0, 0, 0, 0, 0),
                 mav, ports.vehicle(1), "target")
        send(D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_GENERIC, 0, 0, 4, 3), as_link2,
             ports.companion(1), "heartbeat")
        time.sleep(0.01)  # the pace of the spoofs: 100 Hz
    raw.close()


def test_signed_fleet_ignores_an_unkeyed_process_and_serves_a_keyed_gcs(tmp_path, fleet_ports):
    """three_link_signed.toml: signing required everywhere; the four spoofs change nothing, a keyed
    ground station reads and sets a parameter."""
    sc = load_scenario(ROOT / "configs" / "sitl" / "chain" / "three_link_signed.toml", duration_s=16.0)
    key_file = tmp_path / "fleet.key"
    new_key_file(key_file)
    sc = replace(sc, signing=replace(sc.signing, key_file=str(key_file)))
    sent: dict = {}
    gcs_result: dict = {}

    def gcs_and_attacker(stop):
        gcs = MavlinkPort(f"udpin://127.0.0.1:{fleet_ports.gcs_port}", system_id=254, component_id=190,
                          signing="required", key=load_key(key_file))
        try:
            deadline = time.monotonic() + 60
            seen: set[int] = set()
            boot_s = {}
            # every link heard, hovering: the take-off ends at 7 s (the time of each one's telemetry)
            while (len(seen) < 3 or min(boot_s.values(), default=0.0) < 7.0) and time.monotonic() < deadline \
                    and not stop.is_set():
                wait_readable([gcs], 0.2)
                for m in gcs.read():
                    seen |= {m.get_srcSystem()} if m.get_type() == "HEARTBEAT" else set()
                    if getattr(m, "time_boot_ms", None) is not None:
                        boot_s[m.get_srcSystem()] = m.time_boot_ms * 1e-3
            t0 = time.monotonic()
            _unkeyed_attacks(sent, stop, fleet_ports)
            gcs_result["attack_s"] = (t0, time.monotonic())
            # the keyed ground station sets and reads back a parameter on link 2 (through link 2's GCS port)
            gcs.transport.learn_peer(("127.0.0.1", fleet_ports.gcs_from(1)))
            gcs.send(load_dialect().MAVLink_param_set_message(2, 1, b"COM_OF_LOSS_T", 1.5, 9))
            end = time.monotonic() + 2.0
            while time.monotonic() < end:
                wait_readable([gcs], 0.1)
                for m in gcs.read():
                    if m.get_type() == "PARAM_VALUE" and m.param_id == "COM_OF_LOSS_T" and m.get_srcSystem() == 2:
                        gcs_result["value"] = m.param_value
            gcs_result["stats"] = dict(vars(gcs.stats), rejected_signing=gcs.stats.rejected_signing)
        finally:
            gcs.close()

    m = _launch_under(sc, tmp_path, fleet_ports, gcs_and_attacker)
    assert sent["correction"] == 200 and sent["heartbeat"] == 200 and sent["disarm"] == 100
    counters = m["mavlink"]
    # everything unsigned was rejected where it arrived, and counted
    assert counters["link2"]["rejected_unsigned"] >= sent["correction"] + sent["target"] + sent["disarm"]
    assert counters["companion"]["rejected_unsigned"] >= sent["heartbeat"]
    assert counters["companion"]["peer_kept"] == 0  # nothing to re-aim: no frame passed
    assert counters["link2"]["correction_rejected"] == 0 and counters["link2"]["signed"] > 500
    assert not m["crashed"] and m["min_altitude_m"] > 2.0
    # no link moved: the true tracking error in the attack window is what it is without attack
    log = np.load(tmp_path / "log.npz")
    err = np.linalg.norm(log["p_true"] - log["p_target"], axis=-1)
    hover = (log["t"] > 8.0)
    print("tracking error after take-off, max per link [m]:", err[hover].max(axis=0))
    assert err[hover].max() < 0.35  # a 0.35 m target or a 5 m correction would show here
    assert gcs_result.get("value") == pytest.approx(1.5)
    assert gcs_result["stats"]["signed"] > 100 and gcs_result["stats"]["rejected_signing"] == 0
    assert_ports_released(fleet_ports, 3)


def _crafted_states(sent: dict, stop: threading.Event, ports: FleetPorts, seconds: float = 4.0) -> None:
    """SKELETON_LINK_STATEs for link 2 with valid CRCs, from another process, at the companion's
    port for link 2 (PX4's 14541): NaN position, a covariance that is not positive definite, a stamp
    1000 s ahead, a replayed (old) stamp, and a plausible state 3 m above link 2 (its time and
    position read from its telemetry to the GCS port) with a 1e-6 covariance."""
    from companion.mavlink.codec import encode_link_state
    from companion.messages import LinkState
    as_link2 = D.MAVLink(None, srcSystem=2, srcComponent=1)
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", ports.gcs_port))
    gcs.settimeout(0.2)
    parser = D.MAVLink(None)
    parser.robust_parsing = True
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    seen = None
    q = np.array([1.0, 0.0, 0.0, 0.0])

    def send(state, key, P=None):
        st = state if P is None else replace(state, P=P)
        raw.sendto(encode_link_state(st).pack(as_link2), ("127.0.0.1", ports.companion(1)))
        sent[key] = sent.get(key, 0) + 1

    end = None
    try:
        while not stop.is_set() and (end is None or time.monotonic() < end):
            try:
                data = gcs.recv(4096)
            except socket.timeout:
                continue
            for m in parser.parse_buffer(data) or []:
                if m.get_type() == "LOCAL_POSITION_NED" and m.get_srcSystem() == 2:
                    seen = (m.time_boot_ms * 1e-3, np.array([m.y, m.x, -m.z]), time.monotonic())
            if seen is None or seen[0] < 8.0:
                continue  # after the take-off (it ends at 7 s): inside the metrics window
            end = end or time.monotonic() + seconds
            t_seen, p, at = seen
            # stamped where link 2's clock is now (the 10 Hz telemetry's time plus the wall time
            # since it came: about simulated time at --speed 0) and 0.08 s ahead: newer than its own
            # 50 Hz states, within the companion's 0.25 s stamp margin
            t = t_seen + min(time.monotonic() - at, 0.1)
            good = LinkState(1, t + 0.08, p + [0.0, 0.0, 3.0], np.zeros(3), q, np.zeros(3), np.eye(9) * 1e-6)
            send(good, "plausible_3m")
            send(replace(good, p_w_m=np.array([np.nan, 0.0, 2.5])), "nan")
            send(good, "non_pd", P=-np.eye(9))
            send(replace(good, time_s=t + 1000.0), "future")
            send(replace(good, time_s=max(t - 5.0, 0.5)), "replay")
            time.sleep(0.02)  # the pace of the crafted states: 50 Hz
    finally:
        gcs.close()
        raw.close()


def test_crafted_states_neither_stop_the_companion_nor_move_a_healthy_link(tmp_path, batch_reference, fleet_ports):
    """Crafted states at the companion (unsigned three_link.toml): it keeps stepping at
    20 Hz, rejects or leaves out every one, and the healthy links fly as without them."""
    sc = load_scenario(THREE_LINK, duration_s=16.0)
    sent: dict = {}
    m = _launch_under(sc, tmp_path, fleet_ports, lambda stop: _crafted_states(sent, stop, fleet_ports), join_s=10.0)
    assert min(sent.values()) > 100 and len(sent) == 5
    comp = json.loads((tmp_path / "companion" / "companion_summary.json").read_text())
    link2 = comp["links"]["2"]
    # NaN and non-PD: malformed; future: stamped too far ahead; replay: older than the last
    assert link2["rejected"] >= sent["nan"] + sent["non_pd"]
    assert link2["future"] >= sent["future"] and link2["replayed"] >= sent["replay"]
    # the plausible +3 m states: those used left link 2 out by the joint gate, never spread
    print("companion, link 2:", link2, "sent:", sent)
    assert link2["excluded_steps"].get("gate", 0) > 0
    # nor does anything forged (stamps ahead, "disarmed" flags) make the companion carry a link
    # (measured 0.0 s; a link alive but unheard for 60 ms of stamps would be)
    assert all(comp["links"][str(i)]["carried_s"] <= 0.1 for i in (1, 2, 3)), comp["links"]
    # the companion kept stepping at 20 Hz over the whole flight (no stall on a future stamp)
    assert comp["steps"] >= 0.9 * 20 * 16.0
    assert not m["crashed"]
    for i in (0, 2):  # the healthy links: within 2 cm of batch mode's RMS tracking
        assert m["rms_track_true_m"][i] < batch_reference["rms_track_true_m"][i] + 0.02, m["rms_track_true_m"]
    windows = m["uncorrected"]["windows"]
    assert windows and all(w["end_s"] >= w["start_s"] for w in windows)
    assert_ports_released(fleet_ports, 3)

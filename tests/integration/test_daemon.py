"""The companion daemon (the engine behind MAVLink ports), against fake flight controllers on loopback UDP.

The daemon's clock is a fake the test moves; the engine's decisions are tested in test_engine.py.
"""

from __future__ import annotations

import logging
import math
import socket
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from companion.config import CompanionConfig, CompanionSetup, LinkEndpoint, load_setup
from companion.configfile import ConfigError
from companion.daemon import CompanionDaemon
from companion.estimation.so3 import quat_from_euler_zyx
from companion.fleetnet.bus import zenoh_config
from companion.mavlink.codec import decode_correction, encode_link_state
from companion.mavlink.dialect import load_dialect
from companion.mavlink.port import MavlinkPort
from companion.fleetnet.certs import new_fleet_certs
from companion.fleetnet.config import new_users_file
from companion.mavlink.signing import new_key_file
from companion.mavlink.standard import encode_odometry
from companion.messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, LinkState
from companion.skeleton.body import SkeletonConfig
from companion.trajectory import TrajectoryConfig

from ..clocks import FakeClock
from ..paths import ROOT

D = load_dialect()


class Fleet:
    """``n`` fake autopilots (sysid i + 1) talking to one daemon."""

    def __init__(self, tmp_path, n=3, **companion):
        links = tuple(LinkEndpoint(i + 1, "udpin://127.0.0.1:0") for i in range(n))
        self.setup = CompanionSetup(name="daemon_test", skeleton=SkeletonConfig(n_links=n),
                                    companion=CompanionConfig(links=links, **{"arm": True, **companion}),
                                    trajectory=TrajectoryConfig(kind="bend"))
        self.clock = FakeClock()
        self.daemon = CompanionDaemon(self.setup, tmp_path / "companion", clock=self.clock)
        self.fcs = [MavlinkPort(f"udpout://127.0.0.1:{port.transport.local_port()}", system_id=i + 1)
                    for i, port in enumerate(self.daemon.ports)]
        self.inbox: list[list] = [[] for _ in range(n)]

    def pump(self, rounds=3, dt=0.01):
        for _ in range(rounds):
            self.daemon.poll(0.01)
            self.clock.t += dt
            for i, fc in enumerate(self.fcs):
                self.inbox[i] += fc.read()

    def take(self, i, kind):
        got = [m for m in self.inbox[i] if m.get_type() == kind]
        self.inbox[i] = [m for m in self.inbox[i] if m.get_type() != kind]
        return got

    def state(self, i, t, dx=0.0):
        n = len(self.fcs)
        p = np.array([(i - (n - 1) / 2) + dx, 0.0, 2.0])
        return LinkState(i, t, p, np.zeros(3), quat_from_euler_zyx(0.0, 0.0, 0.0), np.zeros(3),
                         np.diag([0.04] * 6 + [1e-3] * 3))

    def send_states(self, t, dx=(0.0, 0.0, 0.0)):
        for i, fc in enumerate(self.fcs):
            fc.send(encode_link_state(self.state(i, t, dx[i]), STATE_FLAG_EKF_OK))

    def close(self):
        self.daemon.close()
        for fc in self.fcs:
            fc.close()


@pytest.fixture
def fleet(tmp_path):
    f = Fleet(tmp_path)
    yield f
    f.close()


def test_stream_request_over_mavlink_until_acknowledged_and_heartbeats(fleet):
    for fc in fleet.fcs:
        fc.send(D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_GENERIC, 0, 0, 3, 3))
    fleet.pump()
    for i in range(3):
        req = fleet.take(i, "COMMAND_LONG")
        assert len(req) == 1 and req[0].command == D.MAV_CMD_SET_MESSAGE_INTERVAL
        assert req[0].param1 == D.MAVLINK_MSG_ID_SKELETON_LINK_STATE
        assert req[0].param2 == pytest.approx(1e6 / 50.0) and req[0].target_system == i + 1
        fleet.fcs[i].send(D.MAVLink_command_ack_message(D.MAV_CMD_SET_MESSAGE_INTERVAL, D.MAV_RESULT_ACCEPTED))
    fleet.pump()
    fleet.clock.t += 5.0  # a retry and a heartbeat are due
    for fc in fleet.fcs:
        fc.send(D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_GENERIC, 0, 0, 3, 3))
    fleet.pump()
    assert not fleet.take(0, "COMMAND_LONG")
    assert all(lk.stream_acked for lk in fleet.daemon.engine.links)
    hb = fleet.take(2, "HEARTBEAT")
    assert hb and hb[0].type == D.MAV_TYPE_ONBOARD_CONTROLLER and hb[0].get_srcSystem() == 190


def test_corrections_targets_and_arm_go_out_as_mavlink(fleet):
    for k in range(3):
        fleet.send_states(0.02 * k, dx=(0.0, 0.2, 0.0))
        fleet.pump()
    corr = [fleet.take(i, "SKELETON_CORRECTION") for i in range(3)]
    assert all(len(c) == 1 for c in corr)
    deltas = [decode_correction(c[0], i) for i, c in enumerate(corr)]
    assert deltas[0].ekf_time_s == 0.0 and deltas[1].dp_w_m[0] < -0.05
    targets = fleet.take(1, "SET_POSITION_TARGET_LOCAL_NED")
    assert targets and targets[0].target_system == 2 and targets[0].coordinate_frame == D.MAV_FRAME_LOCAL_NED
    assert fleet.take(1, "SET_ATTITUDE_TARGET")
    arm = [m for m in fleet.take(1, "COMMAND_LONG") if m.command == D.MAV_CMD_COMPONENT_ARM_DISARM]
    assert arm and arm[0].param1 == 1
    summary = fleet.daemon.summary()
    assert summary["steps"] == 1 and summary["links"]["2"]["rx_messages"] >= 3


def test_what_one_poll_sends_a_link_leaves_in_one_datagram(fleet):
    """A poll's messages for one link (its correction, its target's messages, a command) go as one
    UDP datagram: one wake-up of the flight controller, not one per message."""
    datagrams = []
    for k in range(3):
        fleet.send_states(0.02 * k, dx=(0.0, 0.2, 0.0))
        for _ in range(3):
            fleet.daemon.poll(0.01)
            fleet.clock.t += 0.01
            for fc in fleet.fcs:
                chunks = fc.transport.recv_chunks()
                assert len(chunks) <= 1
                parser = D.MAVLink(None)
                datagrams += [[m.get_type() for m in parser.parse_buffer(bytearray(data)) or []] for data, _ in chunks]
    assert any({"SET_POSITION_TARGET_LOCAL_NED", "SET_ATTITUDE_TARGET"} <= set(kinds) for kinds in datagrams)
    assert sum(kinds.count("SKELETON_CORRECTION") for kinds in datagrams) == 3


@pytest.mark.parametrize("bad", ["nan", "not_pd", "not_unit", "wrong_sysid"])
def test_bad_states_are_rejected_and_the_daemon_keeps_going(fleet, bad):
    fleet.send_states(0.0)
    fleet.pump()
    fleet.take(1, "SKELETON_CORRECTION")
    good = encode_link_state(fleet.state(1, 0.02), STATE_FLAG_EKF_OK)
    if bad == "nan":
        good.p_ned = [math.nan, 0.0, 0.0]
    elif bad == "not_pd":
        good.covariance = [-1.0] + list(good.covariance[1:])
    elif bad == "not_unit":
        good.q = [0.9, 0.0, 0.0, 0.0]
    if bad == "wrong_sysid":
        stranger = MavlinkPort(f"udpout://127.0.0.1:{fleet.daemon.ports[1].transport.local_port()}", system_id=9)
        stranger.send(good)
        stranger.close()
    else:
        fleet.fcs[1].send(good)
    fleet.pump()
    link = fleet.daemon.engine.links[1]
    assert link.state.time_s == 0.0  # the bad state was not used
    if bad == "wrong_sysid":
        assert fleet.daemon.ports[1].stats.ignored >= 1 and link.rejected == 0
    else:
        assert link.rejected == 1
    for t in (0.02, 0.04, 0.06):  # still running: the next good states give the next step
        fleet.send_states(t)
        fleet.pump()
    assert fleet.take(1, "SKELETON_CORRECTION")
    table = fleet.daemon.health_table(1.0)
    assert "rejected" in table.splitlines()[0] and len(table.splitlines()) == 4


def test_standard_mode_reads_odometry_and_answers_with_vision_odometry(tmp_path):
    fleet = Fleet(tmp_path, n=2, mode="standard")
    try:
        for k in range(2):
            for i, fc in enumerate(fleet.fcs):
                st = fleet.state(i, 0.02 * k, dx=0.1 if i else 0.0)
                fc.send(encode_odometry(st, int(round(st.time_s * 1e6)), estimator_type=D.MAV_ESTIMATOR_TYPE_NAIVE))
            fleet.pump()
        vision = fleet.take(1, "ODOMETRY")
        assert vision and vision[0].frame_id == D.MAV_FRAME_LOCAL_NED and vision[0].child_frame_id == D.MAV_FRAME_BODY_FRD
        assert vision[0].estimator_type == D.MAV_ESTIMATOR_TYPE_VISION and vision[0].time_usec == 0
        assert 0.5 < vision[0].y < 0.599  # link 2 (y_ned = x_enu = 0.5 + 0.1) pulled back towards the chain
        assert math.isnan(vision[0].rollspeed)  # external vision has no body rates
        assert not fleet.take(1, "SKELETON_CORRECTION")
    finally:
        fleet.close()


def test_standard_mode_with_a_stock_px4s_odometry_heartbeat_and_setpoints(tmp_path):
    """A stock PX4 as it speaks: ODOMETRY in its own form (velocity in LOCAL_NED, variances only,
    NaN elsewhere) is read; its HEARTBEAT says whether it is armed, so a companion that arms links
    (SITL) stops at an armed one; its targets are SET_POSITION_TARGET_LOCAL_NED with the heading
    and no SET_ATTITUDE_TARGET (an attitude setpoint with a thrust of its own on PX4)."""
    fleet = Fleet(tmp_path, n=2, mode="standard")
    try:
        armed = D.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | D.MAV_MODE_FLAG_SAFETY_ARMED
        for fc in fleet.fcs:  # link 2 armed (by its pilot), link 1 not
            base = armed if fc.mav.srcSystem == 2 else D.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            fc.send(D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_PX4, base, 0, 3, 3))
        for k in range(3):
            for i, fc in enumerate(fleet.fcs):
                st = fleet.state(i, 0.02 * k, dx=0.1 if i else 0.0)
                fc.send(encode_odometry(st, int(round(st.time_s * 1e6)), estimator_type=D.MAV_ESTIMATOR_TYPE_AUTOPILOT,
                                        px4=True))
            fleet.pump()
        links = fleet.daemon.engine.links
        assert [lk.rejected for lk in links] == [0, 0] and all(lk.state is not None for lk in links)
        assert [bool(lk.flags & STATE_FLAG_ARMED) for lk in links] == [False, True]
        assert fleet.take(1, "ODOMETRY")  # its corrections, as external vision
        arms = [[m for m in fleet.take(i, "COMMAND_LONG") if m.command == D.MAV_CMD_COMPONENT_ARM_DISARM]
                for i in range(2)]
        assert arms[0] and not arms[1]  # (the default arm = true of a SITL config)
        targets = fleet.take(1, "SET_POSITION_TARGET_LOCAL_NED")
        assert targets and targets[-1].type_mask == 0  # position, velocity, acceleration, yaw and its rate
        assert targets[-1].yaw == pytest.approx(math.pi / 2, abs=1e-6)  # ENU yaw 0: facing east
        assert not fleet.take(1, "SET_ATTITUDE_TARGET") and not fleet.take(1, "SKELETON_TARGET_FEEDFORWARD")
    finally:
        fleet.close()


@pytest.mark.parametrize("mode", ["standard", "dialect"])
def test_standard_mode_answers_px4s_timesync_on_px4s_clock(tmp_path, caplog, mode):
    """PX4 asks for TIMESYNC (10 Hz on an onboard link) and, once converged, adds the offset it
    measured to the stamps of the external vision it receives. The companion learns the
    autopilot's clock from its own requests and answers on that clock, so the offset PX4 measures
    is zero and the corrections keep their stamps: the time of the autopilot's state they correct.
    Before it has learnt the clock it does not answer (PX4 stamps on arrival, as without it); nor
    once PX4 rebooted, until it has learnt the new clock. The dialect's firmware takes the
    corrections on its own clock: no TIMESYNC there."""
    fleet = Fleet(tmp_path, n=1, mode=mode)
    fc, clock = fleet.fcs[0], fleet.clock
    boot_s = clock.t - 42.0  # the autopilot's clock counts from its boot, 42 s before

    def fc_ns():
        return int(round((clock.t - boot_s) * 1e9))

    def px4_answers():  # PX4's Timesync: a request (tc1 = 0) answered with its clock
        for m in fleet.take(0, "TIMESYNC"):
            assert m.tc1 == 0
            fc.send(D.MAVLink_timesync_message(fc_ns(), m.ts1))

    try:
        fc.send(D.MAVLink_timesync_message(0, fc_ns()))
        fleet.pump(rounds=1, dt=0.001)
        got = fleet.take(0, "TIMESYNC")
        if mode == "dialect":
            fleet.pump(rounds=5, dt=0.1)
            assert not got and not fleet.take(0, "TIMESYNC")
            assert "timesync" not in fleet.daemon.summary()["links"]["1"]
            return
        assert all(m.tc1 == 0 for m in got)  # no answer to PX4's request yet (its own requests only)
        for _ in range(8):  # the companion's requests at 10 Hz, each answered within a millisecond
            clock.t += 0.1
            fleet.pump(rounds=1, dt=0.001)
            px4_answers()
            fleet.pump(rounds=1, dt=0.001)
        report = fleet.daemon.summary()["links"]["1"]["timesync"]
        assert report["synchronised"] and report["taken"] >= 5 and report["unknown"] == report["slow"] == 0
        assert report["offset_ms"] == pytest.approx(-boot_s * 1e3, abs=1.0)
        ts1 = fc_ns()
        fc.send(D.MAVLink_timesync_message(0, ts1))  # PX4's request
        fleet.pump(rounds=1, dt=0.001)
        answers = [m for m in fleet.take(0, "TIMESYNC") if m.tc1 != 0]
        assert len(answers) == 1 and answers[0].ts1 == ts1
        px4_offset_ns = (ts1 + fc_ns() - 2 * answers[0].tc1) // 2  # what PX4's filter is fed
        assert abs(px4_offset_ns) <= 1_000_000
        boot_s = clock.t - 3.0  # PX4 rebooted: its next request, on its new clock, is not answered
        with caplog.at_level(logging.WARNING, logger="companion.daemon"):
            fc.send(D.MAVLink_timesync_message(0, fc_ns()))
            fleet.pump(rounds=1, dt=0.001)
        assert not [m for m in fleet.take(0, "TIMESYNC") if m.tc1 != 0]
        report = fleet.daemon.summary()["links"]["1"]["timesync"]
        assert report["restarts"] == 1 and not report["synchronised"] and "clock restarted" in caplog.text
    finally:
        fleet.close()


def test_standard_mode_warns_once_when_no_link_answers_timesync(tmp_path, caplog):
    """A link that never answers (a PX4 port not in onboard mode, a wire too slow for a 10 ms round
    trip): the user is told once that PX4 stamps the corrections on arrival."""
    fleet = Fleet(tmp_path, n=1, mode="standard")
    try:
        fleet.fcs[0].send(D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_PX4, 0, 0, 3, 3))
        with caplog.at_level(logging.WARNING, logger="companion.daemon"):
            for _ in range(30):
                fleet.pump(rounds=1, dt=1.0)
        assert caplog.text.count("no TIMESYNC answer") == 1 and "EKF2_EV_DELAY" in caplog.text
        requests = fleet.take(0, "TIMESYNC")
        assert requests and all(m.tc1 == 0 for m in requests)
    finally:
        fleet.close()


def test_arming_real_flight_controllers_is_refused_and_off_unless_asked_for():
    serial = (LinkEndpoint(1, "serial:///dev/ttyACM0:921600"), LinkEndpoint(2, "udpin://127.0.0.1:14541"))
    with pytest.raises(ValueError, match="arm = true with flight controllers on serial links"):
        CompanionConfig(links=serial, arm=True)
    assert not CompanionConfig(links=serial, arm=False).arm
    # a companion's config arms nothing unless it says so (a Pixhawk on Ethernet is a UDP link);
    # a SITL scenario's companion arms its simulated links unless it says not to
    assert not CompanionConfig().arm and not CompanionConfig(links=serial[1:]).arm
    from sitl.scenario import load_scenario

    assert load_scenario(ROOT / "configs" / "sitl" / "chain" / "three_link.toml").companion.arm
    assert not load_scenario(ROOT / "configs" / "sitl" / "chain" / "seven_link_static.toml").companion.arm


@pytest.mark.parametrize("name, n", [("three_link_rpi", 3), ("seven_link_rpi", 7)])
def test_hardware_configs_load_and_the_daemon_waits_for_missing_devices(tmp_path, caplog, name, n):
    sc = load_setup(CompanionSetup, ROOT / "configs" / "hardware" / f"{name}.toml")
    links = sc.companion.links
    assert [lk.system_id for lk in links] == list(range(1, n + 1))
    assert all(lk.url.startswith("serial:///dev/serial/by-id/") and lk.url.endswith(":921600") for lk in links)
    assert not sc.companion.arm and sc.companion.targets == "none"  # never arms or steers real vehicles
    assert sc.companion.time_base == "gps"  # Pixhawks booted at different times
    # signed links, with a key file named by the config (never in the repository)
    assert sc.signing.mode == "required" and sc.signing.key_file.endswith("keys/skeleton.key")
    with pytest.raises(ValueError, match="cannot read the signing key"):
        CompanionDaemon(sc, tmp_path)
    new_key_file(tmp_path / "skeleton.key")
    sc = replace(sc, signing=replace(sc.signing, key_file=str(tmp_path / "skeleton.key")))
    group = None
    if sc.companion.distributed:  # the Pi of group 2; its Zenoh session config is valid as written
        assert sc.zenoh.users_file.endswith("keys/zenoh_users.txt")  # the Pis authenticate
        assert sc.zenoh.tls.certs_dir.endswith("keys/certs") and sc.zenoh.tls.mtls  # with mutual TLS
        assert all(ep.startswith("tls/") for ep in sc.zenoh.endpoints)
        users = tmp_path / "zenoh_users.txt"
        new_users_file(users, 3)
        certs = tmp_path / "certs"  # as the config's comment says, plus loopback and an address not up for this test
        hosts = [f"{ep.split('/')[1].split(':')[0]},127.0.0.1,10.255.255.1" for ep in sc.zenoh.endpoints]
        new_fleet_certs(certs, 3, hosts)
        sc = replace(sc, zenoh=replace(sc.zenoh, users_file=str(users), tls=replace(sc.zenoh.tls, certs_dir=str(certs))))
        zenoh_config(sc.zenoh, 1, 3, "seven_link_rpi.toml")
        group = 1
        ports = [_free_tcp_port() for _ in range(3)]
        # a Pi whose network is not up: its address is waited for as long as asked (--duration), then named
        down = replace(sc, zenoh=replace(sc.zenoh, endpoints=tuple(f"tls/10.255.255.1:{p}" for p in ports)))
        (tmp_path / "down").mkdir()
        with pytest.raises(ConfigError) as info:
            CompanionDaemon(down, tmp_path / "down", group=group, bus_wait_s=1.0)
        assert info.value.key == "zenoh.listen" and "Cannot assign requested address" in info.value.reason
        caplog.clear()
        sc = replace(sc, zenoh=replace(sc.zenoh, endpoints=tuple(f"tls/127.0.0.1:{p}" for p in ports)))
    daemon = CompanionDaemon(sc, tmp_path, group=group)  # the Pixhawks are not plugged in here
    served = n if group is None else len(sc.companion.group_layout(n)[group])
    try:
        for _ in range(3):
            daemon.poll(0.01)
        table = daemon.health_table(1.0).splitlines()
        assert len(table) == served + 1 and all(" down " in row for row in table[1:])
        assert all(port.signing_mode == "required" for port in daemon.ports)
        assert caplog.text.count("cannot open: no such device") == served
    finally:
        daemon.close()


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "numpy"])
def test_the_daemon_loads_its_compiled_kernels_before_its_ports_open(tmp_path, monkeypatch, caplog, compiled):
    """With the compiled kernels on, the daemon loads (or compiles) every one of them (the CPG's
    for a CPG flight) before it opens its ports: a launcher that waits for its ports finds it ready
    to fly, and a first cycle that loaded them would stall the chain's corrections. Without them
    (the onboard install) nothing is loaded."""
    import signal

    import companion.daemon as daemon_module
    from companion.kernels import warm  # (what the daemon loads)

    calls = []
    monkeypatch.setattr(warm, "ENABLED", compiled)
    monkeypatch.setattr(warm, "warm_up", lambda **kw: calls.append(("warm", kw)) or 0.5)

    def port(*args, **kwargs):
        calls.append(("port", {}))
        return MavlinkPort(*args, **kwargs)

    monkeypatch.setattr(daemon_module, "MavlinkPort", port)
    fleet = Fleet(tmp_path)
    daemon = fleet.daemon
    assert calls == ([("warm", {"cpg": False})] if compiled else []) + [("port", {})] * 3
    cpg = SimpleNamespace(trajectory=SimpleNamespace(kind="cpg"))  # (a CPG flight's: the CPG's kernels too)
    assert daemon_module._warm_kernels(cpg) == (0.5 if compiled else None)
    assert calls[-1:] == ([("warm", {"cpg": True})] if compiled else [("port", {})])
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        with caplog.at_level(logging.INFO, logger="companion.daemon"):
            daemon.run(duration_s=0.0)  # (no cycle: the loop ends at once; run closes the daemon)
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        for fc in fleet.fcs:
            fc.close()
    assert ("compiled kernels ready in 0.5 s" in caplog.text) == compiled
    assert ("numpy path (no compiled kernels)" in caplog.text) != compiled


def test_the_daemon_leaves_its_flight_as_mcap(fleet):
    """companion.mcap: the states taken in and the corrections sent at each step, the health report
    and a link's STATUSTEXT, every message on the companion's time base, read back with mcap's reader."""
    import json as _json

    from mcap.reader import make_reader

    for k in range(6):
        fleet.send_states(0.02 * k, dx=(0.0, 0.2, 0.0))
        fleet.pump()
    fleet.fcs[1].send(D.MAVLink_statustext_message(D.MAV_SEVERITY_WARNING, b"GPS glitch: position rejected"))
    fleet.pump()
    fleet.daemon.health_table(5.0)
    steps = fleet.daemon.step_log()
    fleet.daemon.write_log()
    with open(fleet.daemon.out_dir / "companion.mcap", "rb") as f:
        messages = [(ch.topic, m.log_time, _json.loads(m.data)) for _, ch, m in make_reader(f).iter_messages()]
    topics = {t for t, _, _ in messages}
    assert topics == {"/companion/step", "/statustext",
                      *(f"/link{i}/{k}" for i in (1, 2, 3) for k in ("state_in", "corrected", "correction", "health"))}
    step_ns = np.round(steps["t_sckf"] * 1e9).astype(np.int64).tolist()
    assert [ns for t, ns, _ in messages if t == "/link2/state_in"] == step_ns
    moves = [m["delta_p_m"] for t, _, m in messages if t == "/link2/correction"]
    np.testing.assert_allclose(moves, steps["p_corr_sckf"][:, 1] - steps["p_ekf_sckf"][:, 1])
    assert moves[0][0] < -0.05  # link 2, 0.2 m off the chain, pulled back
    [(_, _, text)] = [x for x in messages if x[0] == "/statustext"]
    assert text["name"] == "link 2" and text["level"] == 3 and text["message"] == "GPS glitch: position rejected"
    [(_, _, health)] = [x for x in messages if x[0] == "/link1/health"]
    assert health["rejected"] == 0 and health["left_out"] == 0.0 and health["state_hz"] > 0

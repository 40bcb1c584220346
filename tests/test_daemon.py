"""The companion daemon in-process, against fake flight controllers on loopback UDP."""

from __future__ import annotations

import math
import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from companion.daemon import CompanionDaemon
from companion.estimation.so3 import quat_from_euler_zyx
from companion.fleetnet.bus import zenoh_config
from companion.mavlink.codec import STATE_FLAG_EKF_OK, decode_correction, encode_link_state
from companion.mavlink.dialect import load_dialect
from companion.mavlink.frames import quat_enu_flu_to_ned_frd
from companion.mavlink.port import MavlinkPort
from companion.messages import LinkState
from sitl.scenario import LinkEndpoint, load_scenario

ROOT = Path(__file__).resolve().parents[1]
D = load_dialect()


class Fleet:
    """``n`` fake autopilots (sysid i + 1) talking to one daemon."""

    def __init__(self, tmp_path, n=3, **companion):
        sc = load_scenario(ROOT / "configs" / "sitl" / "three_link.toml")
        links = tuple(LinkEndpoint(i + 1, "udpin://127.0.0.1:0") for i in range(n))
        sc = replace(sc, skeleton=replace(sc.skeleton, n_links=n),
                     companion=replace(sc.companion, links=links, groups=(), **companion))
        self.sc = sc
        self.daemon = CompanionDaemon(sc, tmp_path / "companion")
        self.fcs = [MavlinkPort(f"udpout://127.0.0.1:{lk.port.transport.local_port()}", system_id=i + 1)
                    for i, lk in enumerate(self.daemon.links)]
        self.inbox: list[list] = [[] for _ in range(n)]
        self.L = sc.skeleton.link_length_m

    def pump(self, rounds=3):
        for _ in range(rounds):
            self.daemon.poll(0.01)
            for i, fc in enumerate(self.fcs):
                self.inbox[i] += fc.read()

    def take(self, i, kind):
        got = [m for m in self.inbox[i] if m.get_type() == kind]
        self.inbox[i] = [m for m in self.inbox[i] if m.get_type() != kind]
        return got

    def state(self, i, t, dx=0.0, P=None):
        n = len(self.fcs)
        p = np.array([(i - (n - 1) / 2) * self.L + dx, 0.0, 2.0])
        return LinkState(i, t, p, np.zeros(3), quat_from_euler_zyx(0.0, 0.0, 0.0), np.zeros(3),
                         np.diag([0.04] * 6 + [1e-3] * 3) if P is None else P)

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


def test_stream_rate_request_until_acknowledged(fleet):
    for fc in fleet.fcs:
        fc.send(D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_GENERIC, 0, 0, 3, 3))
    fleet.pump()
    for i in range(3):
        req = fleet.take(i, "COMMAND_LONG")
        assert len(req) == 1 and req[0].command == D.MAV_CMD_SET_MESSAGE_INTERVAL
        assert req[0].param1 == D.MAVLINK_MSG_ID_SKELETON_LINK_STATE
        assert req[0].param2 == pytest.approx(1e6 / fleet.sc.companion.state_rate_hz)
        assert req[0].target_system == i + 1
        fleet.fcs[i].send(D.MAVLink_command_ack_message(D.MAV_CMD_SET_MESSAGE_INTERVAL, D.MAV_RESULT_ACCEPTED))
    fleet.pump()
    fleet.daemon.links[0].stream_sent_wall -= 5.0  # a retry would be due now, were it not acknowledged
    for fc in fleet.fcs:
        fc.send(D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_GENERIC, 0, 0, 3, 3))
    fleet.daemon._next_heartbeat_wall = 0.0  # the 1 Hz heartbeat is due (its first went out before any peer was known)
    fleet.pump()
    assert not fleet.take(0, "COMMAND_LONG")
    assert all(lk.stream_acked for lk in fleet.daemon.links)
    hb = fleet.take(2, "HEARTBEAT")
    assert hb and hb[0].type == D.MAV_TYPE_ONBOARD_CONTROLLER and hb[0].get_srcSystem() == 190


def test_step_on_flight_controller_time_sends_corrections_targets_and_arm(fleet):
    # link 2 is 0.2 m off the chain: the step pulls it back, and all three get a delta
    for k in range(3):
        fleet.send_states(0.02 * k, dx=(0.0, 0.2, 0.0))
        fleet.pump()
    corr = [fleet.take(i, "SKELETON_CORRECTION") for i in range(3)]
    assert all(len(c) == 1 for c in corr)  # 20 Hz on FC time: one step in 0.04 s
    deltas = [decode_correction(c[0], i) for i, c in enumerate(corr)]
    assert deltas[0].ekf_time_s == 0.0 and deltas[0].seq == deltas[1].seq
    assert deltas[1].dp_w_m[0] < -0.05  # link 2 moved back towards the chain
    assert deltas[0].dp_w_m[0] > 0.0 and deltas[2].dp_w_m[0] > 0.0  # its neighbours meet it
    targets = fleet.take(1, "SET_POSITION_TARGET_LOCAL_NED")
    assert targets and targets[0].target_system == 2 and targets[0].coordinate_frame == D.MAV_FRAME_LOCAL_NED
    assert fleet.take(1, "SET_ATTITUDE_TARGET")
    arm = [m for m in fleet.take(1, "COMMAND_LONG") if m.command == D.MAV_CMD_COMPONENT_ARM_DISARM]
    assert arm and arm[0].param1 == 1
    # the next step waits for every link's state at its time
    fleet.fcs[0].send(encode_link_state(fleet.state(0, 0.06), STATE_FLAG_EKF_OK))
    fleet.pump()
    assert not fleet.take(0, "SKELETON_CORRECTION")
    for i in (1, 2):
        fleet.fcs[i].send(encode_link_state(fleet.state(i, 0.06), STATE_FLAG_EKF_OK))
    fleet.pump()
    nxt = decode_correction(fleet.take(0, "SKELETON_CORRECTION")[0], 0)
    assert nxt.ekf_time_s == pytest.approx(0.06) and nxt.seq == deltas[0].seq + 1


def test_links_on_different_clocks_get_no_corrections(fleet, caplog):
    """Pixhawks booted at different times (or a link that stopped): no extrapolation over seconds."""
    for k in range(3):
        for i, fc in enumerate(fleet.fcs):
            fc.send(encode_link_state(fleet.state(i, 0.02 * k + (12.5 if i == 2 else 0.0)), STATE_FLAG_EKF_OK))
        fleet.pump()
    assert not any(fleet.take(i, "SKELETON_CORRECTION") for i in range(3))
    assert fleet.daemon.withheld >= 1 and fleet.daemon.summary()["withheld_steps"] == fleet.daemon.withheld
    assert "link 1's newest state is 12.500 s behind" in caplog.text and "time base" in caplog.text


def test_gps_time_base_aligns_pixhawks_booted_at_different_times(tmp_path, caplog):
    """Real Pixhawks count from their own boot; SYSTEM_TIME maps each onto GPS time."""
    caplog.set_level("INFO", logger="companion.daemon")
    f = Fleet(tmp_path, time_base="gps")
    boot = [0.0, 7.25, 31.5]  # link i's clock reads t + boot[i] at GPS time t (since 1.8e9 s)
    unix0 = 1_800_000_000.0
    try:
        for k in range(3):  # states alone are not used until the link's offset is known
            for i, fc in enumerate(f.fcs):
                fc.send(encode_link_state(f.state(i, 0.02 * k + boot[i], dx=0.2 * (i == 1)), STATE_FLAG_EKF_OK))
            f.pump()
        assert not any(f.take(i, "SKELETON_CORRECTION") for i in range(3))
        for i, fc in enumerate(f.fcs):
            fc.send(D.MAVLink_system_time_message(0, int((boot[i] + 0.04) * 1000)))  # no fix yet: ignored
            fc.send(D.MAVLink_system_time_message(int((unix0 + 0.05) * 1e6), int((boot[i] + 0.05) * 1000)))
        f.pump()
        assert [lk.offset_us for lk in f.daemon.links] == [int((unix0 - b) * 1e6) for b in boot]
        for k in range(3, 6):
            for i, fc in enumerate(f.fcs):
                fc.send(encode_link_state(f.state(i, 0.02 * k + boot[i], dx=0.2 * (i == 1)), STATE_FLAG_EKF_OK))
            f.pump()
        corr = [[decode_correction(m, i) for m in f.take(i, "SKELETON_CORRECTION")] for i in range(3)]
        assert all(len(c) == 1 for c in corr)
        for i in range(3):  # stamped on each link's own clock, the step at GPS time unix0 + 0.1 s
            assert corr[i][0].ekf_time_s == pytest.approx(0.10 + boot[i], abs=1e-6)
        assert corr[1][0].dp_w_m[0] < -0.05  # the same correction as with one clock
        assert f.daemon.withheld == 0 and "boot clock + " in caplog.text
    finally:
        f.close()


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
        stranger = MavlinkPort(f"udpout://127.0.0.1:{fleet.daemon.links[1].port.transport.local_port()}", system_id=9)
        stranger.send(good)
        stranger.close()
    else:
        fleet.fcs[1].send(good)
    fleet.pump()
    link = fleet.daemon.links[1]
    assert link.state.time_s == 0.0  # the bad state was not used
    if bad == "wrong_sysid":
        assert link.port.stats.ignored >= 1 and link.rejected == 0
    else:
        assert link.rejected == 1
    # still running: the next good states give the next step
    for t in (0.02, 0.04, 0.06):
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
                fc.send(D.MAVLink_odometry_message(
                    time_usec=int(round(st.time_s * 1e6)), frame_id=D.MAV_FRAME_LOCAL_NED,
                    child_frame_id=D.MAV_FRAME_BODY_FRD, x=st.p_w_m[1], y=st.p_w_m[0], z=-st.p_w_m[2],
                    q=quat_enu_flu_to_ned_frd(st.q_wxyz).tolist(), vx=0.0, vy=0.0, vz=0.0,
                    rollspeed=0.0, pitchspeed=0.0, yawspeed=0.0,
                    pose_covariance=_upper6(np.diag([0.04] * 3 + [1e-3] * 3)),
                    velocity_covariance=_upper6(np.diag([0.04] * 3 + [1e-3] * 3)),
                    reset_counter=0, estimator_type=D.MAV_ESTIMATOR_TYPE_NAIVE, quality=100))
            fleet.pump()
        vision = fleet.take(1, "ODOMETRY")
        assert vision and vision[0].frame_id == D.MAV_FRAME_LOCAL_FRD
        assert vision[0].estimator_type == D.MAV_ESTIMATOR_TYPE_VISION and vision[0].time_usec == 0
        assert 0.5 < vision[0].y < 0.599  # link 2 (y_ned = x_enu = 0.5 + 0.1) pulled back towards the chain
        assert not fleet.take(1, "SKELETON_CORRECTION")
    finally:
        fleet.close()


def _upper6(M):
    return M[np.triu_indices(6)].tolist()


@pytest.mark.parametrize("name, n", [("three_link_rpi", 3), ("seven_link_rpi", 7)])
def test_hardware_configs_load_and_the_daemon_waits_for_missing_devices(tmp_path, caplog, name, n):
    sc = load_scenario(ROOT / "configs" / "hardware" / f"{name}.toml")
    links = sc.companion.links
    assert [lk.system_id for lk in links] == list(range(1, n + 1))
    assert all(lk.url.startswith("serial:///dev/serial/by-id/") and lk.url.endswith(":921600") for lk in links)
    assert not sc.companion.arm and sc.companion.targets == "none"  # never arms or steers real vehicles
    assert sc.companion.time_base == "gps"  # Pixhawks booted at different times
    group = None
    if sc.companion.distributed:  # the Pi of group 2; its Zenoh session config is valid as written
        zenoh_config(sc.zenoh, 1, 3, "seven_link_rpi.toml")
        group = 1
        ports = [_free_tcp_port() for _ in range(3)]
        sc = replace(sc, zenoh=replace(sc.zenoh, endpoints=tuple(f"tcp/127.0.0.1:{p}" for p in ports)))
    daemon = CompanionDaemon(sc, tmp_path, group=group)  # the Pixhawks are not plugged in here
    served = n if group is None else len(sc.companion.group_layout(n)[group])
    try:
        for _ in range(3):
            daemon.poll(0.01)
        table = daemon.health_table(1.0).splitlines()
        assert len(table) == served + 1 and all(" down " in row for row in table[1:])
        assert caplog.text.count("cannot open: no such device") == served
    finally:
        daemon.close()


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]

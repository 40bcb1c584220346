"""Neighbour poses over real Zenoh sessions on loopback: the vision consumer (``run_node`` with
``[[neighbours]]``) publishes what a chain camera sees of its neighbour's marker, a companion's
:class:`~companion.fleetnet.inbox.MessageInbox` takes it; hostile payloads and poses
on another link's key are counted and dropped; in a fleet with a users file, a session without
its credentials delivers nothing."""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import pytest

from companion.fleetnet import codec
from companion.fleetnet.config import ZenohConfig, new_users_file
from companion.fleetnet.keys import neighbour_key
from companion.vision.config import PipelineConfig
from companion.vision.node_config import NeighbourCamera, VisionNodeSetup, ZenohCameraSource

from ..camera_frames import marker_frame
from ..fleetnet_cases import neighbour_pose
from ..ports import free_ports
from ..waits import wait_for
from ..zenoh_peers import peer_session

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("cv2")

PREFIX = "nbtest"
CAMERA = NeighbourCamera("cam1", observer=1, observed=2, marker_id=7, camera_pos_b_m=(0.45, 0.0, 0.05),
                         camera_q_bc_wxyz=(0.5, -0.5, 0.5, -0.5), marker_pos_b_m=(-0.45, 0.0, 0.06))


def _through_the_consumer(tmp_path, kind: str, rogue: list[tuple[str, bytes]], **setup_fields):
    """Three frames of vehicle 1's camera (each waited for until its message reaches the inbox)
    and two of vehicle 2's go through a consumer configured with ``setup_fields``; then a rogue
    session puts ``rogue`` (key, payload) on the companion's session. Returns the consumer's
    summary, the messages the ``kind`` inbox delivered, its summary and the consumer's frame log."""
    from companion.fleetnet.inbox import MessageInbox
    from companion.vision.camera_wire import CameraPublisher
    from companion.vision.node import FRAMES_FILE, read_frame_log, run_node

    cam_ep, comp_ep = (f"tcp/127.0.0.1:{p}" for p in free_ports(2))
    harness = peer_session(listen=(cam_ep,))
    companion = peer_session(listen=(comp_ep,))
    inbox = MessageInbox(companion, PREFIX, kind)
    setup = VisionNodeSetup(name="t", source="zenoh", zenoh=ZenohCameraSource(prefix=PREFIX, connect=(cam_ep, comp_ep)),
                            pipeline=PipelineConfig(marker_length_m=0.2), **setup_fields)
    frames_log = tmp_path / FRAMES_FILE
    stop = threading.Event()
    result = {}

    def measured_all() -> bool:
        return stop.is_set() or (frames_log.exists() and frames_log.read_text().count("\n") >= 5)

    worker = threading.Thread(target=lambda: result.update(run_node(setup, tmp_path, stop=measured_all)))
    got = []
    try:
        pubs = [CameraPublisher(harness, PREFIX, v, fmt="png") for v in range(2)]
        worker.start()
        assert wait_for(lambda: all(p.matched for p in pubs), 10.0), "the consumer never subscribed"
        for seq in range(3):
            pubs[0].publish(marker_frame(vehicle=0, seq=seq))
            assert wait_for(lambda: (got.extend(inbox.drain()), len(got) > seq)[1], 10.0), f"message {seq} lost"
        for seq in range(2):
            pubs[1].publish(marker_frame(vehicle=1, seq=seq))
        worker.join(15)
        assert not worker.is_alive()
        session = peer_session(connect=(comp_ep,))
        try:
            assert wait_for(lambda: session.info.peers_zid(), 5.0)
            for key, payload in rogue:
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_for(lambda: (got.extend(inbox.drain()), inbox.counts["received"] >= 3 + len(rogue))[1], 5.0)
        finally:
            session.close()
    finally:
        stop.set()
        inbox.close()
        companion.close()
        harness.close()
    return result, got, inbox.summary(), [r for r in read_frame_log(frames_log) if r["camera"] == "cam1"]


def test_the_consumer_publishes_neighbour_poses_and_the_inbox_takes_them(tmp_path):
    """Three frames of link 1's camera and two of a camera named as link 1's but on vehicle 2
    (a wrong configuration: counted, not published) go through the consumer; the companion's
    inbox gets the three poses as measured, with the mounts and capture times. Garbage and a
    valid pose on another link's key are counted as rejected and never delivered."""
    rogue = [(neighbour_key(PREFIX, 0), b"ASKZ" + bytes([codec.VERSION, 7]) + b"\0" * 10),  # truncated
             (neighbour_key(PREFIX, 2), codec.encode(neighbour_pose(np.random.default_rng(1), 0, 1))),  # link 3's key
             (neighbour_key(PREFIX, 0), codec.encode(neighbour_pose(np.random.default_rng(2), 0, 1)))]  # delivered
    result, got, summary, measured = _through_the_consumer(tmp_path, "neighbour pose", rogue,
                                                           neighbours=(CAMERA, replace(CAMERA, camera="cam2")))
    assert result["neighbour_poses"] == {"published": 3, "wrong_vehicle": 2}
    assert summary == {"received": 6, "delivered": 4, "rejected": 2, "overflow": 0,
                       "reasons": {"NeighbourPose.t_capture_s": 1, "NeighbourPose does not belong on this key": 1}}
    for pose, rec in zip(got[:3], measured):
        assert (pose.observer, pose.observed, pose.seq, pose.t_capture_s) == (0, 1, rec["seq"], rec["t_capture_s"])
        np.testing.assert_allclose(pose.t_cm_m, rec["poses"][0]["t_cm_m"], atol=1e-12)
        np.testing.assert_allclose(pose.q_cm_wxyz, rec["poses"][0]["q_cm_wxyz"], atol=1e-12)
        np.testing.assert_allclose(pose.cov_c, np.reshape(rec["poses"][0]["cov"], (6, 6)), atol=1e-15)
        np.testing.assert_allclose(pose.camera_pos_b_m, CAMERA.camera_pos_b_m)
        np.testing.assert_allclose(pose.q_bc_wxyz, CAMERA.camera_q_bc_wxyz)
    assert [p.seq for p in got] == [0, 1, 2, 42]


def test_a_session_without_the_fleets_credentials_delivers_no_neighbour_pose(tmp_path):
    """A centralised companion's inbox (``[zenoh] vision_session``) with a users file: a session
    with no credentials, or a wrong password, opens no transport and delivers nothing; one with
    group 1's user and password delivers its pose."""
    from companion.fleetnet.bus import peer_config
    from companion.fleetnet.credentials import group_credentials
    from companion.fleetnet.inbox import MessageInbox, open_vision_session

    import zenoh

    users = tmp_path / "zenoh_users.txt"
    new_users_file(users, 1)
    (port,) = free_ports(1)
    cfg = ZenohConfig(prefix=PREFIX, endpoints=(f"tcp/127.0.0.1:{port}",), users_file=str(users), vision_session=True)
    session = open_vision_session(cfg, "companion.toml")
    inbox = MessageInbox(session, PREFIX, "neighbour pose")
    endpoint = cfg.group_endpoint(0)
    sessions = []
    try:
        for settings in ({}, {"transport__auth__usrpwd__user": "companion-g1",
                              "transport__auth__usrpwd__password": "x" * 43}):
            sessions.append(peer_session(connect=(endpoint,), **settings))
        payload = codec.encode(neighbour_pose(np.random.default_rng(3), 0, 1))
        for _ in range(20):
            for s in sessions:
                s.put(neighbour_key(PREFIX, 0), payload)
            inbox_got = inbox.drain()
            assert not inbox_got
        assert all(not s.info.peers_zid() for s in sessions)
        insider = zenoh.open(peer_config((), (endpoint,), group_credentials(cfg, 0, 1, "companion.toml")))
        sessions.append(insider)
        assert wait_for(lambda: insider.info.peers_zid(), 5.0)
        got = []
        assert wait_for(lambda: (insider.put(neighbour_key(PREFIX, 0), payload), got.extend(inbox.drain()),
                                 bool(got))[2], 5.0)
        assert got[0].observer == 0 and inbox.counts["rejected"] == 0
    finally:
        for s in sessions:
            s.close()
        inbox.close()
        session.close()


def test_the_consumer_publishes_load_observations_and_the_load_inbox_takes_them(tmp_path):
    """With ``[load]``, three frames of vehicle 1's camera go out as eq. 4 load observations (the
    camera's PnP pose through :func:`~companion.load.measurements.observation_from_pnp`) on
    vehicle 1's key; two of a camera configured on another vehicle are counted, not published; a
    load observation on another vehicle's key is refused."""
    from companion.estimation.so3 import quat_to_rotmat
    from companion.fleetnet.keys import load_key
    from companion.load.measurements import observation_from_pnp
    from companion.load.model import Pose3
    from companion.vision.node_config import LoadCamera, LoadMarker

    from ..fleetnet_cases import load_observation

    load = LoadMarker(7, marker_pos_b_m=(0.0, 0.0, 0.102), cameras=(
        LoadCamera("cam1", vehicle=1, camera_pos_b_m=(0.15, 0.0, -0.05), camera_q_bc_wxyz=(0.5, -0.5, 0.5, -0.5)),
        LoadCamera("cam2", vehicle=3)))
    rogue = [(load_key(PREFIX, 2), codec.encode(load_observation(np.random.default_rng(1), vehicle=0)))]
    result, got, summary, measured = _through_the_consumer(tmp_path, "load observation", rogue, load=load)
    assert result["load_observations"] == {"published": 3, "wrong_vehicle": 2}
    assert summary == {"received": 4, "delivered": 3, "rejected": 1, "overflow": 0,
                       "reasons": {"LoadObservation does not belong on this key": 1}}
    cam = load.cameras[0]
    for obs, rec in zip(got, measured):
        pose = rec["poses"][0]
        want = observation_from_pnp(0, rec["t_capture_s"], quat_to_rotmat(np.asarray(pose["q_cm_wxyz"])),
                                    np.asarray(pose["t_cm_m"]), np.reshape(pose["cov"], (6, 6)),
                                    Pose3(np.asarray(cam.camera_pos_b_m), np.asarray(cam.camera_q_bc_wxyz)),
                                    Pose3(np.asarray(load.marker_pos_b_m), np.asarray(load.marker_q_bm_wxyz)))
        assert (obs.vehicle, obs.stamp_s) == (0, rec["t_capture_s"])
        np.testing.assert_allclose(obs.vehicle_in_load_m, want.vehicle_in_load_m, atol=1e-9)
        np.testing.assert_allclose(obs.joint_cov, want.joint_cov, rtol=1e-6, atol=1e-15)


def test_a_session_that_will_not_close_is_logged_not_raised(caplog):
    """A Zenoh close that times out (a stalled peer) must not lose what a stopping process still
    writes: close_session logs it and returns."""
    import zenoh

    from companion.fleetnet.bus import close_session

    class Stalled:
        def close(self):
            raise zenoh.ZError("close operation timed out!")

    with caplog.at_level("WARNING"):
        close_session(Stalled(), "the test's session")
    assert "the test's session: close failed (close operation timed out!)" in caplog.text

"""Camera frames in a secured fleet (users file and mutual TLS): a group's camera session
(:func:`sitl.cameras.stream.open_camera_session`) and the vision consumer (its ``[zenoh]`` naming
the fleet's config and a group) take the companions' credentials; sessions without them neither
receive frames nor get frames of their own to the consumer; the consumer's config errors name the
file and the key."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from companion.configfile import dump_toml
from companion.fleetnet.certs import new_fleet_certs
from companion.fleetnet.config import load_zenoh_table, new_users_file, read_users_file
from companion.vision.frame import CameraFrame, CameraFrameHeader
from companion.vision.geometry import CameraIntrinsics
from companion.vision.node_config import VisionNodeSetup, ZenohCameraSource, load_vision_setup

from ..ports import free_ports
from ..waits import wait_for
from ..zenoh_peers import peer_session

pytest.importorskip("zenoh")

PREFIX = "camsec"


@pytest.fixture(scope="module")
def secured_fleet(tmp_path_factory):
    """A two-group fleet's folder: the fleet CA and the groups' certificates (``certs/``), a users
    file and ``fleet.toml`` whose ``[zenoh]`` names them, with ``tls/`` endpoints on loopback."""
    folder = tmp_path_factory.mktemp("fleet")
    new_fleet_certs(folder / "certs", 2)
    new_users_file(folder / "zenoh_users.txt", 2)
    endpoints = ", ".join(f'"tls/127.0.0.1:{p}"' for p in free_ports(2))
    (folder / "fleet.toml").write_text(f'[zenoh]\nprefix = "{PREFIX}"\nendpoints = [{endpoints}]\n'
                                       'users_file = "zenoh_users.txt"\n[zenoh.tls]\ncerts_dir = "certs"\n')
    return folder


def _vision_config(path, fleet: str = "", group: int = 0, connect=("tls/127.0.0.1:7450",)):
    src = ZenohCameraSource(prefix=PREFIX, connect=tuple(connect), fleet=fleet, group=group)
    path.write_text(dump_toml(VisionNodeSetup(name="t", source="zenoh", zenoh=src)))
    return path


def _frame(seq: int, vehicle: int = 1) -> CameraFrame:
    intr = CameraIntrinsics.from_fov(32, 24, 60.0)
    h = CameraFrameHeader("down", vehicle, seq, 0.1 * seq, 0.1 * seq + 0.05, 32, 24, "mono8", intr)
    return CameraFrame(h, np.full((24, 32), seq % 256, np.uint8))


def test_only_sessions_with_the_fleets_credentials_exchange_camera_frames(secured_fleet, tmp_path):
    """Vehicle 2's camera on group 2's computer publishes; the consumer, presenting group 1's
    credentials, receives every frame. Sessions with no credentials, with a client certificate and
    a wrong password, or with the right password and no client certificate open no transport:
    they receive no frame and their forged frames never reach the consumer."""
    import zenoh

    from companion.vision.camera_wire import CameraPublisher, camera_key, camera_pattern
    from companion.vision.frame_codec import encode_frame
    from companion.vision.node import ZenohFrames
    from sitl.cameras.stream import open_camera_session

    certs = secured_fleet / "certs"
    fleet = load_zenoh_table(secured_fleet / "fleet.toml")
    endpoint, camera = open_camera_session(fleet, 1, 2, "fleet.toml")
    assert endpoint.startswith("tls/127.0.0.1:")
    vision = _vision_config(tmp_path / "vision.toml", str(secured_fleet / "fleet.toml"), 1, (endpoint,))
    setup = load_vision_setup(vision)
    consumer = ZenohFrames(setup.zenoh, str(vision))
    password = read_users_file(str(secured_fleet / "zenoh_users.txt"))["companion-g1"]
    ca = {"transport__link__tls__root_ca_certificate": str(certs / "ca.pem")}
    cert = {"transport__link__tls__connect_certificate": str(certs / "companion-g1.pem"),
            "transport__link__tls__connect_private_key": str(certs / "companion-g1.key"),
            "transport__link__tls__enable_mtls": True}

    def login(secret: str) -> dict:
        return {"transport__auth__usrpwd__user": "companion-g1", "transport__auth__usrpwd__password": secret}

    outsiders, heard, got = [], [], []
    try:
        publisher = CameraPublisher(camera, PREFIX, 1, fmt="raw")
        for settings in ({**ca}, {**ca, **cert, **login("x" * 43)}, {**ca, **login(password)}):
            s = peer_session(connect=(endpoint,), **settings)
            s.declare_subscriber(camera_pattern(PREFIX), lambda sample: heard.append(str(sample.key_expr)),
                                 allowed_origin=zenoh.Locality.REMOTE)
            outsiders.append(s)
        assert wait_for(lambda: publisher.matched, 5.0), "the consumer never subscribed"
        for seq in range(3):  # each awaited: the publisher drops under congestion
            publisher.publish(_frame(seq))
            assert wait_for(lambda: (got.extend(consumer.poll(0.0)), len(got) > seq)[1], 5.0), f"frame {seq} lost"
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            for s in outsiders:
                s.put(camera_key(PREFIX, 1), encode_frame(_frame(99), "raw"))
            time.sleep(0.05)
        publisher.publish(_frame(3))  # after the forgeries: by now they would have arrived
        assert wait_for(lambda: (got.extend(consumer.poll(0.0)), len(got) > 3)[1], 5.0)
        got += consumer.poll(0.2)
        assert [kind for kind, _ in got] == ["frame"] * 4, got
        assert [f.header.seq for _, f in got] == [0, 1, 2, 3]  # the camera's own only
        assert heard == [] and all(not s.info.peers_zid() for s in outsiders)
        # the control: the wrong-password session's TLS settings with the right password get in
        insider = peer_session(connect=(endpoint,), **ca, **cert, **login(password))
        outsiders.append(insider)
        assert wait_for(lambda: insider.info.peers_zid(), 5.0)
    finally:
        for s in outsiders:
            s.close()
        consumer.close()
        camera.close()


def test_the_consumers_secured_config_errors_exit_2_naming_file_and_key(secured_fleet, tmp_path, capsys):
    """``python -m companion.vision`` with a fleet's credentials: a fleet config, a group or an
    endpoint that does not fit, and the fleet's users file or certificates missing are bad input
    (exit 2, nothing opened), named by file and key; relative paths are the config file's."""
    from companion.vision.__main__ import main

    users, certs = secured_fleet / "zenoh_users.txt", secured_fleet / "certs"
    text = (secured_fleet / "fleet.toml").read_text()
    with_users, with_certs = text.replace('"zenoh_users.txt"', f'"{users}"'), text.replace('"certs"', f'"{certs}"')
    (tmp_path / "fleet.toml").write_text(with_users.replace('"certs"', f'"{certs}"'))
    (tmp_path / "no_users.toml").write_text(with_certs)  # no zenoh_users.txt in tmp_path
    (tmp_path / "no_certs.toml").write_text(with_users)  # no certs/ in tmp_path
    cases = [
        (dict(fleet="nowhere.toml", group=1), r"vision.toml: zenoh.fleet: no such file: .*nowhere.toml"),
        (dict(fleet="fleet.toml", group=3), r"vision.toml: zenoh.group: .*has 2 groups"),
        (dict(fleet="fleet.toml", group=1, connect=("tcp/127.0.0.1:7450",)), r"vision.toml: zenoh.connect: .*use tls/"),
        (f'[zenoh]\nprefix = "{PREFIX}"\nconnect = ["tls/127.0.0.1:7450"]\n',
         r"vision.toml: zenoh.connect: .*tls/ and quic/ need the fleet's credentials"),
        (dict(fleet="no_users.toml", group=1), r"no_users.toml: zenoh.users_file: .*zenoh_users.txt: cannot read"),
        (dict(fleet="no_certs.toml", group=2), r"no_certs.toml: zenoh.tls.certs_dir: no such file: .*ca.pem"),
    ]
    vision = tmp_path / "vision.toml"
    for args, message in cases:
        if isinstance(args, str):  # what the dataclass refuses to hold: written by hand
            vision.write_text(args)
        else:
            _vision_config(vision, **args)
        assert main(["--config", str(vision), "--out", str(tmp_path / "out")]) == 2, args
        err = capsys.readouterr().err
        assert re.search(message, err), (args, err)
    assert not (tmp_path / "out").exists()

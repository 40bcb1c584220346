"""Fleet mode's cameras and the vision consumer.

* A fleet run of a camera scenario: the harness renders the camera, publishes its frames over Zenoh
  (loopback, a port the OS picked), the consumer process (``python -m companion.vision``) measures
  the marker in them, and ``metrics.json["vision"]`` scores its poses against the truth.
* The consumer's ``cv2.VideoCapture`` source, on a video file written here with ``cv2.VideoWriter``
  (synthetic views of a marker at known poses; no camera hardware).
* The consumer over a loopback Zenoh session: good frames measured, hostile payloads counted.
* Its config and ``--help`` need neither OpenCV nor Zenoh; without OpenCV it says which extra.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading

import numpy as np
import pytest

from companion.configfile import ConfigError, dump_toml
from companion.estimation.so3 import quat_to_rotmat
from companion.vision.config import PipelineConfig
from companion.vision.geometry import CameraIntrinsics, geodesic_angle_rad
from companion.vision.node_config import VideoCaptureSource, VisionNodeSetup, ZenohCameraSource, load_vision_setup

from ..camera_frames import marker_frame
from ..ports import children_of
from ..waits import wait_for
from ..zenoh_peers import peer_session
from ..paths import ROOT

cv2 = pytest.importorskip("cv2")

CAMERA_FLEET = ROOT / "configs" / "sitl" / "cameras" / "three_link_camera_fleet.toml"


@pytest.mark.e2e
@pytest.mark.rendering
def test_fleet_frames_cross_zenoh_and_the_consumer_measures_the_marker(tmp_path, fleet_ports):
    pytest.importorskip("zenoh")
    pytest.importorskip("mujoco")
    from sitl.fleet.launcher import launch
    from sitl.scenario import load_scenario

    sc = load_scenario(CAMERA_FLEET, duration_s=5.0)
    m = launch(sc, tmp_path, speed=0.0, plots=False, **fleet_ports.launch_kwargs)
    assert not children_of(os.getpid()), "fleet or consumer processes left behind"
    assert not m["crashed"] and not m["aborted"]

    v = m["vision"]
    wire = v["wire"]
    # every rendered frame crossed Zenoh and was decoded: 10 Hz for 5 s
    assert 48 <= wire["published"] <= 51 and wire["bytes_published"] > 100_000 * wire["published"]
    assert wire["received"] == wire["published"] and wire["lost"] == 0
    assert wire["rejected_payloads"] == 0 and wire["unmatched_frames"] == 0
    assert v["frames"] == {"down": wire["published"]}
    # hovering at 2.5 m over the 0.5 m marker: seen in (nearly) every frame, within a centimetre or two
    assert v["detection_rate"]["down"] >= 0.9
    ippe = v["pnp"]["ippe_square"]
    assert ippe["poses"] >= 0.9 * wire["published"]
    assert ippe["pos_rms_m"] < 0.02 and ippe["pos_max_m"] < 0.05, ippe
    assert ippe["att_rms_deg"] < 2.0, ippe
    assert 0 < v["detect_ms_per_frame"] < 200 and v["render_ms_per_frame"] > 0

    # the consumer's own artefacts: per frame the stamps (simulation clock), the pose and its covariance
    folder = tmp_path / "vision"
    summary = json.loads((folder / "vision_summary.json").read_text())
    assert summary["source"] == "zenoh" and summary["frames_total"] == wire["received"]
    assert summary["ended_by"] == "stopped"  # SIGTERM from the launcher, after draining
    records = [json.loads(x) for x in (folder / "vision_frames.jsonl").read_text().splitlines()]
    assert [r["seq"] for r in records] == list(range(len(records)))
    t = np.array([r["t_capture_s"] for r in records])
    np.testing.assert_allclose(np.diff(t), 0.1, atol=1e-9)
    assert all(r["vehicle"] == 1 and r["camera"] == "down" for r in records)  # link 2 (0-based 1)
    pose = next(r["poses"][0] for r in records if r["poses"])
    cov = np.array(pose["cov"]).reshape(6, 6)
    assert pose["id"] == 7 and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    arrays = np.load(tmp_path / "vision.npz")
    assert arrays["vision_pos_err_m"].shape == (ippe["poses"],)
    assert (tmp_path / "vision.toml").exists()


def _marker_view(K: np.ndarray, R_cm: np.ndarray, t_cm: np.ndarray, size_m: float, shape=(240, 320)) -> np.ndarray:
    """A grey view of ArUco marker 7 (DICT_4X4_50; ``size_m`` the black square's side) at pose
    ``(R_cm, t_cm)`` in a pinhole camera ``K``: the printed marker warped by its plane's homography
    at 4x the resolution, then averaged down (a camera's pixels integrate their area)."""
    from companion.vision.markers import marker_image

    img, fraction = marker_image("DICT_4X4_50", 7, bit_px=24)
    n = img.shape[0]
    s = size_m / fraction / n  # metres per marker-image pixel
    A = np.array([[s, 0.0, -s * (n - 1) / 2], [0.0, -s, s * (n - 1) / 2], [0.0, 0.0, 1.0]])  # px -> marker x, y (up)
    up = np.array([[4.0, 0.0, 1.5], [0.0, 4.0, 1.5], [0.0, 0.0, 1.0]])  # pixel centres at 4x: u4 = 4 u + 1.5
    H = up @ K @ np.column_stack((R_cm[:, 0], R_cm[:, 1], t_cm)) @ A
    big = cv2.warpPerspective(img, H, (4 * shape[1], 4 * shape[0]), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=150)
    return cv2.resize(big, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])}[axis]


def test_video_capture_source_reads_a_file_and_measures_the_marker(tmp_path):
    """A hardware config names a cv2.VideoCapture source: here a 20-frame 640x480 MJPG file of a 0.2 m marker
    1.0-1.4 m away, tilted 20-40 deg; the CLI measures every frame within 1.5 cm and 2 deg."""
    intr = CameraIntrinsics.from_fov(640, 480, 60.0)
    poses = [(_rot("x", 180.0) @ _rot("y", 20.0 + k) @ _rot("x", -0.5 * k), np.array([0.05, -0.03, 1.0 + 0.02 * k]))
             for k in range(20)]
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (640, 480))
    assert writer.isOpened()
    for R, t in poses:
        writer.write(cv2.cvtColor(_marker_view(intr.K, R, t, 0.2, (480, 640)), cv2.COLOR_GRAY2BGR))
    writer.release()
    setup = VisionNodeSetup(name="bench_cam", source="video",
                            video=VideoCaptureSource(url="clip.avi", camera="front", vehicle=3, width_px=640,
                                                     height_px=480, fovy_deg=60.0),
                            pipeline=PipelineConfig(marker_length_m=0.2, ids=(7,)))
    config = tmp_path / "vision.toml"
    config.write_text(dump_toml(setup))  # relative url: resolved against the config's folder
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "companion.vision", "--config", str(config), "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((out / "vision_summary.json").read_text())
    assert summary["ended_by"] == "end of stream" and summary["source"] == "video"
    assert summary["frames"] == {"front": 20} and summary["frames_detected"] == 20 and summary["rejected_payloads"] == 0
    records = [json.loads(x) for x in (out / "vision_frames.jsonl").read_text().splitlines()]
    assert [r["seq"] for r in records] == list(range(20))
    np.testing.assert_allclose([r["t_capture_s"] for r in records], 0.1 * np.arange(20), atol=1e-6)  # file position
    assert all(r["vehicle"] == 2 for r in records)  # 0-based in the header, 1-based in the config
    err_deg = []
    for r, (R, t) in zip(records, poses):
        (p,) = r["poses"]
        assert np.linalg.norm(np.array(p["t_cm_m"]) - t) < 0.015, (r["seq"], p["t_cm_m"], t)
        err_deg.append(np.degrees(geodesic_angle_rad(quat_to_rotmat(np.array(p["q_cm_wxyz"])), R)))
    assert max(err_deg) < 2.0, err_deg
    assert "end of stream" in (out / "vision.log").read_text()

    # a file of another size than the calibration: every frame rejected and counted, none measured
    wrong = tmp_path / "wrong.toml"
    wrong.write_text(dump_toml(VisionNodeSetup(source="video", video=VideoCaptureSource(
        url=str(video), width_px=320, height_px=240, fovy_deg=60.0))))
    proc = subprocess.run([sys.executable, "-m", "companion.vision", "--config", str(wrong), "--out",
                           str(tmp_path / "out2")], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    s2 = json.loads((tmp_path / "out2" / "vision_summary.json").read_text())
    assert s2["frames_total"] == 0 and s2["rejected_payloads"] == 20 and s2["rejected_reasons"] == {"size": 20}
    # a file that is not there: exit 3, named
    missing = tmp_path / "missing.toml"
    missing.write_text(dump_toml(VisionNodeSetup(source="video", video=VideoCaptureSource(
        url=str(tmp_path / "nope.avi"), fovy_deg=60.0))))
    proc = subprocess.run([sys.executable, "-m", "companion.vision", "--config", str(missing), "--out",
                           str(tmp_path / "out3")], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 3 and "nope.avi" in proc.stderr


def test_consumer_over_zenoh_measures_frames_and_counts_hostile_payloads(tmp_path):
    """run_node on a loopback Zenoh session: 5 good frames of two vehicles measured; a frame on the
    wrong vehicle's key and garbage are counted as rejected, never measured."""
    zenoh = pytest.importorskip("zenoh")
    from companion.vision.camera_wire import CameraPublisher, camera_key
    from companion.vision.frame_codec import encode_frame
    from companion.vision.node import FRAMES_FILE, run_node
    from sitl.cameras.stream import free_loopback_port

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    harness = peer_session(listen=(endpoint,))
    setup = VisionNodeSetup(name="t", source="zenoh", zenoh=ZenohCameraSource(prefix="camtest", connect=(endpoint,)),
                            pipeline=PipelineConfig(marker_length_m=0.2))
    stop = threading.Event()
    result = {}
    frames_log = tmp_path / FRAMES_FILE

    def measured() -> int:
        return frames_log.read_text().count("\n") if frames_log.exists() else 0

    def measured_all() -> bool:
        return stop.is_set() or measured() >= 5

    worker = threading.Thread(target=lambda: result.update(run_node(setup, tmp_path, stop=measured_all)))
    try:
        pubs = [CameraPublisher(harness, "camtest", v, fmt="png") for v in range(2)]
        worker.start()
        assert wait_for(lambda: all(p.matched for p in pubs), 10.0), "the consumer never subscribed"
        for seq in range(2):  # the publishers drop under congestion by design: each frame awaited
            for v, p in enumerate(pubs):
                p.publish(marker_frame(vehicle=v, seq=seq))
                assert wait_for(lambda: measured() >= 2 * seq + v + 1, 10.0), "a frame was never measured"
        # the hostile payloads, then a last good frame, all queued without loss and delivered in order:
        # when the last frame is measured, both hostile payloads have been taken
        block = zenoh.CongestionControl.BLOCK
        harness.put(camera_key("camtest", 1), encode_frame(marker_frame(vehicle=0), "raw"),
                    congestion_control=block)  # wrong key
        harness.put(camera_key("camtest", 0), b"ASKC" + b"\0" * 40, congestion_control=block)  # garbage
        harness.put(camera_key("camtest", 1), encode_frame(marker_frame(vehicle=1, seq=2), "png"),
                    congestion_control=block)
        worker.join(15)
        assert not worker.is_alive()
    finally:
        stop.set()
        harness.close()
    assert result["frames_total"] == 5 and result["frames_detected"] == 5 and result["poses"] == 5
    assert result["rejected_payloads"] == 2
    assert result["frames"] == {"cam1": 2, "cam2": 3}
    lines = (tmp_path / "vision_frames.jsonl").read_text().splitlines()
    assert len(lines) == 5 and all(json.loads(x)["poses"][0]["id"] == 7 for x in lines)


def test_config_errors_name_the_key(tmp_path):
    def load(text: str):
        path = tmp_path / "v.toml"
        path.write_text(text)
        return load_vision_setup(path)

    with pytest.raises(ConfigError, match="zenoh: prefix"):
        load('source = "zenoh"\n[zenoh]\nconnect = ["tcp/127.0.0.1:7450"]\n')
    with pytest.raises(ConfigError, match=r"zenoh\.connect: .*not a Zenoh endpoint"):
        load('[zenoh]\nprefix = "x"\nconnect = ["ws/127.0.0.1:7450"]\n')
    with pytest.raises(ConfigError, match="video: device: .*exactly one"):
        load('source = "video"\n[video]\nfovy_deg = 60.0\n')
    with pytest.raises(ConfigError, match="video: fx_px: the intrinsics"):
        load('source = "video"\n[video]\ndevice = 0\n')
    with pytest.raises(ConfigError, match=r"video\.fovy_deg: .*not both"):
        load('source = "video"\n[video]\ndevice = 0\nfovy_deg = 60.0\nfx_px = 500.0\nfy_px = 500.0\n')
    with pytest.raises(ConfigError, match=r"pipeline\.method"):
        load('[zenoh]\nprefix = "x"\nconnect = ["tcp/127.0.0.1:7450"]\n[pipeline]\nmethod = "magic"\n')
    ok = load('source = "video"\n[video]\ndevice = 0\nfx_px = 500.0\nfy_px = 505.0\ncx_px = 320.0\ncy_px = 240.0\n'
              'dist_coeffs = [0.1, -0.02, 0.0, 0.0]\n')
    assert ok.video.intrinsics().fy_px == 505.0 and ok.video.intrinsics().distorted


BLOCKER = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {'cv2', 'zenoh', 'mujoco'}:
            raise ImportError('blocked: ' + name)
sys.meta_path.insert(0, Block())
"""


def test_the_consumer_config_and_help_need_neither_opencv_nor_zenoh(tmp_path):
    config = tmp_path / "v.toml"
    config.write_text(dump_toml(VisionNodeSetup(source="video", video=VideoCaptureSource(device=0, fovy_deg=60.0))))
    code = BLOCKER + (
        "import companion.vision.node_config, companion.vision.node, companion.vision.__main__ as m\n"
        f"companion.vision.node_config.load_vision_setup({str(config)!r})\n"
        "m.build_parser().format_help()\n"
        f"sys.exit(m.main(['--config', {str(config)!r}, '--out', {str(tmp_path / 'out')!r}]))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 3, proc.stderr  # the source needs OpenCV: the extra is named
    assert "blocked: cv2" in proc.stderr and "[vision]" in proc.stderr

"""A flight's camera frames kept as JPEG (sitl.cameras.frame_archive), as run.mcap's image channels
(companion.recording.mcap_log.image_channels) and in the replay (sitl.view.timeline)."""

import base64
import json
import types

import cv2
import numpy as np
import pytest

from companion.recording.mcap_log import export_log, image_channels
from sitl.cameras.frame_archive import FRAMES_NAME, FrameArchive
from sitl.view.timeline import open_run

from .test_mcap_log import read_back, synthetic_log


def captured(t, camera, value, shape=(24, 32, 3)):
    image = np.zeros(shape, np.uint8)
    image[..., 0] = value  # red, in RGB
    header = types.SimpleNamespace(t_capture_s=t)
    return types.SimpleNamespace(frame=types.SimpleNamespace(header=header, image=image), camera_index=camera)


@pytest.fixture
def archive():
    a = FrameArchive(["front", "down"])
    for k, (t, cam) in enumerate([(0.1, 0), (0.1, 1), (0.2, 0), (0.35, 1), (0.3, 0)]):
        a.on_frame(captured(t, cam, 40 * k))
    return a


def decode(jpeg: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)


def test_frames_are_jpeg_back_to_back(archive):
    f = archive.arrays()
    assert f["frame_t"].tolist() == [0.1, 0.1, 0.2, 0.35, 0.3] and f["frame_camera"].tolist() == [0, 1, 0, 1, 0]
    assert f["frame_offsets"][0] == 0 and f["frame_offsets"][-1] == f["frame_jpeg"].size
    third = decode(f["frame_jpeg"][f["frame_offsets"][2]:f["frame_offsets"][3]].tobytes())
    assert third.shape == (24, 32, 3) and abs(int(third[..., 2].mean()) - 80) <= 3  # red is BGR's last


def test_an_image_channel_per_camera_in_capture_order(tmp_path, archive):
    f = archive.arrays()
    counts = export_log(synthetic_log(2), tmp_path / "run.mcap", extra=image_channels(f))
    assert counts["/camera/front/image"] == 3 and counts["/camera/down/image"] == 2
    _, messages = read_back(tmp_path / "run.mcap")
    front = messages["/camera/front/image"]
    assert [log_time for log_time, *_ in front] == [100_000_000, 200_000_000, 300_000_000]
    reds = [int(decode(base64.b64decode(m["data"]))[..., 2].mean()) for *_, m in front]
    assert np.allclose(reds, [0, 80, 160], atol=3)  # the frame at 0.3 s was captured last but comes third
    assert front[0][3]["format"] == "jpeg" and front[0][3]["frame_id"] == "camera_front"


@pytest.mark.parametrize("break_it", [
    lambda f: f.pop("frame_jpeg"),
    lambda f: f.update(frame_offsets=f["frame_offsets"][:-1]),
    lambda f: f.update(frame_camera=f["frame_camera"] + 5),
    lambda f: f.update(frame_t=np.full_like(f["frame_t"], np.nan)),
    lambda f: f.update(frame_offsets=f["frame_offsets"][::-1].copy()),
    lambda f: f.update(frame_jpeg=f["frame_jpeg"][:10]),
])
def test_arrays_that_do_not_fit_give_no_channel(archive, break_it):
    f = archive.arrays()
    break_it(f)
    assert image_channels(f) == []


def test_the_replay_shows_each_cameras_newest_frame(tmp_path, archive):
    np.savez(tmp_path / "log.npz", **synthetic_log(2))
    np.savez(tmp_path / FRAMES_NAME, **archive.arrays())
    timeline, _ = open_run(tmp_path)
    assert timeline.images_at(0.05) == {}
    at = timeline.images_at(0.32)
    assert {cam: number for cam, (number, _) in at.items()} == {0: 4, 1: 1}
    assert int(decode(at[0][1])[..., 2].mean()) == pytest.approx(160, abs=3)
    (tmp_path / FRAMES_NAME).write_bytes(b"not a zip")
    timeline, _ = open_run(tmp_path)
    assert timeline.images_at(1.0) == {}


def test_messages_are_json(tmp_path, archive):
    export_log(synthetic_log(2), tmp_path / "run.mcap", extra=image_channels(archive.arrays()))
    _, messages = read_back(tmp_path / "run.mcap")
    assert json.dumps(messages["/camera/down/image"][0][3])  # decoded and re-encodable


def test_the_lens_map_sends_each_true_pixel_to_where_its_ray_was_rendered():
    """A camera with a calibration error and distortion: a point projected by the true lens
    (OpenCV, with the true intrinsics) lands, through the rig's map, where the pinhole render shows it."""
    import cv2

    from companion.vision.geometry import CameraIntrinsics
    from sitl.cameras.config import CameraMount
    from sitl.cameras.rig import pixel_maps

    mount = CameraMount(name="c", dist_coeffs=(-0.08, 0.02, 0.001, -0.001), calib_focal_std_frac=0.02,
                        calib_principal_std_px=4.0, calib_dist_std_frac=0.2)
    true = mount.true_intrinsics(np.random.default_rng(3))
    nominal = mount.intrinsics()
    assert true != nominal and abs(true.fx_px / nominal.fx_px - 1) < 0.1
    assert mount.true_intrinsics(np.random.default_rng(3)) == true  # drawn from the seed
    assert CameraMount(name="c").true_intrinsics(np.random.default_rng(3)) == CameraMount(name="c").intrinsics()
    rendered = CameraIntrinsics.from_fov(640, 480, 60.0)
    mx, my = pixel_maps(true, rendered)
    pts = np.array([[0.3, -0.2, 2.0], [-0.5, 0.4, 3.0], [0.05, 0.1, 1.5]])
    px_true = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), true.K, true.dist)[0].reshape(-1, 2)
    px_render = pts[:, :2] / pts[:, 2:] * [rendered.fx_px, rendered.fy_px] + [rendered.cx_px, rendered.cy_px]
    for (u, v), want in zip(px_true, px_render):
        iu, iv = int(round(u)), int(round(v))  # the map at the nearest pixel (half a pixel off at most)
        got = np.array([mx[iv, iu], my[iv, iu]], dtype=float)
        assert np.linalg.norm(got - want) < 1.5


@pytest.mark.parametrize("bad", [{"drop_probability": 1.0}, {"drop_probability": -0.1}, {"calib_focal_std_frac": 0.3},
                                 {"calib_principal_std_px": -1.0}])
def test_a_camera_refuses_an_impossible_calibration_or_drop_rate(bad):
    from sitl.cameras.config import CameraMount

    with pytest.raises(ValueError):
        CameraMount(name="c", **bad)

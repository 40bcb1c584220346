"""Cameras rendered by MuJoCo in the SITL (sitl/cameras/rig.py), markers, and the flight video (sitl/cameras/video.py).

The tests marked ``rendering`` render offscreen with a headless OpenGL backend (conftest.py; .ci/run
installs libosmesa6)."""

from __future__ import annotations

from dataclasses import replace

import cv2
import mujoco
import numpy as np
import pytest

from companion.configfile import ConfigError
from companion.vision.config import PNP_METHOD_NAMES, PipelineConfig
from companion.vision.geometry import geodesic_angle_rad, project_points, translation_error_m
from companion.vision.pnp import measure_markers
from sitl.cameras.rig import CameraRig, vision_mjcf
from sitl.cameras.config import CameraMount, MarkerMount
from sitl.runner import BatchRunner
from sitl.scenario import load_scenario
from sitl.cameras.video import VideoRecorder

BASE = """<mujoco><option timestep="0.001"/><worldbody>
<light pos="0 0 5" directional="true" dir="0 0 -1"/>
<body name="rig" pos="0 0 0"/>
<geom name="dot" type="sphere" size="0.03" pos="2.0 0.25 -0.15" rgba="1 0 0 1" contype="0" conaffinity="0"/>
<geom name="wall" type="box" size="0.01 8 8" pos="5 0 0" rgba="0.5 0.5 0.5 1" contype="0" conaffinity="0"/>
</worldbody></mujoco>"""

# a camera at the origin looking along world +x, image right = world -y
CAM = CameraMount(name="fwd", body="rig", pos_b_m=(0.0, 0.0, 0.0), optical_axis_b=(1.0, 0.0, 0.0),
                  image_right_b=(0.0, -1.0, 0.0), noise_std_dn=2.0, rate_hz=10.0, latency_s=0.05)


def marker_facing_camera(tilt_deg: float, size_m: float = 0.4) -> MarkerMount:
    """A marker 2 m ahead of CAM, its face towards it, turned by ``tilt_deg`` about the vertical."""
    a = np.radians(tilt_deg)
    normal = (-np.cos(a), -np.sin(a), 0.0)
    return MarkerMount(id=3, body="world", size_m=size_m, pos_b_m=(2.0, 0.1, 0.05), normal_b=normal,
                       right_b=(normal[1], -normal[0], 0.0))


def render_once(cameras, markers, ticks=1):
    xml, assets = vision_mjcf(BASE, cameras, markers)
    m = mujoco.MjModel.from_xml_string(xml, assets)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    with CameraRig(m, d, cameras, markers, 0.001, seed=4) as rig:
        for k in range(ticks):
            rig.on_tick(k, k * 0.001)
        return rig.poll(10.0), m, d


@pytest.fixture(scope="module")
def marker_frame(rendering_backend):
    frames, _, _ = render_once((CAM,), (marker_facing_camera(30.0),))
    return frames[0]


@pytest.mark.rendering
def test_intrinsics_match_the_render_of_a_known_point():
    frames, m, d = render_once((replace(CAM, noise_std_dn=0.0),), ())
    img = frames[0].frame.image.astype(int)
    red = img[..., 0] - np.maximum(img[..., 1], img[..., 2]) > 25  # lit or shaded side of the red sphere
    assert red.sum() > 10
    v, u = np.nonzero(red)
    truth = frames[0].truth
    p_c = truth.R_wc.T @ (d.geom_xpos[m.geom("dot").id] - truth.p_wc_m)
    assert p_c[2] == pytest.approx(2.0)  # in front, along the optical axis
    expected = project_points(p_c[None], frames[0].frame.header.intrinsics)[0]
    assert np.hypot(u.mean() - expected[0], v.mean() - expected[1]) < 0.5


@pytest.mark.rendering
@pytest.mark.parametrize("method", PNP_METHOD_NAMES)
def test_a_rendered_marker_2m_away_is_recovered_by_each_method(marker_frame, method):
    f = marker_frame
    R_true, t_true = f.truth.marker_in_camera(3)
    assert np.linalg.norm(t_true) == pytest.approx(2.0, abs=0.01)
    _, poses = measure_markers(f.frame.image, f.frame.header.intrinsics,
                               PipelineConfig(marker_length_m=0.4, method=method))
    (p,) = poses
    assert np.linalg.norm(translation_error_m(p.t_cm_m, t_true)) < 0.01
    assert np.degrees(geodesic_angle_rad(p.R_cm, R_true)) < 1.0


@pytest.mark.rendering
def test_rate_latency_stamps_and_seeded_noise():
    cams = (CAM, replace(CAM, name="blur", exposure_s=0.004, blur_samples=3, latency_s=0.0))
    xml, assets = vision_mjcf(BASE, cams, ())
    m = mujoco.MjModel.from_xml_string(xml, assets)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    with CameraRig(m, d, cams, (), 0.001, seed=1) as rig:
        got = []
        for k in range(0, 201):
            rig.on_tick(k, k * 0.001)
            got += [(k, f.frame.header) for f in rig.poll(k * 0.001)]
        renders = rig.renders
    fwd = [(k, h) for k, h in got if h.camera == "fwd"]
    assert [h.t_capture_s for _, h in fwd] == pytest.approx([0.0, 0.1])
    assert [k for k, _ in fwd] == [50, 150]  # delivered after the 50 ms latency, not before
    assert [h.seq for _, h in fwd] == [0, 1]
    blur = [h for _, h in got if h.camera == "blur"]
    assert [h.t_capture_s for h in blur] == pytest.approx([0.0, 0.098, 0.198])  # mid-exposure (tick 0: one render)
    assert renders == 3 + 1 + 2 * 3  # fwd at 0, 100, 200; blur at 0, then 3 renders at 96/98/100 and 196/198/200
    a = render_once((CAM,), ())[0][0].frame.image
    b = render_once((CAM,), ())[0][0].frame.image
    assert np.array_equal(a, b)  # same seed, same noise
    c = render_once((replace(CAM, noise_std_dn=0.0),), ())[0][0].frame.image
    grey = (c > 20) & (c < 235)  # away from the clipping at 0 and 255
    assert grey.mean() > 0.5
    assert 1.8 < np.std(a[grey].astype(float) - c[grey]) < 2.2


def test_config_errors_name_the_key(tmp_path):
    base = open("configs/sitl/cameras/three_link_camera.toml").read()
    bad = tmp_path / "bad.toml"
    bad.write_text(base.replace("rate_hz = 10.0\nlatency_s", "rate_hz = 7.0\nlatency_s"))
    with pytest.raises(ConfigError, match=r"cameras\[0\]"):
        load_scenario(bad)
    bad.write_text(base.replace("id = 7", "id = 70"))
    with pytest.raises(ConfigError, match="id"):
        load_scenario(bad)
    with pytest.raises(ValueError, match="no body 'link9'"):
        vision_mjcf(BASE, (replace(CAM, body="link9"),), ())


@pytest.mark.rendering
def test_video_of_a_short_three_link_flight(tmp_path):
    sc = load_scenario("configs/sitl/chain/three_link.toml")
    runner = BatchRunner(sc)
    path = tmp_path / "flight.mp4"
    rec = VideoRecorder(runner.model.model, runner.model.data, path, runner.dt, title=sc.name)
    runner.tick_hooks.append(rec.on_tick)
    try:
        runner.run(0.5)
    finally:
        rec.close()
    assert rec.frames == 15
    cap = cv2.VideoCapture(str(path))
    n, ok, first = 0, True, None
    while ok:
        ok, img = cap.read()
        if ok:
            first = img if first is None else first
            n += 1
    cap.release()
    assert n == 15 and first.shape == (480, 640, 3) and first.std() > 5  # a picture, not a blank


@pytest.mark.rendering
def test_video_with_the_onboard_inset(tmp_path, marker_frame):
    xml, assets = vision_mjcf(BASE, (CAM,), (marker_facing_camera(30.0),))
    m = mujoco.MjModel.from_xml_string(xml, assets)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    with CameraRig(m, d, (CAM,), (marker_facing_camera(30.0),), 0.001, seed=0) as rig:
        rec = VideoRecorder(m, d, tmp_path / "v.mp4", 0.001, rig=rig, markers=(marker_facing_camera(30.0),))
        try:
            for k in range(0, 120):
                rig.on_tick(k, k * 0.001)
                rig.poll(k * 0.001)
                rec.on_tick(k, k * 0.001)
        finally:
            rec.close()
    assert rec.frames == 4 and rec._pip_cache is not None  # the inset: frame 0, annotated
    pip = rec._pip_cache[1]
    # the estimated axes are drawn: pure red (x) and green (y) pixels (BGR) appear in the inset
    assert np.any((pip[..., 2] > 200) & (pip[..., 1] < 60) & (pip[..., 0] < 60))
    assert np.any((pip[..., 1] > 200) & (pip[..., 2] < 60) & (pip[..., 0] < 60))

"""The cameras' world and flaws beyond the lens: the ``[scene]`` (ground, light, clutter:
sitl/cameras/scene.py, backdrop.py), the sensor's response (photometry.py) and the delivery
jitter (rig.py's Delivery). Everything seeded; nothing here renders but the one tiny frame of the
test marked ``rendering``."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from companion.configfile import ConfigError
from sitl.cameras.config import CameraMount
from sitl.cameras.photometry import GaussMarkov, SensorResponse, SunSchedule, vignetting_map
from sitl.cameras.scene import ClutterConfig, LightingConfig, SceneConfig, scene_rng

REALISTIC = "configs/sitl/load/slung_load_realistic.toml"
GROUND_XML = """<mujoco><visual><global offwidth="64" offheight="48"/></visual><worldbody>
<geom name="ground" type="plane" size="50 50 0.1" rgba="0.35 0.4 0.35 1"/>
<light name="sun" pos="0 0 20" dir="0 0 -1" directional="true"/>
</worldbody></mujoco>"""


@pytest.mark.parametrize("bad", [{"latency_jitter_s": -0.01}, {"latency_jitter_dist": "gaussian"}, {"vignetting": 1.0},
                                 {"vignetting": -0.1}, {"gain_std": -0.1}, {"gain_std": 1.5}, {"gain_time_s": 0.0},
                                 {"gamma": 0.0}, {"gamma": 9.0}])
def test_a_camera_refuses_impossible_jitter_or_response(bad, tmp_path):
    if "latency_jitter_dist" in bad:  # a Literal: checked when the file is read
        text = open(REALISTIC).read().replace('_dist = "halfnormal"', '_dist = "gaussian"', 1)
        (tmp_path / "s.toml").write_text(text)
        from sitl.scenarios import load

        with pytest.raises(ConfigError, match=r"cameras\[0\]\.latency_jitter_dist"):
            load(tmp_path / "s.toml")
        return
    with pytest.raises(ValueError, match=next(iter(bad))):
        CameraMount(name="c", **bad)


@pytest.mark.parametrize("cls, bad", [
    (LightingConfig, {"cloud_cover": 1.5}), (LightingConfig, {"cloud_depth": -0.1}),
    (LightingConfig, {"sun_elevation_deg": (60.0, 30.0)}), (LightingConfig, {"sun_elevation_deg": (0.0, 30.0)}),
    (LightingConfig, {"cloud_time_s": 0.0}), (LightingConfig, {"sun_intensity": 1.5, "sky_ambient": 0.8}),
    (ClutterConfig, {"count": -1}), (ClutterConfig, {"markers": 50}), (ClutterConfig, {"dictionary": "DICT_9X9"}),
    (ClutterConfig, {"inner_radius_m": 4.0, "outer_radius_m": 4.5}), (ClutterConfig, {"size_m": (1.0, 0.5)}),
    (SceneConfig, {"ground_rgb": (1.2, 0.0, 0.0)}), (SceneConfig, {"ground_tile_m": 0.0}),
])
def test_the_scene_refuses_impossible_settings(cls, bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        cls(**bad)


def test_the_longest_delivery_delay_covers_every_jitter_draw():
    rng = np.random.default_rng(7)
    for dist, cap in (("uniform", 1.0), ("halfnormal", 3.0)):
        cam = CameraMount(name="c", latency_s=0.08, latency_jitter_s=0.03, latency_jitter_dist=dist)
        assert cam.max_latency_s == pytest.approx(0.08 + cap * 0.03)
        assert max(cam.latency_s + cam.latency_jitter_draw(rng) for _ in range(2000)) <= cam.max_latency_s


def test_everything_new_is_off_by_default():
    cam = CameraMount(name="c")
    assert not cam.photometric and cam.latency_jitter_draw(np.random.default_rng(0)) == 0.0
    assert not SceneConfig().active and not SceneConfig().clutter.active
    assert SceneConfig(shadows=True).active


def test_the_realistic_file_has_it_all_and_an_unknown_scene_key_is_an_error(tmp_path):
    from sitl.scenarios import load

    _, sc = load(REALISTIC)
    s = sc.scene
    assert s.active and s.ground == "noise" and s.lighting.enabled and s.lighting.cloud_cover > 0
    assert s.clutter.count > 0 and s.clutter.markers > 0
    assert all(c.latency_jitter_s > 0 and c.photometric for c in sc.cameras)
    _, off = load(REALISTIC, settings={"scene.lighting.enabled": False, "scene.ground": "plain",
                                       "scene.clutter.count": 0, "scene.clutter.markers": 0})
    assert not off.scene.lighting.enabled and not off.scene.clutter.active
    text = open(REALISTIC).read().replace("[scene.lighting]\n", "[scene.lighting]\nfog = 1\n")
    (tmp_path / "s.toml").write_text(text)
    with pytest.raises(ConfigError, match=r"scene\.lighting\.fog"):
        load(tmp_path / "s.toml")


@pytest.mark.parametrize("dist", ["uniform", "halfnormal"])
def test_jitter_is_seeded_never_negative_and_bounded(dist):
    cam = CameraMount(name="c", latency_jitter_s=0.02, latency_jitter_dist=dist)
    rng1, rng2 = np.random.default_rng(5), np.random.default_rng(5)
    d1 = np.array([cam.latency_jitter_draw(rng1) for _ in range(2000)])
    d2 = np.array([cam.latency_jitter_draw(rng2) for _ in range(2000)])
    assert np.array_equal(d1, d2)  # the same seed, the same draws
    assert d1.min() >= 0.0 and d1.max() <= 3 * 0.02 + 1e-12
    assert d1.std() > 0.004  # a jitter, not a constant
    if dist == "uniform":
        assert d1.max() <= 0.02 and d1.mean() == pytest.approx(0.01, abs=0.001)
    else:
        assert d1.mean() == pytest.approx(0.02 * math.sqrt(2 / math.pi), abs=0.001)


def test_delivery_keeps_each_cameras_capture_order_and_leaves_the_capture_stamp():
    from sitl.cameras.rig import Delivery

    cam = CameraMount(name="c", rate_hz=30.0, latency_s=0.05, latency_jitter_s=0.08, latency_jitter_dist="halfnormal")
    t_cap = np.arange(200) / 30.0
    d = Delivery(cam, np.random.default_rng([3, 0x717E, 0]))
    t_av = np.array([d.available_s(t) for t in t_cap])
    assert np.all(t_av >= t_cap + 0.05)  # never before the latency
    assert np.all(np.diff(t_av) >= 0)  # in capture order, though a jitter exceeds the frame period
    assert np.any(t_av - t_cap > 0.05 + 1 / 30.0)
    again = Delivery(cam, np.random.default_rng([3, 0x717E, 0]))
    assert np.array_equal([again.available_s(t) for t in t_cap], t_av)
    still = Delivery(replace(cam, latency_jitter_s=0.0), np.random.default_rng(0))
    assert [still.available_s(t) for t in t_cap[:3]] == [t + 0.05 for t in t_cap[:3]]


def test_the_slow_signals_are_seeded_stationary_and_read_anywhere():
    a, b = GaussMarkov(np.random.default_rng(1), 2.0, 0.5), GaussMarkov(np.random.default_rng(1), 2.0, 0.5)
    late_first = [b.at(30.0), b.at(3.0)]  # read out of order: the same values
    assert [a.at(3.0), a.at(30.0)] == late_first[::-1]
    x = np.array([a.at(t) for t in np.arange(0.0, 2000.0, 1.0)])
    assert abs(x.mean()) < 0.15 and 0.8 < x.std() < 1.2
    assert abs(a.at(10.0) - a.at(10.01)) < 0.05  # smooth over a frame
    cfg = LightingConfig(enabled=True, cloud_cover=0.3, cloud_depth=0.5, cloud_time_s=5.0)
    s1, s2 = SunSchedule(cfg, scene_rng(7, "clouds")), SunSchedule(cfg, scene_rng(7, "clouds"))
    f = np.array([s1.factor(t) for t in np.arange(0.0, 3000.0, 0.5)])
    assert np.array_equal(f[:40], [s2.factor(t) for t in np.arange(0.0, 20.0, 0.5)])
    assert f.min() >= 0.5 - 1e-9 and f.max() <= 1.0
    assert np.mean(f < 0.75) == pytest.approx(0.3, abs=0.06)  # the cloud cover
    clear = SunSchedule(replace(cfg, cloud_cover=0.0), np.random.default_rng(0))
    assert clear.factor(12.0) == 1.0


def test_sensor_response_vignettes_drifts_and_tones():
    cam = CameraMount(name="c", width_px=64, height_px=48, vignetting=0.3, gain_std=0.2, gain_time_s=1.0, gamma=2.0)
    intr = cam.intrinsics()
    v = vignetting_map(intr, 0.3)[..., 0]
    assert v.max() == pytest.approx(1.0, abs=1e-3) and min(v[0, 0], v[-1, -1], v[0, -1], v[-1, 0]) == pytest.approx(0.7)
    r = SensorResponse(cam, intr, np.random.default_rng(2))
    gains = [r.gain_at(t) for t in np.arange(0.0, 20.0, 0.5)]
    assert np.std(np.log(gains)) > 0.05 and gains == [SensorResponse(cam, intr, np.random.default_rng(2)).gain_at(t)
                                                      for t in np.arange(0.0, 20.0, 0.5)]
    flat = np.full((48, 64, 3), 64.0, dtype=np.float32)
    out = r.expose(flat, 0.0)
    assert out[24, 32, 0] == pytest.approx(64.0 * gains[0], rel=1e-3) and out[0, 0, 0] < out[24, 32, 0]
    assert r.tone(np.array([[[64.0, 255.0, 300.0]]]))[0, 0].tolist() == [128, 255, 255]  # 255 sqrt(1/4)


def test_clutter_is_seeded_outside_the_flight_and_never_collides():
    from sitl.scenarios import load

    _, sc = load(REALISTIC)
    c = sc.scene.clutter
    items = c.place(scene_rng(sc.seed, "clutter"), exclude_ids=(7,))
    assert items == c.place(scene_rng(sc.seed, "clutter"), exclude_ids=(7,))
    assert items != c.place(scene_rng(sc.seed + 1, "clutter"), exclude_ids=(7,))
    assert len(items) == c.count + c.markers
    centre = np.asarray(sc.load.formation.start_w_m) - (sc.load.formation.circle_radius_m, 0.0)
    for it in items:
        r = math.dist(it.pos_w_m[:2], centre)
        assert r - it.footprint_m >= sc.flight_reach_m()  # outside the formation's whole circle
        assert math.dist(it.pos_w_m[:2], c.center_w_m) + it.footprint_m <= c.outer_radius_m
        assert it.pos_w_m[2] == pytest.approx(it.half_m[2])  # standing on the ground
    ids = [it.marker_id for it in items if it.kind == "crate"]
    assert len(ids) == c.markers == len(set(ids)) and 7 not in ids
    with pytest.raises(ConfigError, match="scene"):  # a ring whose inside does not hold the flight
        load(REALISTIC, settings={"scene.clutter.inner_radius_m": 3.0})


def test_the_scene_in_the_model_is_seeded_and_visual_only():
    import mujoco

    from sitl.cameras.rig import vision_mjcf

    scene = SceneConfig(ground="noise", lighting=LightingConfig(enabled=True, cloud_cover=0.5),
                        clutter=ClutterConfig(count=5, markers=2, inner_radius_m=4.0, outer_radius_m=8.0))
    cams = (CameraMount(name="c", body="world", pos_b_m=(0.0, 0.0, 3.0), width_px=32, height_px=24),)
    xml, assets = vision_mjcf(GROUND_XML, cams, (), scene=scene, seed=3)
    assert (xml, assets) == vision_mjcf(GROUND_XML, cams, (), scene=scene, seed=3)
    m = mujoco.MjModel.from_xml_string(xml, assets)
    clutter = [m.geom(i) for i in range(m.ngeom) if m.geom(i).name.startswith("clutter")]
    assert len(clutter) == 5 + 2 * 2  # the crates carry their marker plates
    assert all(g.contype[0] == 0 and g.conaffinity[0] == 0 for g in clutter)
    assert "scene_ground.png" in assets and sum(k.startswith("clutter_marker") for k in assets) == 2
    sun = m.light("sun")
    assert sun.dir[2] < 0 and np.allclose(sun.diffuse, 0.7) and np.allclose(m.vis.headlight.diffuse, 0.0)
    other, _ = vision_mjcf(GROUND_XML, (), (), scene=scene, seed=4)
    assert other != xml  # another seed: another sun, another clutter
    plain, none = vision_mjcf(GROUND_XML, (), (), scene=SceneConfig(), seed=3)
    assert none == {} and plain.count("<geom") == GROUND_XML.count("<geom")


@pytest.mark.rendering
def test_a_tiny_frame_of_the_lit_scene_under_a_passing_cloud():
    import mujoco

    from sitl.cameras.rig import CameraRig, vision_mjcf

    cam = CameraMount(name="c", body="world", pos_b_m=(0.0, 0.0, 3.0), width_px=32, height_px=24, noise_std_dn=0.0,
                      latency_s=0.01,
                      latency_jitter_s=0.02, vignetting=0.2)
    scene = SceneConfig(ground="checker", ground_tile_m=1.0, lighting=LightingConfig(enabled=True, cloud_cover=0.5,
                                                                                     cloud_depth=0.8))
    xml, assets = vision_mjcf(GROUND_XML, (cam,), (), scene=scene, seed=0)
    m = mujoco.MjModel.from_xml_string(xml, assets)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    with CameraRig(m, d, (cam,), (), 0.001, seed=0, scene=scene) as rig:
        rig.on_tick(0, 0.0)  # the one render
        (f,) = rig.poll(1.0)
        sun = m.light_diffuse[rig.sun_id, 0]
        rig.light(50.0)
        factors = [rig.sun.factor(t) for t in np.arange(0.0, 60.0, 0.5)]
        assert m.light_diffuse[rig.sun_id, 0] == pytest.approx(0.7 * rig.sun.factor(50.0))
    h = f.frame.header
    assert h.t_capture_s == 0.0 and 0.01 <= h.t_available_s <= 0.01 + 0.02
    assert sun == pytest.approx(0.7 * factors[0])
    assert min(factors) < 0.5 < 0.9 < max(factors)  # the sun comes and goes
    assert f.frame.image.std() > 3  # the checker shows


@pytest.mark.parametrize("std_m, std_deg", [(0.0, 0.0), (0.002, 0.1)], ids=["exact", "mount_error"])
def test_cameras_and_markers_sit_where_their_mount_error_puts_them(std_m, std_deg):
    """A camera and a marker with a mount error are placed in the model off their configured
    mounts by a seeded draw (the same seed: the same placement; another: another), with the
    spread asked over many draws; without one, exactly where configured."""
    import mujoco

    from sitl.cameras.config import MarkerMount, placement_error
    from sitl.cameras.rig import CV_TO_MUJOCO_CAM, mount_rng, vision_mjcf

    cam = CameraMount(name="c", body="world", pos_b_m=(0.0, 0.0, 3.0), width_px=32, height_px=24,
                      mount_std_m=std_m, mount_std_deg=std_deg)
    marker = MarkerMount(id=3, body="world", size_m=0.1, pos_b_m=(1.0, 0.0, 0.5), mount_std_m=std_m,
                         mount_std_deg=std_deg)
    xml, assets = vision_mjcf(GROUND_XML, (cam,), (marker,), seed=5)
    assert xml == vision_mjcf(GROUND_XML, (cam,), (marker,), seed=5)[0]
    m = mujoco.MjModel.from_xml_string(xml, assets)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    pos_c, R_c = cam.true_mount(mount_rng(5, "camera", 0))
    pos_m, R_m = marker.true_mount(mount_rng(5, "marker", 3))
    np.testing.assert_allclose(d.cam_xpos[0], pos_c, atol=1e-8)
    np.testing.assert_allclose(d.cam_xmat[0].reshape(3, 3), R_c @ CV_TO_MUJOCO_CAM, atol=1e-8)
    np.testing.assert_allclose(d.site_xpos[m.site("marker3").id], pos_m, atol=1e-8)
    np.testing.assert_allclose(d.site_xmat[m.site("marker3").id].reshape(3, 3), R_m, atol=1e-8)
    off = np.linalg.norm(pos_c - np.asarray(cam.pos_b_m)) + np.linalg.norm(pos_m - np.asarray(marker.pos_b_m))
    assert (off == 0.0) == (std_m == 0.0)
    assert (xml == vision_mjcf(GROUND_XML, (cam,), (marker,), seed=6)[0]) == (std_m == 0.0)
    rng = np.random.default_rng(0)
    draws = [placement_error(rng, std_m, std_deg) for _ in range(4000)]
    dp = np.array([x[0] for x in draws])
    ang = np.degrees([np.arccos(np.clip((np.trace(x[1]) - 1.0) / 2.0, -1.0, 1.0)) for x in draws])
    np.testing.assert_allclose(dp.std(axis=0), std_m, rtol=0.05)
    # the angle of a rotation of N(0, s) per axis: a chi of 3 dof, RMS sqrt(3) s
    assert np.sqrt(np.mean(ang**2)) == pytest.approx(np.sqrt(3) * std_deg, rel=0.05, abs=1e-9)
    assert all(np.allclose(x[1].T @ x[1], np.eye(3), atol=1e-12) for x in draws[:50])

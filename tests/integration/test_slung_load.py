"""The slung-load scenario (sitl.scenarios.slung_load): formation targets, config, a short MuJoCo flight."""

from __future__ import annotations

import base64
import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from companion.configfile import ConfigError
from companion.load.formation import (
    CircleFormationConfig,
    cable_feedforward,
    formation_state,
    formation_targets,
)
from companion.recording.mcap_log import write_run_mcap
from sitl.scenarios import kind_of
from sitl.scenarios.slung_load.config import load_slung_scenario

from ..paths import ROOT

CONFIG = ROOT / "configs" / "sitl" / "load" / "slung_load_three.toml"


@pytest.mark.parametrize("t", [0.0, 5.0, 9.0, 20.0])
def test_formation_geometry(t):
    cfg = CircleFormationConfig(start_s=4.0, ramp_s=4.0)
    f = formation_state(t, cfg)
    # vehicles on the formation's circle around the centre, 120 deg apart, at the altitude
    off = f.pos_w_m - f.center_w_m
    assert np.allclose(np.linalg.norm(off, axis=1), cfg.formation_radius_m)
    assert np.allclose(f.pos_w_m[:, 2], cfg.altitude_m)
    # the centre on the report's circle
    c0 = np.array([cfg.start_w_m[0] - cfg.circle_radius_m, cfg.start_w_m[1]])
    assert math.isclose(np.linalg.norm(f.center_w_m[:2] - c0), cfg.circle_radius_m, rel_tol=1e-12)
    # the same side faces the circle's centre: vehicle 0 always radially outward
    radial = (f.center_w_m[:2] - c0) / cfg.circle_radius_m
    assert np.allclose(off[0, :2] / cfg.formation_radius_m, radial, atol=1e-9)


def test_formation_targets_speed_and_yaw_rate():
    cfg = CircleFormationConfig(start_s=1.0, ramp_s=2.0, speed_m_s=1.5, circle_radius_m=2.0)
    before = formation_targets(0.5, cfg)
    assert all(np.allclose(x.v_w_m_s, 0.0, atol=1e-9) for x in before)
    after = formation_targets(10.0, cfg)
    centre_speed = np.linalg.norm(np.mean([x.v_w_m_s for x in after], axis=0))
    assert centre_speed == pytest.approx(1.5, rel=1e-4)
    assert after[0].omega_d_rad_s[2] == pytest.approx(1.5 / 2.0, rel=1e-4)  # the formation yaws with the circle
    # centripetal acceleration of the centre: v^2 / R
    a_c = np.linalg.norm(np.mean([x.a_w_m_s2 for x in after], axis=0))
    assert a_c == pytest.approx(1.5**2 / 2.0, rel=1e-3)


def test_cable_feedforward_balances_the_load():
    rng = np.random.default_rng(4)
    u = np.column_stack((0.3 * np.cos([0, 2.1, 4.2]), 0.3 * np.sin([0, 2.1, 4.2]), np.ones(3)))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    acc = rng.normal(0, 0.5, 3)
    f = cable_feedforward(u, 1.3, acc)
    assert np.allclose(f.sum(axis=0), 1.3 * (acc + [0, 0, 9.80665]))
    assert np.allclose(np.cross(f, u), 0.0)  # along the cables


def test_config_loads_and_validates(tmp_path):
    assert kind_of(CONFIG).name == "slung_load"
    sc = load_slung_scenario(CONFIG)
    assert sc.load.n == 3 and len(sc.cameras) == 3
    assert sc.marker_in_load().pos_m[2] > 0.5 * sc.load.size_m[2]  # above the top face
    bad = tmp_path / "bad.toml"
    bad.write_text(CONFIG.read_text().replace("marker_id = 7", "marker_id = 8"))
    with pytest.raises(ConfigError, match="marker_id"):
        load_slung_scenario(bad)
    bad.write_text(CONFIG.read_text().replace("cable_length_m = [1.5, 1.5, 1.5]", "cable_length_m = [1.5, 1.5]"))
    with pytest.raises(ConfigError, match="cable_length_m"):
        load_slung_scenario(bad)
    bad.write_text(CONFIG.read_text().replace("sigma_floor_px = 0.1", "sigma_floor_px = 0.0"))
    with pytest.raises(ConfigError, match="sigma_floor_px"):
        load_slung_scenario(bad)
    good = tmp_path / "floor.toml"
    good.write_text(CONFIG.read_text().replace("sigma_floor_px = 0.1", "sigma_floor_px = 0.2"))
    assert load_slung_scenario(good).load.sigma_floor_px == 0.2


@pytest.mark.rendering
def test_short_flight_estimates_the_load(tmp_path):
    """1.2 simulated seconds (hovering with the load, the cameras at 10 Hz): no crash, the cables
    carry the load, every camera sees the marker, and the EKF, UKF and unfiltered estimates exist
    and are near the truth (the filters start from the rigging's prior, not from the truth)."""
    pytest.importorskip("cv2")
    from sitl.scenarios.slung_load.flight import fly_slung_load

    sc = load_slung_scenario(CONFIG, duration_s=1.2)
    sc = replace(sc, load=replace(sc.load, settle_s=0.5))
    m = fly_slung_load(sc, tmp_path, plots=False)
    assert not m["crashed"], m["crash_reason"]
    err = m["load_pose_err"]
    for kind in ("ekf", "ukf", "unfiltered", "ekf_fixed_lag", "ukf_fixed_lag"):
        assert err[kind]["n_samples"] > 0, kind
        assert err[kind]["pos_rms_m"] < 0.1, (kind, err[kind])
        assert err[kind]["att_rms_deg"] < 5.0, (kind, err[kind])
    # the baseline without cameras: the rigging below the vehicles' own estimates
    assert err["camera_free"]["n_samples"] == err["ekf"]["n_samples"] and err["camera_free"]["pos_rms_m"] < 0.1
    for kind in ("ekf", "ukf"):  # the NEES check: the mean and the bounds of such a mean around 6
        nees = m["load_pose_nees"][kind]
        lo, hi = nees["bounds95"]
        assert nees["mean"] > 0 and nees["effective_samples"] >= 1 and lo < 6.0 < hi
        assert nees["inside95"] == (lo <= nees["mean"] <= hi)
    assert m["load_filter_stats"]["ekf"]["accepted"] > 0
    assert m["load_filter_stats"]["ekf"]["mean_dof"] == 6.0  # eq. 4 and the marker's attitude in every image
    assert m["load_fixed_lag_s"] >= max(c.latency_s for c in sc.cameras)
    assert m["load_filter_stats"]["ekf"]["late"] > 0  # the 50 ms camera latency: out-of-sequence updates
    assert min(m["load_vision"]["detection_rate"].values()) > 0.5
    load = np.load(tmp_path / "load.npz")
    tension = load["load_cable_tension"][:, 1:]
    assert np.all(tension[-5:] > 1.0)  # taut: the cables carry the 1 kg box
    assert abs(tension[-5:].sum(axis=1).mean() - 9.80665 * sc.load.mass_kg * 1.5 / sc.load.hang_drop_m()[0]) < 2.0
    assert (tmp_path / "metrics.json").exists() and (tmp_path / "vision.npz").exists()
    # every camera frame kept as JPEG, and as an image channel of run.mcap (the frames in capture order)
    frames = np.load(tmp_path / "camera_frames.npz")
    names = [str(x) for x in frames["frame_names"]]
    assert names == [c.name for c in sc.cameras] and len(frames["frame_t"]) > 10
    _, counts = write_run_mcap(tmp_path)
    assert {t: c for t, c in counts.items() if t.startswith("/camera/")} == {
        f"/camera/{name}/image": int(np.sum(frames["frame_camera"] == j)) for j, name in enumerate(names)}
    with open(tmp_path / "run.mcap", "rb") as f:
        _, ch, msg = next(make_reader(f).iter_messages(topics=[f"/camera/{names[0]}/image"]))
    image = cv2.imdecode(np.frombuffer(base64.b64decode(json.loads(msg.data)["data"]), np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (sc.cameras[0].height_px, sc.cameras[0].width_px, 3)


@pytest.mark.e2e
@pytest.mark.rendering
def test_as_a_fleet_the_companion_flies_the_formation_and_estimates_the_load(tmp_path, fleet_ports):
    """Fleet mode, 5 s: three vehicle processes, one companion, the vision consumer. The companion
    arms the vehicles and flies the formation; every frame the harness renders reaches the
    consumer, every view of the load's marker goes to the companion as an eq. 4 observation over
    its authenticated Zenoh session and into its load EKF, whose estimate is near the truth and
    better than the camera-free pose in attitude."""
    pytest.importorskip("zenoh")
    from sitl.scenarios.slung_load.fleet import launch_slung_load

    sc = load_slung_scenario(CONFIG, duration_s=5.0)
    sc = replace(sc, load=replace(sc.load, settle_s=1.0))
    m = launch_slung_load(sc, tmp_path, speed=0.0, plots=False, **fleet_ports.launch_kwargs)
    assert not m["crashed"] and not m["aborted"] and m["took_off"]
    assert max(m["rms_track_true_m"]) < 0.1  # the companion's formation targets, flown
    frames = m["vision"]["wire"]["published"]
    consumer = json.loads((tmp_path / "vision" / "vision_summary.json").read_text())["load_observations"]
    wire = m["load_observations_wire"]
    assert frames >= 140 and consumer["wrong_vehicle"] == 0 and consumer["published"] >= 0.95 * frames, (frames, consumer)
    # (the consumer stops first and drains the frames in flight; the observations of its last ones may
    # still be on their way when the companion stops: at most a frame's worth)
    assert wire["delivered"] == wire["received"] and wire["rejected"] == 0, wire
    assert consumer["published"] - 3 <= wire["received"] <= consumer["published"], (wire, consumer)
    stats = m["load_filter_stats"]
    ekf = stats["filters"]["ekf"]
    assert ekf["images"] + stats["observations_before_start"] == wire["delivered"], stats
    assert ekf["accepted"] >= 0.9 * ekf["images"], stats
    assert stats["vehicle_samples"] >= 240  # 50 Hz of the links' time
    err = m["load_pose_err"]
    for kind in ("ekf", "ekf_fixed_lag"):
        assert err[kind]["n_samples"] > 100 and err[kind]["pos_rms_m"] < 0.05 and err[kind]["att_rms_deg"] < 3.0, err
    assert err["ekf"]["att_rms_deg"] < 0.5 * err["camera_free"]["att_rms_deg"], err
    assert m["load_fixed_lag_s"] == pytest.approx(0.06)
    assert (tmp_path / "load.npz").exists() and (tmp_path / "companion" / "load.npz").exists()

"""CPG motion in flight: the command schedule, the CPG chain trajectory (hover -> undulation with no
jump, deterministic), the scenario section, limits of the adaptation, and a short batch flight."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from companion.configfile import ConfigError
from companion.estimation.constraints import constraint_residual
from companion.estimation.so3 import attitude_error, quat_to_rotmat
from companion.motion.generator import MotionGenerator
from companion.motion.inverse import InverseModel
from companion.motion.schedule import PACKAGED_MODEL, MotionCommand, MotionConfig, desired_motion
from sitl.scenarios.chain.flight import fly
from sitl.scenario import load_scenario
from companion.trajectory import CpgChainTrajectory, TrajectoryConfig

from ..paths import ROOT

CONFIG = ROOT / "configs" / "sitl" / "chain" / "seven_link_cpg.toml"
MODEL = Path(PACKAGED_MODEL)


@pytest.fixture(scope="module")
def model():
    return InverseModel.load(MODEL)


def test_schedule_validation_and_desired_motion():
    with pytest.raises(ValueError, match="at_s must start at 0"):
        MotionConfig(commands=(MotionCommand(1.0),))
    with pytest.raises(ValueError, match="exclude each other"):
        MotionCommand(0.0, yaw_deg=10.0, yaw_rate_deg_s=2.0)
    cfg = MotionConfig(commands=(MotionCommand(0.0, 0.3), MotionCommand(5.0, 0.5, "vertical", yaw_deg=90.0)))
    assert cfg.active(-1.0) is None and cfg.active(4.9).speed_m_s == 0.3 and cfg.active(5.0).gait == "vertical"
    level = np.eye(3)
    xi = desired_motion(cfg, cfg.active(0.0), level, 0.0)
    np.testing.assert_array_equal(xi, [-0.3, 0, 0, 0, 0, 0, 0])  # head first along -x of {B}
    xi = desired_motion(cfg, cfg.active(6.0), level, 0.0)
    assert xi[5] == pytest.approx(math.radians(cfg.yaw_rate_max_deg_s))  # 90 deg to go: limited rate, turning left
    assert xi[6] == pytest.approx(math.pi / 2)
    # too low: pitch up (positive about y raises the head, which leads along -x), limited
    assert 0 < desired_motion(cfg, cfg.active(0.0), level, -0.5)[4] <= math.radians(cfg.pitch_rate_max_deg_s)
    assert desired_motion(cfg, cfg.active(0.0), level, +0.5)[4] < 0
    assert desired_motion(replace(cfg, hold_altitude=False), cfg.active(0.0), level, 0.5)[4] == 0
    np.testing.assert_array_equal(desired_motion(cfg, None, level, 0.0), np.zeros(7))


def _trajectory(model, commands, start_s=8.0):
    motion = MotionConfig(start_s=start_s, commands=commands)
    cfg = TrajectoryConfig(kind="cpg", takeoff_start_s=1.0, takeoff_duration_s=5.0, takeoff_altitude_m=3.0, yaw_deg=20.0)
    return CpgChainTrajectory(cfg, motion, model, 7, 1.0, [0.0, 0.0, 0.2])


def test_cpg_trajectory_starts_from_the_hover_and_steps_without_jumps(model):
    """Targets are continuous through the motion start and through speed and gait steps (the CPG
    filters the parameter steps), satisfy the chain constraint (eq. 3), and the same schedule
    gives the same numbers."""
    commands = (MotionCommand(0.0, 0.4), MotionCommand(6.0, 0.2, "vertical"), MotionCommand(12.0, 0.4, yaw_deg=40.0))
    traj = _trajectory(model, commands)
    again = _trajectory(model, commands)
    dt = 0.02
    prev = None
    d = np.tile([0.5, 0.0, 0.0], (7, 1))
    for k in range(int(7.0 / dt), int(28.0 / dt)):
        t = k * dt
        targets = traj.targets(t)
        p = np.stack([x.p_w_m for x in targets])
        q = np.stack([x.q_wxyz for x in targets])
        v = np.stack([x.v_w_m_s for x in targets])
        w = np.stack([x.omega_d_rad_s for x in targets])
        assert np.abs(constraint_residual(p, v, q, w, d)).max() < 1e-9
        if prev is not None:
            step = np.linalg.norm(p - prev[0], axis=1).max()
            turn = np.degrees(np.linalg.norm(attitude_error(q, prev[1]), axis=1)).max()
            assert step < 1.2 * dt and turn < 1.5, (t, step, turn)  # under 1.2 m/s and 75 deg/s
        prev = (p, q)
        if k % 50 == 0:
            other = again.targets(t)
            np.testing.assert_array_equal(np.stack([x.p_w_m for x in other]), p)
    # the hover heading carries into the motion: the chain swims towards yaw + 180 deg at first
    assert traj.generator.body.p_w_m[2] == pytest.approx(3.0, abs=0.5)
    with pytest.raises(ValueError, match="already at"):
        traj.targets(10.0)


def test_straight_start_matches_the_hover_targets(model):
    traj = _trajectory(model, (MotionCommand(0.0, 0.3),))
    hover = traj.hover.targets(8.0 - 1e-3)
    start = traj.targets(8.0)
    for h, s in zip(hover, start):
        np.testing.assert_allclose(s.p_w_m, h.p_w_m, atol=1e-9)
        np.testing.assert_allclose(quat_to_rotmat(s.q_wxyz), quat_to_rotmat(h.q_wxyz), atol=1e-9)


def test_adaptation_stays_in_the_models_range_on_an_impossible_command(model):
    """3 m/s is far beyond what the CPG makes: parameters stay within the training range, and the
    integral does not wind up (a reachable command afterwards is tracked again)."""
    gen = MotionGenerator(model)
    for _ in range(6000):
        gen.step(np.array([-3.0, 0, 0, 0, 0, 0, 0]), 0.01)
        assert np.all(gen.eta >= model.eta_low - 1e-12) and np.all(gen.eta <= model.eta_high + 1e-12)
    speeds = []
    for k in range(6000):
        gen.step(np.array([-0.3, 0, 0, 0, 0, 0, 0]), 0.01)
        if k >= 3000:
            speeds.append(-(gen.body.R_wb.T @ gen.body.v_w_m_s)[0])
    assert abs(np.mean(speeds) - 0.3) < 0.05


def test_scenario_motion_section_is_checked(tmp_path):
    sc = load_scenario(CONFIG)
    assert sc.trajectory.kind == "cpg" and Path(sc.motion.model).resolve() == MODEL.resolve()
    text = CONFIG.read_text()
    bad = tmp_path / "bad_model.toml"
    bad.write_text(text.replace("[motion]\n", '[motion]\nmodel = "missing.npz"\n'))
    with pytest.raises(ConfigError, match="motion.model: cannot load"):
        load_scenario(bad)
    wrong = tmp_path / "five.toml"
    wrong.write_text(text.replace("n_links = 7", "n_links = 5").replace("groups = [[1, 2], [3, 4, 5], [6, 7]]",
                                                                    "groups = [[1, 2], [3], [4, 5]]"))
    with pytest.raises(ConfigError, match="is for 7 links of 1 m, the skeleton has 5"):
        load_scenario(wrong)
    typo = tmp_path / "typo.toml"
    typo.write_text(text.replace("speed_m_s = 0.45", "sped_m_s = 0.45"))
    with pytest.raises(ConfigError, match=r"motion.commands\[1\].sped_m_s|sped_m_s: unknown key"):
        load_scenario(typo)


def test_short_cpg_batch_flight_tracks_its_targets(tmp_path):
    """Take-off, hover and 10 s of undulation in batch mode: no crash, pose tracking reported."""
    sc = load_scenario(CONFIG, duration_s=20.0)
    metrics = fly(sc, tmp_path, plots=True)
    assert not metrics["crashed"], metrics["crash_reason"]
    assert metrics["pose_track_window_s"][0] == sc.motion.start_s
    assert 0.0 < metrics["rms_pose_track_pos_m"] < 0.4
    assert 0.0 < metrics["rms_pose_track_att_deg"] < 10.0
    assert metrics["motion"][0]["speed_cmd_m_s"] == 0.25 and metrics["motion"][0]["speed_achieved_m_s"] > 0.05
    assert (tmp_path / "body_motion.png").exists() and (tmp_path / "attitude_tracking.png").exists()
    assert np.load(tmp_path / "log.npz")["eta"].shape[1] == 4

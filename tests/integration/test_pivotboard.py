"""The pivotboard in MuJoCo (sitl.scenarios.pivotboard): its model from the config, and its CPG
moving it as the thesis describes: forward with the plates out of phase, backward with the
opposite phase, coasting to a stop at zero phase difference (sec. 4.3.3), curving with a bias."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from companion.motion.oscillators import PhaseMap
from sitl.scenarios import load
from sitl.scenarios.pivotboard.config import PivotCommand, PivotGround

from ..paths import ROOT

CONFIG = ROOT / "configs" / "sitl" / "ground" / "pivotboard.toml"


def _scenario(**changes):
    _, sc = load(CONFIG)
    return replace(sc, **changes)


@pytest.mark.parametrize("incline", [0.0, 5.0])
def test_the_board_starts_on_its_wheels_and_stays_at_rest_without_a_command(incline):
    from sitl.scenarios.pivotboard.model import PivotModel

    sc = _scenario(ground=replace(PivotGround(), incline_deg=incline))
    robot = PivotModel(sc)
    m, d = robot.model, robot.data
    assert [m.jnt_axis[m.joint(f"j{s}").id].tolist() for s in "rl"] == [[0, 0, 1], [0, 0, 1]]
    wheels = [m.body(f"wheel_{s}{k}").id for s in "rl" for k in (1, 2)]
    height = d.xpos[wheels] @ robot.plane.normal
    np.testing.assert_allclose(height, sc.body.wheel_radius_m, atol=1e-6)  # every wheel's axle one radius up
    com = robot.centre_of_mass()
    d.ctrl[:] = 0.0
    robot.step(500)  # one second: on the flat it stays; on the slope it rolls down (free wheels), straight
    moved = robot.in_plane(robot.centre_of_mass() - com)
    if incline == 0.0:
        assert np.linalg.norm(moved) < 1e-3
    else:
        assert moved[0] < -0.05 and abs(moved[1]) < 1e-3


def test_the_plates_phase_difference_drives_it_forward_backward_or_not_at_all():
    from sitl.scenarios.pivotboard.flight import fly_pivotboard

    base = _scenario(duration_s=10.0, settle_s=6.0, commands=(PivotCommand(0.0, 30.0, 0.0, 0.1),))
    speeds = {}
    for phase_deg in (90.0, -90.0):
        sc = replace(base, cpg=replace(base.cpg, phase=PhaseMap.constant(math.radians(phase_deg), 3)))
        speeds[phase_deg] = fly_pivotboard(sc, None)["commands"][0]["v_x_m_s"]["mean"]
    assert speeds[90.0] > 0.03 and speeds[-90.0] == pytest.approx(-speeds[90.0], rel=0.05), speeds
    still = replace(base, commands=(PivotCommand(0.0, 30.0, 0.0, -0.1),))  # slowing down: zero phase difference
    assert abs(fly_pivotboard(still, None)["commands"][0]["v_x_m_s"]["mean"]) < 0.05 * speeds[90.0]


def test_it_speeds_up_then_coasts_to_a_stop_and_a_bias_curves_its_path(tmp_path):
    """The scenario: the speed rises to a plateau while speeding up (the thesis's decaying
    acceleration) and falls once the command slows down; deterministic; with a bias it turns."""
    from sitl.scenarios.pivotboard.flight import fly_pivotboard, pivot_run

    sc = _scenario()
    m = fly_pivotboard(sc, tmp_path, plots=True)
    up, down = m["commands"]
    assert up["v_x_m_s"]["mean"] > 0.03 and down["v_x_m_s"]["mean"] < 0.3 * up["v_x_m_s"]["mean"], m["commands"]
    assert abs(up["omega_rad_s"]["mean"]) < 0.01 and m["servo_rms_deg"]["plates"] < 6.0
    run = pivot_run(replace(sc, duration_s=12.0))
    run.run()
    a = run.arrays()
    v = a["v_x"]
    early, late = v[a["period_t"] < 3.0].mean(), v[(a["period_t"] > 8.0)].mean()
    assert early < 0.7 * late  # accelerating towards the plateau
    assert (tmp_path / "pivotboard.png").exists() and fly_pivotboard(sc, None)["commands"] == m["commands"]
    curved = replace(sc, duration_s=10.0, commands=(PivotCommand(0.0, 30.0, 10.0, 0.1),))
    assert abs(fly_pivotboard(curved, None)["commands"][0]["omega_rad_s"]["mean"]) > 0.01


def test_eq_4_2_fits_its_runs_and_the_bias_sets_the_curvature():
    """Speeding up from rest, the board's speed follows eq. 4.2 (residual a few percent of v_s);
    slowing down it decays to zero; the bias, not the amplitude, bends its path (c ~ B)."""
    from sitl.scenarios.pivotboard.da_fit import fit_runs

    sc = _scenario()
    fits = {B: fit_runs(sc, 30.0, B, 10.0) for B in (0.0, 10.0)}
    for B, (up, down) in fits.items():
        assert up.model.v_s_m_s > 0.04 and up.model.d_per_s > 0.1, up
        assert up.v_rms_m_s < 0.05 * up.model.v_s_m_s, up
        assert abs(down.model.v_s_m_s) < 0.1 * up.model.v_s_m_s and down.model.d_per_s > 0.1, down
    assert abs(fits[0.0][0].model.c_rad_per_m) < 0.02 < fits[10.0][0].model.c_rad_per_m


def test_the_inverse_model_command_learns_both_branches_from_runs_and_records_how(tmp_path):
    """``python -m sitl.scenarios.pivotboard.inverse`` on a few short runs: each run's two halves
    give a sample of each branch and its mirror image; each model has the 2-d bottleneck, records
    the seed, the commit, the fits' residuals, the training range and the held-out error."""
    from companion.motion.inverse import InverseModel
    from sitl.scenarios.pivotboard.config import BRANCHES, model_path
    from sitl.scenarios.pivotboard.inverse import dataset, main

    sc = _scenario()
    eta, xi, residual = dataset(sc, 3, seed=2, A_range_deg=(20.0, 35.0), B_max_deg=20.0, duration_s=6.0)
    assert eta.shape == (6, 2) and all(xi[b].shape == (6, 3) for b in BRANCHES)
    np.testing.assert_allclose(eta[3:], eta[:3] * [1, -1])
    np.testing.assert_allclose(xi["accelerating"][3:], xi["accelerating"][:3] * [1, 1, -1])
    up, down = xi["accelerating"][:3], xi["decelerating"][:3]
    assert np.all(up[:, 0] > 0.02) and np.all(np.abs(down[:, 0]) < 0.3 * up[:, 0]), (up, down)  # slowing: v_s ~ 0
    assert np.all(up[:, 2] > 0.0) and np.all(residual["accelerating"] < 0.1 * up[:, 0])  # a right bias curves it left
    assert main(["--config", str(CONFIG), "--samples", "6", "--held-out", "2", "--duration", "6", "--A", "15,35",
                 "--B-max", "20", "--seed", "1", "--out", str(tmp_path)]) == 0
    for branch in BRANCHES:
        model = InverseModel.load(model_path(tmp_path, branch))
        info = model.info
        assert model.steady is None and info["bottleneck"] == 2 and info["samples"] == 12 and info["branch"] == branch
        assert info["data_seed"] == 1 and info["commit"] and len(info["xi_low"]) == 3 and len(info["held_out_eta_rms_deg"]) == 2


def test_motion_commands_through_the_inverse_model_accelerate_hold_the_line_and_turn():
    """Thesis sec. 4.7.2's two tests (Fig. 4-16), shortened: accelerations with the lateral position
    regulated to zero, then a turn rate at a held speed; once per period the line search and the
    branch's model set the CPG's inputs. Deterministic."""
    from sitl.scenarios.pivotboard.flight import fly_pivotboard, pivot_run

    _, sc = load(ROOT / "configs" / "sitl" / "ground" / "pivotboard_motion.toml")
    sc = replace(sc, duration_s=28.0, commands=(
        PivotCommand(0.0, mode="acceleration", v_dot_d_m_s2=0.006, hold_line=True),
        PivotCommand(8.0, mode="acceleration", v_dot_d_m_s2=-0.004, hold_line=True),
        PivotCommand(14.0, mode="velocity", v_x_m_s=0.04, omega_rad_s=0.02)))
    m = fly_pivotboard(sc, None)
    up, down, turn = m["commands"]
    assert up["v_dot_rms_err_m_s2"] < 0.15 * 0.006 and up["y_rms_m"] < 0.01, up  # planned ahead (the lead)
    assert down["v_dot_rms_err_m_s2"] < 0.3 * 0.004 and down["y_rms_m"] < 0.01, down
    assert turn["v_x_rms_err_m_s"] < 0.01 and turn["omega_rms_err_rad_s"] < 0.3 * 0.02, turn
    assert fly_pivotboard(sc, None)["commands"] == m["commands"]
    run = pivot_run(replace(sc, duration_s=6.0))
    run.run()
    log = np.array(run.cpg.control.log)  # (t, v, v_dot, omega, v_dot_d, omega_d, A, B, branch, v_x_d) per period
    np.testing.assert_allclose(log[:, 0], np.arange(7.0), atol=1e-9)
    assert np.all(log[:, 8] == 1) and np.all(np.diff(log[2:, 6]) > 0)  # speeding up: the amplitude grows
    with pytest.raises(ValueError, match="control.model_folder"):
        replace(sc, control=replace(sc.control, model_folder=""))
    with pytest.raises(ValueError, match="hold_line"):
        PivotCommand(0.0, 30.0, hold_line=True)


def test_on_the_slippery_plane_the_adaptation_recovers_the_commanded_speed():
    """Figs. 4-17/4-18 (bottom): on 0.3 friction the model learnt on 1.0 leaves the board well below
    the commanded motion; with the adaptation it comes back towards it."""
    from sitl.scenarios.pivotboard.flight import fly_pivotboard

    _, sc = load(ROOT / "configs" / "sitl" / "ground" / "pivotboard_slippery.toml")
    v_d = sc.commands[0].v_x_m_s
    final = {}
    for adapt in (False, True):
        run_sc = replace(sc, control=replace(sc.control, adapt=adapt),
                         commands=(sc.commands[0], replace(sc.commands[0], t_s=sc.duration_s - 10.0 - sc.settle_s)))
        final[adapt] = fly_pivotboard(run_sc, None)["commands"][1]["v_x_rms_err_m_s"]
    assert final[False] > 0.3 * v_d, final
    assert final[True] < 0.3 * final[False], final


def test_a_sweep_flies_on_the_campaign_engines_cluster_and_writes_the_same_map(tmp_path, dask_cluster):
    """``--scheduler``: eq. 4.1's sweep as tasks on a Dask scheduler's workers (started as a user
    starts them) writes the map the local run writes, to the byte."""
    from sitl.scenarios.pivotboard.phase_map import main

    args = ["--config", str(CONFIG), "--A", "20,30", "--B", "0", "--phases", "4", "--duration", "4"]
    assert main([*args, "--out", str(tmp_path / "local.toml")]) == 0
    assert main([*args, "--scheduler", dask_cluster, "--out", str(tmp_path / "remote.toml")]) == 0
    assert (tmp_path / "remote.toml").read_text() == (tmp_path / "local.toml").read_text()

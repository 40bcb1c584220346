"""Expected physics (thesis sec. 4.4): targets consistent with eq. 3, drag dissipates, the passive
midpoint rotation conserves the free rigid body's invariants, undulation swims and bias turns."""

from __future__ import annotations

import numpy as np
import pytest

from companion.estimation.constraints import constraint_residual
from companion.estimation.so3 import rotmat_to_quat
from companion.motion.cpg import Cpg, CpgParams, so3_exp
from companion.motion.expected_physics import (
    BodyState,
    WaterParams,
    body_step,
    body_wrench,
    chain_shape,
    link_drag,
    link_targets,
)
from companion.motion.__main__ import main
from companion.motion.steady import SteadyConfig, sample_parameters, steady_motion

HALF = 0.5


#: steps of two whole undulation periods at the default frequency (dt 0.01 s)
WHOLE = int(round(2.0 / (CpgParams(7).frequency_hz * 0.01)))


def _swim(A, B, seconds, n=7, dt=0.01):
    cpg, water, body = Cpg(CpgParams(n)), WaterParams(), BodyState.at_rest()
    vel, rate = [], []
    for _ in range(int(round(seconds / dt))):
        cpg.step(A, B, dt)
        _, R, om = cpg.output()
        f, tau = body_wrench(body, R, om, HALF, water)
        body = body_step(body, f, tau, water, dt)
        vel.append(body.R_wb.T @ body.v_w_m_s)
        rate.append(body.omega_b_rad_s)
    return cpg, body, np.array(vel), np.array(rate)


@pytest.mark.parametrize("n", [3, 5, 7])
def test_link_targets_satisfy_the_chain_constraint_exactly(n):
    cpg, body, _, _ = _swim([0.5, 0.2], [0.1, 0.05], 3.0, n=n)
    _, R_bl, om = cpg.output()
    p, v, R_wl, omega_l = link_targets(body, R_bl, om, HALF)
    d = np.tile([HALF, 0.0, 0.0], (n, 1))
    c = constraint_residual(p, v, rotmat_to_quat(R_wl), omega_l, d)
    np.testing.assert_allclose(c, 0.0, atol=1e-12)
    r, _ = chain_shape(R_bl, om, HALF)
    np.testing.assert_allclose(r.mean(axis=0), 0.0, atol=1e-12)  # {B} sits at the centre of mass


def test_drag_opposes_motion_and_is_anisotropic():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(200, 3))
    f = link_drag(v, WaterParams())
    assert np.all(np.einsum("ni,ni->n", f, v) <= 0.0)
    fa = link_drag(np.array([[1.0, 0, 0]]), WaterParams())[0, 0]
    fn = link_drag(np.array([[0, 1.0, 0]]), WaterParams())[0, 1]
    assert fn < 10 * fa < 0  # the normal drag is far larger: undulation makes thrust


def test_passive_midpoint_rotation_keeps_the_free_body_invariants():
    water = WaterParams(inertia_kg_m2=(1.0, 2.0, 3.5))
    J = np.array(water.inertia_kg_m2)
    body = BodyState(np.zeros(3), np.zeros(3), np.eye(3), np.array([0.3, 2.0, 0.4]))  # near the unstable axis
    energy0 = 0.5 * body.omega_b_rad_s @ (J * body.omega_b_rad_s)
    momentum0 = np.linalg.norm(J * body.omega_b_rad_s)
    for _ in range(3000):
        body = body_step(body, np.zeros(3), np.zeros(3), water, 0.01, iterations=12)
    w = body.omega_b_rad_s
    assert 0.5 * w @ (J * w) == pytest.approx(energy0, rel=1e-9)
    assert np.linalg.norm(J * w) == pytest.approx(momentum0, rel=1e-9)
    np.testing.assert_allclose(body.R_wb.T @ body.R_wb, np.eye(3), atol=1e-12)
    # the world-frame momentum is kept only to second order (the rule is not a Lie-group
    # variational integrator): 30 s near the unstable axis move it by less than 0.1%
    world_momentum = body.R_wb @ (J * w)
    np.testing.assert_allclose(world_momentum, J * np.array([0.3, 2.0, 0.4]), rtol=0, atol=1e-3 * momentum0)


def test_undulation_swims_head_first_faster_with_amplitude_and_bias_turns():
    speeds = []
    for A in (0.3, 0.5):
        _, _, vel, rate = _swim([A, 0.0], [0.0, 0.0], 30.0)
        last = slice(-WHOLE, None)  # whole undulation periods at steady state
        speeds.append(-vel[last, 0].mean())  # head (link 1) first: along -x of {B}
        assert abs(rate[last, 2].mean()) < 0.02 * speeds[-1]  # no bias: no net turn
    assert 0 < speeds[0] < speeds[1]
    _, _, _, rate_left = _swim([0.5, 0.0], [0.15, 0.0], 30.0)
    _, _, _, rate_right = _swim([0.5, 0.0], [-0.15, 0.0], 30.0)
    turn = rate_left[-WHOLE:, 2].mean()
    assert abs(turn) > 0.02 and rate_right[-WHOLE:, 2].mean() == pytest.approx(-turn, rel=1e-3)  # mirror image


def test_a_straight_chain_at_rest_stays_at_rest():
    cpg, body, vel, rate = _swim([0.0, 0.0], [0.0, 0.0], 2.0)
    np.testing.assert_allclose(vel, 0.0, atol=1e-15)
    np.testing.assert_allclose(body.R_wb, so3_exp(np.zeros(3)), atol=1e-15)


def test_a_batch_of_parameter_sets_simulates_like_each_alone():
    """Leading batch dimensions: one vectorised run equals the runs one by one."""
    etas = np.array([[0.5, 0.0, 0.1, 0.0], [0.2, 0.4, 0.0, 0.1], [0.0, 0.0, 0.0, 0.0]])
    cfg = SteadyConfig(n_links=5, settle_s=2.0, periods=1)
    batch = steady_motion(etas, cfg)
    for k, eta in enumerate(etas):
        np.testing.assert_allclose(batch[k], steady_motion(eta[None], cfg)[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(batch[2, :6], 0.0, atol=1e-15)  # no undulation, no motion


def test_the_steady_state_is_steady_and_sampling_is_seeded():
    eta = np.array([[0.5, 0.0, 0.05, 0.0], [0.0, 0.4, 0.0, 0.0]])
    a = steady_motion(eta, SteadyConfig(settle_s=30.0, periods=4))
    b = steady_motion(eta, SteadyConfig(settle_s=38.0, periods=4))  # four periods later
    np.testing.assert_allclose(a[:, :6], b[:, :6], atol=2e-3)
    assert a[0, 0] < -0.3 and a[1, 0] < -0.3  # swims head first either way
    assert a[0, 6] == 0.0 and a[1, 6] == pytest.approx(np.pi / 2)
    np.testing.assert_array_equal(sample_parameters(5, np.random.default_rng(3)),
                                  sample_parameters(5, np.random.default_rng(3)))


def test_dataset_command_is_seeded_and_names_its_columns(tmp_path, capsys):
    args = ["dataset", "--samples", "8", "--settle", "2", "--periods", "1", "--quiet"]
    assert main(args + ["--out", str(tmp_path / "a")]) == 0
    assert main(args + ["--out", str(tmp_path / "b")]) == 0
    a, b = np.load(tmp_path / "a" / "cpg_dataset.npz"), np.load(tmp_path / "b" / "cpg_dataset.npz")
    np.testing.assert_array_equal(a["xi"], b["xi"])
    assert a["eta"].shape == (8, 4) and list(a["xi_names"]) == ["v_x", "v_y", "v_z", "omega_x", "omega_y",
                                                                "omega_z", "theta"]
    assert main(["dataset", "--samples", "0", "--out", str(tmp_path / "c")]) == 2
    assert "need k >= 1" in capsys.readouterr().err

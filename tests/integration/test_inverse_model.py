"""Inverse CPG model (thesis sec. 4.5.1) and adaptation (eq. 4.3): gradients, held-out recovery,
save/load, and forward-speed tracking in the expected physics with a model error."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import check_grad

from companion.motion.cpg import CpgParams
from companion.motion.expected_physics import WaterParams
from companion.motion.generator import MotionGenerator
from companion.motion.inverse import InverseModel, Mlp, train_inverse_model
from companion.motion.schedule import PACKAGED_MODEL
from companion.motion.steady import SteadyConfig, sample_parameters, steady_motion


@pytest.fixture(scope="module")
def data():
    eta = sample_parameters(600, np.random.default_rng(11))
    xi = steady_motion(eta, SteadyConfig(settle_s=20.0, periods=2))
    return eta, xi


@pytest.fixture(scope="module")
def model(data):
    eta, xi = data
    return train_inverse_model(eta[:500], xi[:500], seed=0, max_iter=2000)


def test_backprop_and_jacobian_match_finite_differences():
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(30, 5)), rng.normal(size=(30, 3))
    net = Mlp.init((5, 7, 3), rng)

    def loss(t):
        out, _ = net.with_flat(t).forward(x)
        return np.mean(np.sum((out - y) ** 2, axis=1))

    def grad(t):
        n = net.with_flat(t)
        out, acts = n.forward(x)
        dW, db, _ = n.backward(acts, 2 * (out - y) / len(x))
        return np.concatenate([a.ravel() for pair in zip(dW, db) for a in pair])

    assert check_grad(loss, grad, net.flat()) < 1e-5
    bottleneck = Mlp.init((4, 6, 4), rng, tanh_out=True)
    x0, h = rng.normal(size=4), 1e-6
    J = np.stack([(bottleneck((x0 + h * e)[None])[0] - bottleneck((x0 - h * e)[None])[0]) / (2 * h)
                  for e in np.eye(4)], axis=1)
    np.testing.assert_allclose(bottleneck.jacobian(x0), J, atol=1e-8)


def test_inverse_model_recovers_held_out_parameters(data, model, tmp_path):
    """The thesis's Fig. 4-8 check: simulate held-out parameters, recover them from the motion."""
    eta, xi = data
    recovered = model(xi[500:])
    err = np.abs(recovered - eta[500:]).mean(axis=0) / np.array([0.6, 0.6, 0.6, 0.6])
    assert np.all(err < 0.05), err  # mean error under 5% of each parameter's range
    model.save(tmp_path / "inverse.npz")
    again = InverseModel.load(tmp_path / "inverse.npz")
    np.testing.assert_array_equal(again(xi[500:]), recovered)
    stale = dict(np.load(tmp_path / "inverse.npz"))
    stale["version"] = np.array(99)
    np.savez(tmp_path / "stale.npz", **stale)
    with pytest.raises(ValueError, match="format version 99"):
        InverseModel.load(tmp_path / "stale.npz")


def _segments(model, water, adapt, speeds, seconds=40.0, dt=0.01):
    gen = MotionGenerator(model, water=water, adapt=adapt)
    achieved = []
    for v in speeds:
        xi_d = np.array([-v, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # head first along -x of {B}, horizontal
        speed = []
        for _ in range(int(round(seconds / dt))):
            gen.step(xi_d, dt)
            speed.append(-(gen.body.R_wb.T @ gen.body.v_w_m_s)[0])
        achieved.append(np.mean(speed[len(speed) // 2:]))  # the second half of the segment
    return np.array(achieved)


COMMITTED = Path(PACKAGED_MODEL)


@pytest.fixture(scope="module")
def committed():
    return InverseModel.load(COMMITTED)


def test_forward_speed_commands_are_tracked_within_ten_percent(committed):
    """In the expected physics, with the committed model: each segment's mean speed within 10%."""
    model = committed
    speeds = np.array([0.25, 0.45, 0.35])
    achieved = _segments(model, WaterParams(), adapt=True, speeds=speeds)
    assert np.all(np.abs(achieved - speeds) / speeds < 0.10), achieved


@pytest.mark.slow  # a long run: opt in with -m slow
def test_adaptation_reduces_a_deliberate_model_error(committed):
    """Twice the axial drag the model learnt with: the model alone is 20-30% slow; eq. 4.3 fixes it."""
    model = committed
    speeds = np.array([0.25, 0.45, 0.35])
    draggy = WaterParams(cd_axial=0.4)
    plain = np.abs(_segments(model, draggy, adapt=False, speeds=speeds) - speeds) / speeds
    adapted = np.abs(_segments(model, draggy, adapt=True, speeds=speeds) - speeds) / speeds
    assert np.all(plain > 0.15)
    assert adapted.mean() < 0.5 * plain.mean() and np.all(adapted[1:] < 0.10), (plain, adapted)


def test_the_committed_model_matches_the_current_physics():
    """companion/motion/models/inverse_cpg_7link.npz against freshly simulated parameters (a stale model fails)."""
    model = InverseModel.load(COMMITTED)
    # the file records the physics it was made with: today's defaults
    assert replace(model.steady, cpg=None) == SteadyConfig() and model.steady.cpg_params == CpgParams(7)
    eta = sample_parameters(40, np.random.default_rng(2024))
    xi = steady_motion(eta, SteadyConfig())
    err = np.abs(model(xi) - eta).mean(axis=0) / np.array([0.6, 0.6, 0.6, 0.6])
    assert np.all(err < 0.05), err


def test_a_two_dimensional_model_without_a_physics_record_saves_adapts_and_refuses_to_fly_a_chain(tmp_path):
    """The snake's shape of the model (sec. 4.5.2: xi in R^3, h and eta in R^2) on a smooth made-up
    map: it recovers held-out inputs, its Jacobian and the adaptation are 2 x 2, it round-trips
    through its file with no physics record, and a chain's config refuses it."""
    from companion.configfile import ConfigError
    from companion.motion.inverse import Adaptation
    from sitl.scenario import load_scenario

    from ..paths import ROOT

    rng = np.random.default_rng(3)
    eta = np.column_stack((rng.uniform(0.3, 0.7, 400), rng.uniform(-0.15, 0.15, 400)))
    xi = np.column_stack((2.0 * eta[:, 0] - eta[:, 1] ** 2, 0.1 * eta[:, 1], -3.0 * eta[:, 1] * eta[:, 0]))
    m = train_inverse_model(eta[:300], xi[:300], seed=0, hidden=12, steady=None, bottleneck=2, info={"robot": "test"})
    err = np.sqrt(np.mean((m(xi[300:]) - eta[300:]) ** 2, axis=0))
    assert np.all(err < 0.02 * np.ptp(eta, axis=0)), err
    h = m.encode(xi[0])[0]
    assert h.shape == (2,) and m.eta_jacobian(h).shape == (2, 2)
    adapt = Adaptation(m)
    assert adapt.integral.shape == (2,) and adapt.update(xi[0], xi[1], 1.0).shape == (2,)
    m.save(tmp_path / "snake.npz")
    back = InverseModel.load(tmp_path / "snake.npz")
    assert back.steady is None and back.info["robot"] == "test" and back.info["bottleneck"] == 2
    np.testing.assert_array_equal(back(xi[300:]), m(xi[300:]))
    cfg = tmp_path / "cpg.toml"
    cfg.write_text((ROOT / "configs/sitl/chain/seven_link_cpg.toml").read_text()
                   .replace("[motion]", f'[motion]\nmodel = "{tmp_path / "snake.npz"}"', 1))
    with pytest.raises(ConfigError, match="not a flying chain's model"):
        load_scenario(cfg)

"""The companion's load tracker (:mod:`companion.load.tracker`): its vehicle samples from link
states, its filters against a :class:`~companion.load.filter.LoadPoseFilter` fed by hand (the
oracle), its fixed-lag rows and what it refuses."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_euler_zyx
from companion.load.config import LoadConfig
from companion.load.estimate import initial_estimate
from companion.load.filter import LoadPoseFilter
from companion.load.measurements import marker_in_camera, observation_from_pnp
from companion.load.model import Pose3, VehicleStates
from companion.load.tracker import LoadTracker, log_keys, vehicle_states
from companion.messages import LinkState

LOAD = LoadConfig()
CAMERA = Pose3(np.array([0.15, 0.0, -0.05]), np.array([0.5, -0.5, 0.5, -0.5]))
MARKER = Pose3(np.array([0.0, 0.0, 0.102]), np.array([1.0, 0.0, 0.0, 0.0]))
DT = 0.02


def _link_state(i: int, t: float, p, v=(0.0, 0.0, 0.0)) -> LinkState:
    P = np.diag([1e-4] * 3 + [1e-3] * 3 + [1e-5] * 3)
    return LinkState(i, t, np.asarray(p, dtype=float), np.asarray(v, dtype=float), np.array([1.0, 0.0, 0.0, 0.0]),
                     np.zeros(3), P)


def _stream(seed: int, n_samples: int = 60):
    """Vehicles hovering in the formation's start with estimation noise, the load hanging below at
    rest, and every 5th sample one camera's noisy observation of it (captured 0.05 s earlier)."""
    rng = np.random.default_rng(seed)
    f = LOAD.formation
    angles = 2.0 * np.pi * np.arange(3) / 3
    pos = np.column_stack((f.formation_radius_m * np.cos(angles), f.formation_radius_m * np.sin(angles),
                           np.full(3, f.altitude_m)))
    load = LOAD.nominal_pose(np.array([0.0, 0.0, f.altitude_m]), 0.0)
    q = quat_from_euler_zyx(angles + np.pi / 2, np.zeros(3), np.zeros(3))
    samples, observations = [], []
    for k in range(n_samples):
        t = 1.0 + k * DT
        noisy = pos + rng.normal(0.0, 0.005, (3, 3))
        samples.append(VehicleStates(t, noisy, np.zeros((3, 3)), np.broadcast_to(np.eye(3) * 1e-4, (3, 3, 3)), q,
                                     np.broadcast_to(np.eye(3) * 1e-5, (3, 3, 3))))
        if k % 5 == 4:
            i = (k // 5) % 3
            R_cm, t_cm = marker_in_camera(load, Pose3(pos[i], q[i]), CAMERA, MARKER)
            cov = np.diag([1e-4] * 3 + [1e-6] * 3)
            observations.append((k, observation_from_pnp(i, t - 0.05, R_cm, t_cm + rng.normal(0.0, 1e-3, 3), cov,
                                                         CAMERA, MARKER)))
    return samples, observations


def test_vehicle_states_carry_each_link_to_the_time_all_have_reached_and_refuse_the_silent():
    states = [_link_state(0, 2.00, [0, 0, 3], [1, 0, 0]), _link_state(1, 2.02, [1, 0, 3]),
              _link_state(2, 1.98, [0, 1, 3], [0, 0, -1])]
    states[1] = replace(states[1], omega_b_rad_s=np.array([0.0, 0.0, 0.5]))
    veh = vehicle_states(states)
    assert veh.stamp_s == pytest.approx(1.98)
    np.testing.assert_allclose(veh.pos_w_m, [[-0.02, 0, 3], [1, 0, 3], [0, 1, 3]], atol=1e-12)
    # link 2 yawing at 0.5 rad/s, carried back 0.04 s
    np.testing.assert_allclose(veh.q_wxyz[1], [np.cos(-0.01), 0.0, 0.0, np.sin(-0.01)], atol=1e-12)
    np.testing.assert_array_equal(veh.q_wxyz[0], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(veh.pos_cov_m2[0], np.eye(3) * 1e-4)
    np.testing.assert_array_equal(veh.att_cov_rad2[0], np.eye(3) * 1e-5)
    assert vehicle_states([states[0], None, states[2]]) is None
    assert vehicle_states([states[0], states[1], _link_state(2, 1.0, [0, 1, 3])]) is None  # 1 s older


@pytest.mark.parametrize("seed", range(2))
def test_the_trackers_filter_is_the_filter_fed_by_hand(seed):
    samples, observations = _stream(seed)
    tracker = LoadTracker(LOAD, kinds=("ekf",), fixed_lag_s=0.1)
    prior = LOAD.camera_free_pose(samples[0].pos_w_m)
    oracle = LoadPoseFilter("ekf", LOAD.params(), LOAD.filter, initial_estimate(
        samples[0].stamp_s, prior.pos_m, prior.q_wxyz, samples[0], LOAD.params(), pos_sigma_m=0.1, att_sigma_rad=0.1))
    due = dict(observations)
    for k, veh in enumerate(samples):
        if k in due:
            tracker.push_observation(due[k])
            oracle.push_observation(due[k])
        got = tracker.push_vehicles(veh)["ekf"]
        want = oracle.push_vehicles(veh)
        np.testing.assert_array_equal(got.x, want.x)
    a = tracker.arrays()
    assert set(a) == {f"load_{k}" for k in log_keys(("ekf",))}
    assert len(a["load_t"]) == len(samples) and len(a["load_lag_t"]) == len(samples) - 5  # from 0.1 s after the start
    np.testing.assert_allclose(a["load_lag_t"], a["load_t"][5:] - 0.1)
    np.testing.assert_array_equal(a["load_ekf_fixed_lag_p"][-1], oracle.estimate_at(samples[-1].stamp_s - 0.1).pos_w_m)
    stats = tracker.stats()
    assert stats["filters"]["ekf"]["accepted"] == len(observations) and stats["vehicle_samples"] == len(samples)
    # the cameras pull the estimate to the load's pose from the rigging's prior (both are the truth here)
    truth = LOAD.nominal_pose(np.array([0.0, 0.0, LOAD.formation.altitude_m]), 0.0)
    assert np.linalg.norm(a["load_ekf_p"][-1] - truth.pos_m) < 0.02


def test_the_tracker_counts_what_comes_before_it_starts_and_refuses_a_vehicle_without_a_cable():
    samples, observations = _stream(0, n_samples=10)
    tracker = LoadTracker(LOAD)
    tracker.push_observation(observations[0][1])
    assert tracker.stats()["observations_before_start"] == 1 and not tracker.started
    tracker.push_vehicles(samples[0])
    obs = observations[0][1]
    with pytest.raises(ValueError, match="vehicle 4: the load hangs from 3"):
        tracker.push_observation(type(obs)(3, obs.stamp_s, obs.vehicle_in_load_m, obs.cov_m2))
    assert "lag_t" not in tracker.arrays("")  # no fixed lag asked for


@pytest.mark.parametrize("kinds, lag", [((), 0.0), (("kf",), 0.0), (("ekf",), -0.1), (("ekf",), 0.5)])
def test_a_tracker_refuses_unknown_filters_and_a_lag_beyond_the_filters_history(kinds, lag):
    with pytest.raises(ValueError):
        LoadTracker(LOAD, kinds=kinds, fixed_lag_s=lag)

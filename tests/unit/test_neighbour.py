"""A camera on one link seeing its neighbour's marker (companion.estimation.neighbour): the model
against its inverse, its Jacobians against finite differences, common-mode invariance, and the
update's consistency by Monte Carlo; in a chain, the updates before the constraint application."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.chain import ERR_DIM, ERR_P, ERR_TH, ChainInputError
from companion.estimation.neighbour import (ITERATIONS, NeighbourMeasurement, NeighbourView, marker_in_camera,
                                            mount_covariance, neighbour_updates, relative_pose_jacobian,
                                            relative_pose_residual, relative_pose_update)
from companion.estimation.sckf import CAParams, constraint_apply_dense, diagonal_blocks
from companion.estimation.so3 import (attitude_error, quat_conj, quat_from_rotvec, quat_mul, quat_to_rotmat,
                                     quat_to_rotvec, retract, rotmat_to_quat)
from companion.vision.geometry import frame_from_axes

#: a camera at link 1's right tip looking along +x (its neighbour), a marker on top of link 2's
#: centre facing it (a chain stretched along x, links 1 m long: the marker 0.55 m away)
VIEW = NeighbourView(camera_pos_b_m=np.array([0.45, 0.0, 0.05]), R_b_c=frame_from_axes([1.0, 0.0, 0.0], [0.0, -1.0, 0.0]),
                     marker_pos_b_m=np.array([0.0, 0.0, 0.08]), R_b_m=frame_from_axes([-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))


def _pair(rng):
    """Two neighbouring links about 1 m apart along x, slightly tilted."""
    p = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]]) + rng.normal(0.0, 0.05, (2, 3))
    q = quat_from_rotvec(rng.normal(0.0, 0.1, (2, 3)))
    v = rng.normal(0.0, 0.3, (2, 3))
    return p, v, q


def test_the_model_gives_the_marker_where_the_geometry_puts_it():
    rng = np.random.default_rng(0)
    p, _, q = _pair(rng)
    R_cm, t_cm = marker_in_camera(p[0], q[0], p[1], q[1], VIEW)
    R_i, R_j = quat_to_rotmat(q[0]), quat_to_rotmat(q[1])
    cam_w, marker_w = p[0] + R_i @ VIEW.camera_pos_b_m, p[1] + R_j @ VIEW.marker_pos_b_m
    R_wc = R_i @ VIEW.R_b_c
    np.testing.assert_allclose(R_wc @ t_cm + cam_w, marker_w, atol=1e-12)
    np.testing.assert_allclose(R_wc @ R_cm, R_j @ VIEW.R_b_m, atol=1e-12)
    assert t_cm[2] > 0.5  # in front of the camera
    np.testing.assert_allclose(relative_pose_residual(R_cm, t_cm, p[0], q[0], p[1], q[1], VIEW), 0.0, atol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_the_jacobians_match_finite_differences(seed):
    """The model in the tangent space at the estimate, ``[Log(R_cm(x) R_cm(x_hat)^T); t_cm(x)]``,
    differentiated numerically over each link's error state, against ``(H_i, H_j)``."""
    rng = np.random.default_rng(seed)
    p, _, q = _pair(rng)
    R_hat, _ = marker_in_camera(p[0], q[0], p[1], q[1], VIEW)
    H = np.hstack(relative_pose_jacobian(p[0], q[0], p[1], q[1], VIEW))
    eps = 1e-6

    def model(delta):
        dx = delta.reshape(2, ERR_DIM)
        pp = p + dx[:, ERR_P]
        qq = np.stack([retract(q[k], dx[k, ERR_TH]) for k in range(2)])
        R_cm, t_cm = marker_in_camera(pp[0], qq[0], pp[1], qq[1], VIEW)
        return np.r_[attitude_error(rotmat_to_quat(R_cm), rotmat_to_quat(R_hat)), t_cm]

    for col in range(2 * ERR_DIM):
        d = np.zeros(2 * ERR_DIM)
        d[col] = eps
        np.testing.assert_allclose((model(d) - model(-d)) / (2 * eps), H[:, col], atol=1e-7)


@pytest.mark.parametrize("std_m, std_deg", [(0.003, 0.0), (0.0, 0.5), (0.002, 0.3)])
def test_the_mounts_covariance_is_the_spread_of_poses_seen_through_miscalibrated_mounts(std_m, std_deg):
    """Monte Carlo: the camera and the marker mounted off their nominal positions and
    orientations by the given errors; the residual of the pose the true mounts give, against the
    model with the nominal mounts, has the covariance mount_covariance says (4000 draws)."""
    rng = np.random.default_rng(7)
    p, _, q = _pair(rng)
    std_rad = np.radians(std_deg)
    res = []
    for _ in range(4000):
        true = NeighbourView(VIEW.camera_pos_b_m + std_m * rng.normal(size=3),
                             VIEW.R_b_c @ quat_to_rotmat(quat_from_rotvec(std_rad * rng.normal(size=3))),
                             VIEW.marker_pos_b_m + std_m * rng.normal(size=3),
                             VIEW.R_b_m @ quat_to_rotmat(quat_from_rotvec(std_rad * rng.normal(size=3))))
        R_cm, t_cm = marker_in_camera(p[0], q[0], p[1], q[1], true)
        res.append(relative_pose_residual(R_cm, t_cm, p[0], q[0], p[1], q[1], VIEW))
    res = np.array(res)
    want = mount_covariance(marker_in_camera(p[0], q[0], p[1], q[1], VIEW)[1], std_m, std_rad)
    got = np.cov(res.T)
    scale = np.sqrt(np.outer(np.diag(want), np.diag(want))) + 1e-30
    np.testing.assert_allclose(got / scale, want / scale, atol=0.1)  # 4000 draws: about 0.03 sampling error


@given(st.lists(st.floats(-50.0, 50.0), min_size=3, max_size=3), st.integers(0, 1000))
@settings(max_examples=30, deadline=None)
def test_a_common_position_error_of_both_links_does_not_move_the_residual(shift, seed):
    """Both links' GNSS off by the same vector: the relative pose does not see it (the chain
    constraint does not either; an absolute measurement would)."""
    rng = np.random.default_rng(seed)
    p, _, q = _pair(rng)
    R_meas, t_meas = marker_in_camera(p[0] + 0.01, q[0], p[1], q[1], VIEW)  # 1 cm off: a residual to keep
    r0 = relative_pose_residual(R_meas, t_meas, p[0], q[0], p[1], q[1], VIEW)
    r1 = relative_pose_residual(R_meas, t_meas, p[0] + shift, q[0], p[1] + shift, q[1], VIEW)
    np.testing.assert_allclose(r1, r0, atol=1e-9)


def test_the_update_is_consistent_and_cuts_the_relative_error():
    """Monte Carlo: truth, estimates drawn from their covariances, a measurement drawn from the
    PnP covariance. The posterior's NEES averages 18 (the 95 % bounds of 400 draws), and the
    relative position error between the links shrinks to what the posterior covariance says."""
    rng = np.random.default_rng(5)
    p_t, v_t, q_t = _pair(rng)
    # 5 cm and 2 deg per link (a single EKF step with 30 cm priors is visibly nonlinear: NEES 28)
    P_blocks = np.stack([np.diag(np.r_[[0.05**2] * 3, [0.1**2] * 3, [np.radians(2.0) ** 2] * 3])] * 2)
    cov = np.diag(np.r_[[np.radians(1.0) ** 2] * 3, [0.01**2, 0.01**2, 0.03**2]])
    L, Lc = np.linalg.cholesky(P_blocks), np.linalg.cholesky(cov)
    R_true, t_true = marker_in_camera(p_t[0], q_t[0], p_t[1], q_t[1], VIEW)
    nees, rel_before, rel_after = [], [], []
    for _ in range(400):
        e = np.einsum("kij,kj->ki", L, rng.standard_normal((2, ERR_DIM)))
        p, v = p_t - e[:, ERR_P], v_t - e[:, 3:6]
        q = np.stack([retract(q_t[k], -e[k, ERR_TH]) for k in range(2)])
        n = Lc @ rng.standard_normal(6)
        R_meas, t_meas = quat_to_rotmat(quat_from_rotvec(n[:3])) @ R_true, t_true + n[3:]
        up = relative_pose_update(p, v, q, P_blocks, R_meas, t_meas, cov, VIEW)
        assert up.accepted
        err = np.concatenate([np.r_[p_t[k] - up.p[k], v_t[k] - up.v[k], attitude_error(q_t[k], up.q[k])]
                              for k in range(2)])
        nees.append(err @ np.linalg.solve(up.P, err))
        rel_before.append(np.linalg.norm((p_t[1] - p_t[0]) - (p[1] - p[0])))
        rel_after.append(np.linalg.norm((p_t[1] - p_t[0]) - (up.p[1] - up.p[0])))
    mean = float(np.mean(nees))
    half = 1.96 * np.sqrt(2 * 18 / 400)
    assert 18 - half < mean < 18 + half
    rms_before, rms_after = np.sqrt(np.mean(np.square(rel_before))), np.sqrt(np.mean(np.square(rel_after)))
    D = np.zeros((3, 2 * ERR_DIM))
    D[:, ERR_DIM:ERR_DIM + 3], D[:, 0:3] = np.eye(3), -np.eye(3)  # p_j - p_i
    assert rms_after < 0.5 * rms_before
    assert rms_after == pytest.approx(np.sqrt(np.trace(D @ up.P @ D.T)), rel=0.15)  # as the posterior says


@pytest.mark.parametrize("iterations", [1, ITERATIONS], ids=["plain", "iterated"])
def test_with_positions_known_to_a_metre_the_iterated_update_gives_the_chain_its_relative_attitude(iterations):
    """Two joined links whose EKFs know their positions to 1 m (GNSS without RTK, the common
    error taken out) and attitudes to 2 deg, a PnP pose precise to a millimetre
    across the line of sight, then the joint constraint. Linearised once at the prior, the
    camera's lever arm is off by as much as the positions are, and the update hides the relative
    attitude in the positions: after the constraint it is no better than before. Iterated, the
    update is consistent (NEES of the 18 dof within its 95 % bounds) and, with the constraint,
    puts the relative pitch and yaw to a small fraction of a degree."""
    rng = np.random.default_rng(8)
    d = np.array([[0.5, 0.0, 0.0]] * 2)
    q_t = quat_from_rotvec(rng.normal(0.0, 0.1, (2, 3)))
    R_t = quat_to_rotmat(q_t)
    p_t = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0] + R_t[0] @ d[0] + R_t[1] @ d[1]])
    v_t = np.zeros((2, 3))
    P_blocks = np.stack([np.diag(np.r_[[1.0] * 3, [0.1**2] * 3, [np.radians(2.0) ** 2] * 3])] * 2)
    cov = np.diag(np.r_[[np.radians(1.0) ** 2] * 3, [0.001**2, 0.001**2, 0.005**2]])
    L, Lc = np.linalg.cholesky(P_blocks), np.linalg.cholesky(cov)
    R_true, t_true = marker_in_camera(p_t[0], q_t[0], p_t[1], q_t[1], VIEW)
    rel_true = quat_mul(quat_conj(q_t[0]), q_t[1])
    nees, rel = [], []
    for _ in range(300):
        e = np.einsum("kij,kj->ki", L, rng.standard_normal((2, ERR_DIM)))
        p, v = p_t - e[:, ERR_P], v_t - e[:, 3:6]
        q = np.stack([retract(q_t[k], -e[k, ERR_TH]) for k in range(2)])
        n = Lc @ rng.standard_normal(6)
        m = NeighbourMeasurement(0, 1, quat_to_rotmat(quat_from_rotvec(n[:3])) @ R_true, t_true + n[3:], cov, VIEW)
        up = neighbour_updates(p, v, q, P_blocks, [m], iterations=iterations)
        err = np.concatenate([np.r_[p_t[k] - up.p[k], v_t[k] - up.v[k], attitude_error(q_t[k], up.q[k])]
                              for k in range(2)])
        nees.append(err @ np.linalg.solve(up.P, err))
        ca = constraint_apply_dense(up.p, up.v, up.q, np.zeros((2, 3)), d, up.P, CAParams(eps=1e-6))
        # (about the line of sight, along x, only the marker's own orientation tells: leave it out)
        rel.append(np.degrees(np.linalg.norm(quat_to_rotvec(quat_mul(quat_mul(quat_conj(ca.q[0]), ca.q[1]),
                                                                           quat_conj(rel_true)))[1:])))
    rms = float(np.sqrt(np.mean(np.square(rel))))
    if iterations == 1:
        assert rms > 0.8 and np.mean(nees) > 18 + 1.96 * np.sqrt(2 * 18 / 300)
    else:
        half = 1.96 * np.sqrt(2 * 18 / 300)
        assert 18 - half < float(np.mean(nees)) < 18 + half
        assert rms < 0.4, rms


def test_the_gate_and_bad_input():
    rng = np.random.default_rng(2)
    p, v, q = _pair(rng)
    P_blocks = np.stack([np.eye(9) * 1e-4] * 2)
    R_cm, t_cm = marker_in_camera(p[0], q[0], p[1], q[1], VIEW)
    far = relative_pose_update(p, v, q, P_blocks, R_cm, t_cm + [0.5, 0.0, 0.0], np.eye(6) * 1e-4, VIEW, gate_chi2=22.46)
    assert not far.accepted and far.nis > 22.46 and np.array_equal(far.p, p)
    with pytest.raises(ChainInputError, match="t_cm_m"):
        relative_pose_update(p, v, q, P_blocks, R_cm, t_cm + np.nan, np.eye(6), VIEW)
    with pytest.raises(ChainInputError, match="P"):
        relative_pose_update(p, v, q, P_blocks[:1], R_cm, t_cm, np.eye(6), VIEW)
    with pytest.raises(ValueError, match="R_b_c"):
        NeighbourView(VIEW.camera_pos_b_m, 2 * np.eye(3), VIEW.marker_pos_b_m, VIEW.R_b_m)


def _chain(rng, n):
    """``n`` links 1 m apart along x, slightly tilted, and their (n, 9, 9) EKF covariances."""
    p = np.stack([[float(k), 0.0, 2.0] for k in range(n)]) + rng.normal(0.0, 0.05, (n, 3))
    q = quat_from_rotvec(rng.normal(0.0, 0.1, (n, 3)))
    v = rng.normal(0.0, 0.3, (n, 3))
    P = np.stack([np.diag(np.r_[[0.05**2] * 3, [0.1**2] * 3, [np.radians(2.0) ** 2] * 3])] * n)
    return p, v, q, P


@pytest.mark.parametrize("observer, observed", [(0, 1), (1, 0)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_joined_links_taken_back_to_a_capture_stay_joined_whatever_their_velocities(seed, observer, observed):
    """Two links joined at their tips (eq. 3: p_2 = p_1 + R_1 d + R_2 d), turning, and velocity
    estimates off by centimetres per second: with the tip vectors the measurement 0.2 s old is
    compared with the pair taken back still joined, the observed link moved with the observer and
    the turn of both about the joint, so a noise-free measurement of that capture agrees
    (NIS near 0, the states stay) whatever the observed link's velocity error; by the two
    velocities alone it does not (the error times the age is centimetres between the links,
    which the update then moves)."""
    rng = np.random.default_rng(seed)
    d = np.array([[0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    q = quat_from_rotvec(rng.normal(0.0, 0.1, (2, 3)))
    p = np.zeros((2, 3))
    p[0] = [0.0, 0.0, 2.0]
    p[1] = p[0] + quat_to_rotmat(q[0]) @ d[0] + quat_to_rotmat(q[1]) @ d[1]
    w = rng.normal(0.0, 0.5, (2, 3))
    v = np.zeros((2, 3))
    v[observer] = rng.normal(0.0, 0.3, 3)
    v[observed] = v[observer] + rng.normal(0.0, 0.3, 3)  # not the joint's: an estimate's error
    age = 0.2
    q_back = np.array([quat_mul(q[k], quat_from_rotvec(-w[k] * age)) for k in range(2)])
    p_back = np.zeros((2, 3))
    p_back[observer] = p[observer] - v[observer] * age
    sign = 1.0 if observed == observer + 1 else -1.0
    p_back[observed] = p_back[observer] + sign * sum(quat_to_rotmat(q_back[k]) @ d[k] for k in range(2))
    # the view's camera on the observer, the marker on the observed (the chain's order reversed for (1, 0))
    R_cm, t_cm = marker_in_camera(p_back[observer], q_back[observer], p_back[observed], q_back[observed], VIEW)
    m = NeighbourMeasurement(observer, observed, R_cm, t_cm, np.diag([1e-6] * 3 + [1e-8] * 3), VIEW, age_s=age)
    P = np.stack([np.diag(np.r_[[0.01**2] * 3, [0.1**2] * 3, [np.radians(0.5) ** 2] * 3])] * 2)
    joined = neighbour_updates(p, v, q, P, [m], w=w, d=d)
    by_velocity = neighbour_updates(p, v, q, P, [m], w=w)
    assert joined.nis[0] < 1e-6 and np.abs(joined.p - p).max() < 1e-6
    assert by_velocity.nis[0] > 10.0 and np.abs(by_velocity.p - p).max() > 0.01
    with pytest.raises(ChainInputError, match="d must be"):
        neighbour_updates(p, v, q, P, [m], w=w, d=d[:1])


def test_in_a_chain_one_measurement_moves_its_pair_as_the_pair_update_does():
    """A measurement between links 1 and 2 of four independent links: those two come out as the
    pair's own update gives them, links 0 and 3 (uncorrelated with them) unchanged."""
    rng = np.random.default_rng(7)
    p, v, q, P = _chain(rng, 4)
    R_cm, t_cm = marker_in_camera(p[1], q[1], p[2], q[2], VIEW)
    R_meas, t_meas, cov = R_cm @ quat_to_rotmat(quat_from_rotvec([0.01, -0.02, 0.0])), t_cm + [0.02, -0.01, 0.03], \
        np.eye(6) * 1e-4
    up = neighbour_updates(p, v, q, P, [NeighbourMeasurement(1, 2, R_meas, t_meas, cov, VIEW)])
    pair = relative_pose_update(p[1:3], v[1:3], q[1:3], P[1:3], R_meas, t_meas, cov, VIEW)
    assert up.accepted.tolist() == [True] and up.nis[0] == pytest.approx(pair.nis)
    np.testing.assert_allclose(up.p[1:3], pair.p, atol=1e-12)
    np.testing.assert_allclose(up.q[1:3], pair.q, atol=1e-12)
    np.testing.assert_allclose(up.P[9:27, 9:27], pair.P, atol=1e-15)
    for k in (0, 3):
        assert np.array_equal(up.p[k], p[k]) and np.array_equal(up.q[k], q[k])
        np.testing.assert_array_equal(diagonal_blocks(up.P)[k], P[k])
    assert not up.P[:9, 9:].any() and np.abs(up.P[9:18, 18:27]).max() > 0.0  # the pair correlated


def test_a_chain_seen_by_its_cameras_is_consistent_and_the_constraint_takes_it_whole():
    """Four links, three cameras (each link seeing the next): over 200 draws the updated chain's
    NEES (36 dof) and the measurements' NIS (6 dof, each against the chain as the updates before
    it left it) are within their 95 % bounds, and the neighbours' relative positions are more
    than halved in error; the whole covariance then goes through the constraint application."""
    rng = np.random.default_rng(11)
    p_t, v_t, q_t, P = _chain(rng, 4)
    cov = np.diag(np.r_[[np.radians(1.0) ** 2] * 3, [0.01**2, 0.01**2, 0.03**2]])
    L, Lc = np.linalg.cholesky(P), np.linalg.cholesky(cov)
    truth = [marker_in_camera(p_t[k], q_t[k], p_t[k + 1], q_t[k + 1], VIEW) for k in range(3)]
    nees, nis, before, after = [], [], [], []
    for _ in range(200):
        e = np.einsum("kij,kj->ki", L, rng.standard_normal((4, ERR_DIM)))
        p, v = p_t - e[:, ERR_P], v_t - e[:, 3:6]
        q = np.stack([retract(q_t[k], -e[k, ERR_TH]) for k in range(4)])
        meas = []
        for k, (R_true, t_true) in enumerate(truth):
            nz = Lc @ rng.standard_normal(6)
            meas.append(NeighbourMeasurement(k, k + 1, quat_to_rotmat(quat_from_rotvec(nz[:3])) @ R_true,
                                             t_true + nz[3:], cov, VIEW))
        up = neighbour_updates(p, v, q, P, meas)
        assert up.accepted.all()
        nis.extend(up.nis)
        err = np.concatenate([np.r_[p_t[k] - up.p[k], v_t[k] - up.v[k], attitude_error(q_t[k], up.q[k])]
                              for k in range(4)])
        nees.append(err @ np.linalg.solve(up.P, err))
        before.append(np.diff(p_t - p, axis=0))
        after.append(np.diff(p_t - up.p, axis=0))
    half = 1.96 * np.sqrt(2 * 36 / 200)
    assert 36 - half < float(np.mean(nees)) < 36 + half
    assert 6 - 1.96 * np.sqrt(2 * 6 / 600) < float(np.mean(nis)) < 6 + 1.96 * np.sqrt(2 * 6 / 600)
    assert np.sqrt(np.mean(np.square(after))) < 0.5 * np.sqrt(np.mean(np.square(before)))
    d = np.tile([0.5, 0.0, 0.0], (4, 1))
    ca = constraint_apply_dense(up.p, up.v, up.q, np.zeros((4, 3)), d, up.P, CAParams(), compiled=False)
    ca_c = constraint_apply_dense(up.p, up.v, up.q, np.zeros((4, 3)), d, up.P, CAParams(), compiled=True)
    np.testing.assert_allclose(ca_c.p, ca.p, atol=1e-9)
    assert ca.iterations >= 1 and np.all(np.isfinite(ca.P))


def test_neighbour_measurements_refuse_bad_input():
    rng = np.random.default_rng(3)
    p, v, q, P = _chain(rng, 3)
    R_cm, t_cm = marker_in_camera(p[0], q[0], p[1], q[1], VIEW)
    with pytest.raises(ChainInputError, match="another"):
        NeighbourMeasurement(1, 1, R_cm, t_cm, np.eye(6), VIEW)
    with pytest.raises(ChainInputError, match="positive definite"):
        NeighbourMeasurement(0, 1, R_cm, t_cm, -np.eye(6), VIEW)
    with pytest.raises(ChainInputError, match="links 2 and 3 of 3"):
        neighbour_updates(p, v, q, P, [NeighbourMeasurement(2, 3, R_cm, t_cm, np.eye(6), VIEW)])
    with pytest.raises(ChainInputError, match="P must be"):
        neighbour_updates(p, v, q, P[:2], [])
    with pytest.raises(ChainInputError, match="p must be finite"):
        neighbour_updates(p + np.nan, v, q, P, [])


def test_a_measurement_is_compared_with_the_states_at_its_capture():
    """Two links moving and turning (constant velocity and body rate), their states exact at the
    step; a noise-free measurement captured 0.1 s before it: taken back by its age the model
    agrees with it (NIS near 0, the states barely move); taken as of the step it does not."""
    rng = np.random.default_rng(9)
    p, v, q, _ = _chain(rng, 2)
    P = np.stack([np.diag(np.r_[[0.005**2] * 3, [0.05**2] * 3, [np.radians(0.3) ** 2] * 3])] * 2)
    v = np.array([[0.5, 0.2, 0.0], [-0.3, 0.4, 0.1]])
    w = np.array([[0.0, 0.3, 0.5], [0.4, -0.2, 0.0]])
    age = 0.1
    back = [(p[k] - v[k] * age, quat_mul(q[k], quat_from_rotvec(-w[k] * age))) for k in range(2)]
    R_cm, t_cm = marker_in_camera(back[0][0], back[0][1], back[1][0], back[1][1], VIEW)
    cov = np.diag(np.r_[[np.radians(0.5) ** 2] * 3, [0.003**2] * 3])
    aged = neighbour_updates(p, v, q, P, [NeighbourMeasurement(0, 1, R_cm, t_cm, cov, VIEW, age_s=age)], w=w)
    as_now = neighbour_updates(p, v, q, P, [NeighbourMeasurement(0, 1, R_cm, t_cm, cov, VIEW)], w=w)
    assert aged.nis[0] < 1e-6 and np.abs(aged.p - p).max() < 1e-6
    assert as_now.nis[0] > 20.0 and np.abs(as_now.p - p).max() > 0.01
    with pytest.raises(ChainInputError, match="age_s"):
        NeighbourMeasurement(0, 1, R_cm, t_cm, cov, VIEW, age_s=-0.1)

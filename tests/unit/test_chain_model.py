"""The chain's multibody model (pinocchio): kinematics against the numpy fast path and against
finite differences, inverse dynamics against RNEA, and the model against MuJoCo's."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import quat_normalize, quat_to_rotmat, rotmat_to_quat
from companion.messages import PoseTarget
from companion.skeleton.body import SkeletonConfig
from companion.skeleton.dynamics import ChainModel
from companion.skeleton.kinematics import chain_middle, chain_offsets, tension
from companion.skeleton.rotors import RotorGeometry, RotorParams
from companion.trajectory import ChainTrajectory, TrajectoryConfig, with_feedforward


def random_chain(rng, n, spread=0.4):
    """A constraint-consistent chain: attitudes, rates, their derivatives, link 1's motion."""
    R = quat_to_rotmat(quat_normalize(np.array([1.0, 0, 0, 0]) + spread * rng.normal(size=(n, 4))))
    return R, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)


def model_of(n, **kw):
    return ChainModel(SkeletonConfig(n_links=n, **kw))


@pytest.mark.parametrize("n", [1, 2, 3, 7, 12])
def test_numpy_kinematics_equals_pinocchio(n):
    """The vectorised chain kinematics (the fast path for batches) against pinocchio's (the oracle)."""
    rng = np.random.default_rng(n)
    cm = model_of(n, link_length_m=1.3)
    for _ in range(5):
        R, w, wd, p0, v0, a0 = random_chain(rng, n)
        r, rd = chain_offsets(R, w, cm.d)
        q, v, a = cm.coordinates(p0 + r, R, v0 + rd, w, np.tile(a0, (n, 1)), wd)
        P, RR, V, W, A, WD = cm.forward(q, v, a)
        np.testing.assert_allclose(P, p0 + r, atol=1e-12)
        np.testing.assert_allclose(RR, R, atol=1e-12)
        np.testing.assert_allclose(V, v0 + rd, atol=1e-12)
        np.testing.assert_allclose(W, w, atol=1e-12)
        np.testing.assert_allclose(WD, wd, atol=1e-12)
        np.testing.assert_allclose(A[0], a0, atol=1e-12)


def test_batched_kinematics_equals_one_by_one():
    rng = np.random.default_rng(3)
    R = quat_to_rotmat(quat_normalize(rng.normal(size=(4, 5, 6, 4))))
    w = rng.normal(size=(4, 5, 6, 3))
    r, rd = chain_offsets(R, w, [0.5, 0.0, 0.0])
    for idx in np.ndindex(4, 5):
        r1, rd1 = chain_offsets(R[idx], w[idx], [0.5, 0.0, 0.0])
        np.testing.assert_allclose(r[idx], r1, atol=1e-14)
        np.testing.assert_allclose(rd[idx], rd1, atol=1e-14)


@pytest.mark.parametrize("n", [2, 5])
def test_link_accelerations_are_the_derivatives_of_the_velocities(n):
    """Every link's acceleration from pinocchio equals the finite difference of its velocity along
    the motion that integrates (v, a) in the configuration space."""
    rng = np.random.default_rng(10 + n)
    cm = model_of(n)
    R, w, wd, p0, v0, a0 = random_chain(rng, n)
    r, rd = chain_offsets(R, w, cm.d)
    q, v, a = cm.coordinates(p0 + r, R, v0 + rd, w, np.tile(a0, (n, 1)), wd)
    h = 1e-6
    states = []
    for s in (-h, h):
        vs = v + s * a
        qs = pin.integrate(cm.model, q, s * v + 0.5 * s * s * a)
        states.append(cm.forward(qs, vs))
    _, _, _, _, A, WD = cm.forward(q, v, a)
    np.testing.assert_allclose((states[1][2] - states[0][2]) / (2 * h), A, atol=1e-5)
    np.testing.assert_allclose((states[1][3] - states[0][3]) / (2 * h), WD, atol=1e-5)


def _targets(cm, rng, n, scale=1.0, lift=0.0, spread=0.4):
    R, w, wd, p0, v0, a0 = random_chain(rng, n, spread)
    p0 = p0 + [0.0, 0.0, lift]
    w, wd, v0, a0 = scale * w, scale * wd, scale * v0, scale * a0
    r, rd = chain_offsets(R, w, cm.d)
    q, v, a = cm.coordinates(p0 + r, R, v0 + rd, w, np.tile(a0, (n, 1)), wd)
    P, RR, V, W, A, WD = cm.forward(q, v, a)
    return [PoseTarget(P[i], rotmat_to_quat(RR[i]), V[i], A[i], W[i], WD[i]) for i in range(n)]


@pytest.mark.parametrize("n", [2, 3, 7])
def test_inverse_dynamics_is_consistent_with_rnea(n):
    """With the chosen rotor wrenches as external forces, RNEA needs no free-flyer force and each
    joint's generalised force is its passive torque; RNEA's joint forces are the chosen cable forces."""
    rng = np.random.default_rng(20 + n)
    cm = model_of(n)
    targets = _targets(cm, rng, n)
    assert cm.inverse_dynamics(targets).rnea_tau is None  # the feed-forward's call: no RNEA
    dyn = cm.inverse_dynamics(targets, check=True)
    np.testing.assert_allclose(dyn.rnea_tau[:6], 0.0, atol=1e-10)
    R = quat_to_rotmat(np.stack([t.q_wxyz for t in targets]))
    passive = np.concatenate([R[j + 1].T @ dyn.joint_torque_w_nm[j] for j in range(n - 1)])
    np.testing.assert_allclose(dyn.rnea_tau[6:], passive, atol=1e-10)
    np.testing.assert_allclose(cm.cable_forces_rnea(), dyn.joint_force_w_n, atol=1e-10)


@pytest.mark.parametrize("n, passive", [(3, (1,)), (5, (2,)), (7, (1, 4)), (7, (1, 3, 5))])
def test_a_passive_link_is_carried_by_its_neighbours_on_the_joints(n, passive):
    """Links whose rotors are off (``passive``; no two side by side, none at an end): while the
    chain follows any motion their rotors produce no force and no moment across their axis (the
    joints carry them; about its own axis a link is turned only by the joints' springs, so what
    its target's roll needs beyond them stays with it), RNEA agrees, and the links' rotors
    together still produce the whole chain's force."""
    rng = np.random.default_rng(40 + n)
    cm = model_of(n)
    targets = _targets(cm, rng, n, lift=2.0)
    usual = cm.inverse_dynamics(targets, check=True).rotor_wrench_w
    dyn = cm.inverse_dynamics(targets, check=True, passive=passive)
    weight = cm.inertia.mass_kg * 9.80665
    R = quat_to_rotmat(np.stack([t.q_wxyz for t in targets]))
    for i in passive:
        axis = R[i][:, 0]
        moment = dyn.rotor_wrench_w[i, 3:]
        np.testing.assert_allclose(dyn.rotor_wrench_w[i, :3], 0.0, atol=1e-5 * weight)
        np.testing.assert_allclose(moment - axis * (axis @ moment), 0.0, atol=1e-5 * weight * cm.d[0])
    np.testing.assert_allclose(dyn.rnea_tau[:6], 0.0, atol=1e-9)
    joint_torques = np.concatenate([R[j + 1].T @ dyn.joint_torque_w_nm[j] for j in range(n - 1)])
    np.testing.assert_allclose(dyn.rnea_tau[6:], joint_torques, atol=1e-9)
    np.testing.assert_allclose(cm.cable_forces_rnea(), dyn.joint_force_w_n, atol=1e-9)
    np.testing.assert_allclose(dyn.rotor_wrench_w[:, :3].sum(0), usual[:, :3].sum(0), atol=1e-9)
    assert np.abs(usual[list(passive)]).max() > 0.5 * weight  # they would have carried themselves


def test_a_passive_end_link_gets_the_least_squares_compromise():
    """An end link hangs on one ball joint: held level it cannot be carried, since a force at its
    tip that takes its weight turns it by the same amount. The least squares (its wrench weighted
    PASSIVE_WEIGHT over force and moment per half length alike) splits it: the joint takes half
    its weight, and half its weight and the matching moment are left to it."""
    cm = model_of(3)
    traj = ChainTrajectory(TrajectoryConfig(kind="hover", takeoff_start_s=0.0, takeoff_duration_s=1.0), 3, 1.0,
                           [0.0, 0.0, 2.0], dynamics=cm)
    targets = traj.targets(3.0)
    dyn = cm.inverse_dynamics(targets, passive=(0,))
    weight = cm.inertia.mass_kg * 9.80665
    np.testing.assert_allclose(dyn.rotor_wrench_w[0], [0, 0, weight / 2, 0, weight / 2 * cm.d[0], 0], atol=1e-3)
    assert dyn.rotor_wrench_w[1, 2] == pytest.approx(1.5 * weight, rel=1e-3)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 6))
def test_the_cable_forces_minimise_the_rotor_wrenches(seed, n):
    """Any other choice of cable forces asks more of the rotors (the least-squares optimum)."""
    rng = np.random.default_rng(seed)
    cm = model_of(n)
    targets = _targets(cm, rng, n)
    dyn = cm.inverse_dynamics(targets)
    p = np.stack([t.p_w_m for t in targets])
    x = p[:-1] + np.einsum("nij,j->ni", quat_to_rotmat(np.stack([t.q_wxyz for t in targets]))[:-1], cm.d)

    def cost(F):
        f, m = cm._joint_wrench(F, dyn.joint_torque_w_nm, p, x)
        own = dyn.rotor_wrench_w + np.concatenate(cm._joint_wrench(dyn.joint_force_w_n, dyn.joint_torque_w_nm, p, x), 1)
        rotor = own - np.concatenate([f, m], axis=1)
        return np.sum(rotor[:, :3] ** 2) + np.sum((rotor[:, 3:] / cm.d[0]) ** 2)

    best = cost(dyn.joint_force_w_n)
    for _ in range(5):
        assert cost(dyn.joint_force_w_n + 0.1 * rng.normal(size=dyn.joint_force_w_n.shape)) > best


def test_a_straight_hovering_chain_needs_no_cable_force_and_no_feedforward():
    cm = model_of(5)
    traj = ChainTrajectory(TrajectoryConfig(kind="hover", takeoff_start_s=0.0, takeoff_duration_s=1.0), 5, 1.0,
                           [0.0, 0.0, 2.0], dynamics=cm)
    targets = traj.targets(3.0)
    np.testing.assert_allclose(cm.last.joint_force_w_n, 0.0, atol=1e-9)
    for t in targets:
        np.testing.assert_allclose(t.force_ff_w_n, 0.0, atol=1e-9)
        np.testing.assert_allclose(t.torque_ff_b_nm, 0.0, atol=1e-9)


def test_the_feedforward_of_a_bending_chain_is_internal():
    """The bending chain at its largest bend: the joints' springs act, the cables share the load, and
    the feed-forward adds no net force or moment to the whole chain (the cables and joints are internal)."""
    cm = model_of(3, joint_stiffness_nm_rad=0.3, joint_damping_nms_rad=0.1)
    traj = ChainTrajectory(TrajectoryConfig(kind="bend", takeoff_start_s=0.0, takeoff_duration_s=0.0,
                                            bend_start_s=0.0, bend_ramp_s=0.0, bend_period_s=4.0), 3, 1.0,
                           [0.0, 0.0, 2.0])
    targets = with_feedforward(traj.targets(1.0), cm)
    dyn = cm.last
    assert np.linalg.norm(dyn.joint_torque_w_nm) > 1e-3
    assert np.linalg.norm(dyn.joint_force_w_n) > 1e-3
    np.testing.assert_allclose(sum(t.force_ff_w_n for t in targets), 0.0, atol=1e-9)
    total = sum(t.R_d @ t.torque_ff_b_nm + np.cross(t.p_w_m, t.force_ff_w_n) for t in targets)
    np.testing.assert_allclose(total, 0.0, atol=1e-9)


def test_tension_is_positive_when_the_cable_pulls():
    R = np.tile(np.eye(3), (2, 1, 1))
    assert tension(np.array([[-2.0, 0.0, 0.0]]), R)[0] == pytest.approx(2.0)  # child pulled towards the parent
    assert tension(np.array([[3.0, 0.0, 0.5]]), R)[0] == pytest.approx(-3.0)


def test_chain_middle_is_the_middle_link_or_the_middle_joint():
    p = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    q = np.tile([1.0, 0, 0, 0], (4, 1))
    np.testing.assert_allclose(chain_middle(p, q, [0.5, 0, 0]), [1.5, 0, 0])
    np.testing.assert_allclose(chain_middle(p[:3], q[:3], [0.5, 0, 0]), [1.0, 0, 0])


@pytest.mark.parametrize("n", [2, 4])
@pytest.mark.parametrize("through", ["xfrc_applied", "rotors"])
def test_the_model_is_mujocos_chain(n, through):
    """The rotor wrenches of the inverse dynamics applied in MuJoCo (as body wrenches, or as the eight
    rotor thrusts that make them) give the targets' accelerations and the predicted cable forces: the
    two models are the same multibody, and the simulator's cable force is read right."""
    import mujoco

    from sitl.plant.model import SkeletonModel

    rng = np.random.default_rng(30 + n)
    sk = SkeletonConfig(n_links=n)
    cm = ChainModel(sk)
    geometry = RotorGeometry.odar()
    sm = SkeletonModel(sk, geometry, RotorParams())
    targets = _targets(cm, rng, n, scale=0.3, lift=10.0, spread=0.1)  # clear of the ground, within thrust
    R = quat_to_rotmat(np.stack([t.q_wxyz for t in targets]))
    w = np.stack([t.omega_d_rad_s for t in targets])
    qpos = [*targets[0].p_w_m, *targets[0].q_wxyz]
    qvel = [*targets[0].v_w_m_s, *w[0]]
    for i in range(1, n):
        Rrel = R[i - 1].T @ R[i]
        qpos += list(rotmat_to_quat(Rrel))
        qvel += list(w[i] - Rrel.T @ w[i - 1])
    sm.data.qpos[:] = qpos
    sm.data.qvel[:] = qvel
    dyn = cm.inverse_dynamics(targets)
    if through == "xfrc_applied":
        sm.data.xfrc_applied[sm.body_ids] = dyn.rotor_wrench_w
    else:  # each link's wrench in its body frame, made by its rotors (eq. 2.8: U = B lambda)
        B_pinv = np.linalg.pinv(geometry.mapping_matrix())
        U = np.concatenate([np.einsum("nji,nj->ni", R, dyn.rotor_wrench_w[:, :3]),
                            np.einsum("nji,nj->ni", R, dyn.rotor_wrench_w[:, 3:])], axis=1)
        thrust = U @ B_pinv.T
        assert np.abs(thrust).max() < RotorParams().thrust_max_n
        sm.data.ctrl[sm.actuator_ids] = thrust
    mujoco.mj_forward(sm.model, sm.data)
    np.testing.assert_allclose(sm.data.qacc[:3], targets[0].a_w_m_s2, atol=1e-8)
    np.testing.assert_allclose(sm.data.qacc[3:6], targets[0].omega_dot_d_rad_s2, atol=1e-8)
    np.testing.assert_allclose(sm.truth().joint_force_w_n, dyn.joint_force_w_n, atol=1e-8)


@pytest.mark.parametrize("passive", [frozenset(), frozenset({0}), frozenset({1})])
def test_a_feedforward_target_is_the_chains_target_with_its_attitude_forms_as_computed_fresh(passive):
    """The targets of a chain with the feed-forward: the same motion as without it, and the
    attitude forms they carry (``R_d``, ``R_tuple``, filled as they are built) equal to those a
    target computes from its quaternion."""
    cm = model_of(3, joint_stiffness_nm_rad=0.3, joint_damping_nms_rad=0.1)
    cfg = TrajectoryConfig(kind="bend", takeoff_start_s=0.0, takeoff_duration_s=0.0, bend_start_s=0.0,
                           bend_ramp_s=0.0, bend_period_s=4.0)
    bare = ChainTrajectory(cfg, 3, 1.0, [0.0, 0.0, 2.0]).targets(1.3)
    fed = ChainTrajectory(cfg, 3, 1.0, [0.0, 0.0, 2.0], dynamics=cm).targets(1.3, passive=passive)
    for a, b in zip(bare, fed):
        for name in ("p_w_m", "q_wxyz", "v_w_m_s", "a_w_m_s2", "omega_d_rad_s", "omega_dot_d_rad_s2"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        fresh = PoseTarget(b.p_w_m, b.q_wxyz)
        np.testing.assert_array_equal(b.R_d, fresh.R_d)
        assert b.R_tuple == fresh.R_tuple
    assert np.linalg.norm(np.array([t.force_ff_w_n for t in fed])) > 1e-3

"""SE(3) PID (thesis sec. 2.3.2), hybrid pose/wrench control and the momentum observer (sec. 2.3.3)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat, rotmat_to_quat
from companion.messages import PoseTarget
from companion.skeleton.body import GRAVITY_M_S2, SkeletonConfig, link_inertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.firmware import FirmwareConfig
from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.controllers.hybrid import (
    ANG,
    LIN,
    ContactTarget,
    HybridController,
    HybridGains,
    HybridIntegrals,
    MomentumObserver,
    ObserverConfig,
    contact_force_estimate,
    contact_pfaffian,
    coriolis_gravity,
    generalized_mass,
    hybrid_control,
    m_projector,
    null_basis,
)
from link_firmware_sim.vehicle.params import ParamTable, StreamRates
from link_firmware_sim.controllers.se3_control import (
    Se3PidController,
    Se3PidGains,
    Se3PidIntegrals,
    attitude_error_so3,
    c2_bound,
    resolved_c2,
    se3_pid_control,
)

from ..rigid_body import rigid_body_step

INERTIA = link_inertia(SkeletonConfig(n_links=1, link_length_m=1.2, link_mass_kg=2.6), RotorGeometry.odar())
vec3 = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).map(np.array)
rotvec = st.lists(st.floats(-2.5, 2.5), min_size=3, max_size=3).map(np.array)


def _target(rng: np.random.Generator, moving: bool = True) -> PoseTarget:
    q = quat_from_rotvec(rng.normal(size=3))
    if not moving:
        return PoseTarget.hold(rng.normal(size=3), q)
    return PoseTarget(rng.normal(size=3), q, rng.normal(size=3), rng.normal(size=3), rng.normal(size=3),
                      rng.normal(size=3))


# -- SE(3) PID ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(4))
def test_se3_pid_on_target_carries_the_weight_only(seed):
    rng = np.random.default_rng(seed)
    target = _target(rng, moving=False)
    U, _ = se3_pid_control(target.p_w_m, np.zeros(3), target.q_wxyz, np.zeros(3), target, Se3PidGains(), INERTIA,
                           Se3PidIntegrals(), 0.002)
    R = quat_to_rotmat(target.q_wxyz)
    np.testing.assert_allclose(U[:3], R.T @ [0, 0, INERTIA.mass_kg * GRAVITY_M_S2], atol=1e-12)
    np.testing.assert_allclose(U[3:], 0.0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(rotvec, rotvec, vec3)
def test_attitude_error_rate_matches_finite_difference(rv, rv_d, w):
    """d/dt e_R = 1/2 (tr(R^T R_d) I - R^T R_d) e_w for R' = R S(w), R_d fixed ([31], the SO(3) error kinematics)."""
    R, R_d = quat_to_rotmat(quat_from_rotvec(rv)), quat_to_rotmat(quat_from_rotvec(rv_d))
    h = 1e-6
    dR = quat_to_rotmat(quat_from_rotvec(h * w))
    fd = (attitude_error_so3(R @ dR, R_d) - attitude_error_so3(R @ dR.T, R_d)) / (2 * h)
    E = R.T @ R_d
    np.testing.assert_allclose(fd, 0.5 * (np.trace(E) * np.eye(3) - E) @ w, atol=1e-6)
    assert np.linalg.norm(fd) <= np.linalg.norm(w) + 1e-6  # |d/dt e_R| <= |e_w|: used by c2_bound


@settings(max_examples=40, deadline=None)
@given(st.floats(0.5, 50.0), st.floats(0.1, 20.0), st.floats(0.01, 0.99))
def test_c2_below_bound_makes_the_lyapunov_matrices_definite(kR, kw, frac):
    """Below c2_bound, V's quadratic bound is positive definite and dV/dt's negative definite."""
    c2 = frac * c2_bound(kR, kw, INERTIA)
    lm, lM = min(INERTIA.inertia_kgm2), max(INERTIA.inertia_kgm2)
    W1 = np.array([[kR, -c2 * lM], [-c2 * lM, lm]])
    W2 = np.array([[c2 * kR, -0.5 * c2 * kw], [-0.5 * c2 * kw, kw - c2 * lM]])
    assert np.linalg.eigvalsh(W1).min() > 0
    assert np.linalg.eigvalsh(W2).min() > 0


def test_se3_pid_limits_the_position_error():
    """As eq. 1's: a target beyond pos_error_limit_m acts as the point on the way at that distance."""
    rng = np.random.default_rng(11)
    gains = Se3PidGains(pos_error_limit_m=1.5)
    for distance in (0.7, 3.0, 40.0):
        p, v, q, w = rng.normal(size=3), rng.normal(size=3), quat_from_rotvec(rng.normal(size=3)), rng.normal(size=3)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        far = replace(_target(rng), p_w_m=p + distance * direction)
        near = replace(far, p_w_m=p + min(distance, 1.5) * direction)
        ints = Se3PidIntegrals(rng.normal(scale=0.1, size=3), rng.normal(scale=0.1, size=3))
        U_far, i_far = se3_pid_control(p, v, q, w, far, gains, INERTIA, ints, 0.002)
        U_near, i_near = se3_pid_control(p, v, q, w, near, gains, INERTIA, ints, 0.002)
        np.testing.assert_allclose(U_far, U_near, atol=1e-9)
        np.testing.assert_allclose(i_far.pos_m_s, i_near.pos_m_s, atol=1e-12)
        if distance > 1.5:
            U_free, _ = se3_pid_control(p, v, q, w, far, replace(gains, pos_error_limit_m=100.0), INERTIA, ints, 0.002)
            assert np.linalg.norm(U_free[:3]) > np.linalg.norm(U_far[:3]) + 1.0
    with pytest.raises(ValueError, match="pos_error_limit_m"):
        Se3PidGains(pos_error_limit_m=math.inf)


def test_hybrid_limits_the_position_error():
    """As eq. 1's: a target beyond pos_error_limit_m acts as the point on the way at that distance
    (in contact and free)."""
    rng = np.random.default_rng(12)
    gains = HybridGains(pos_error_limit_m=1.5)
    for distance, contact in ((0.7, CONTACT), (3.0, CONTACT), (40.0, None)):
        p, v, q, w = rng.normal(size=3), rng.normal(size=3), quat_from_rotvec(rng.normal(size=3) * 0.3), rng.normal(size=3)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        far = replace(_target(rng), p_w_m=p + distance * direction)
        near = replace(far, p_w_m=p + min(distance, 1.5) * direction)
        lam = np.array([7.0]) if contact is not None else np.zeros(0)
        U_far, i_far = hybrid_control(p, v, q, w, far, contact, lam, gains, INERTIA, HybridIntegrals(), 0.002)
        U_near, i_near = hybrid_control(p, v, q, w, near, contact, lam, gains, INERTIA, HybridIntegrals(), 0.002)
        np.testing.assert_allclose(U_far, U_near, atol=1e-9)
        np.testing.assert_allclose(i_far.pos_m_s, i_near.pos_m_s, atol=1e-12)
    with pytest.raises(ValueError, match="pos_error_limit_m"):
        HybridGains(pos_error_limit_m=0.0)


def test_c2_above_bound_is_rejected():
    bound = c2_bound(6.0, 1.2, INERTIA)
    with pytest.raises(ValueError, match="c2"):
        resolved_c2(Se3PidGains(c2=1.01 * bound), INERTIA)
    assert resolved_c2(Se3PidGains(), INERTIA) == pytest.approx(0.9 * bound)
    with pytest.raises(ValueError, match="kp_n_m"):
        Se3PidGains(kp_n_m=(1.0, -1.0, 1.0))


def test_se3_pid_class_agrees_with_function():
    rng = np.random.default_rng(7)
    ctrl = Se3PidController(Se3PidGains(), INERTIA)
    integrals = Se3PidIntegrals()
    for _ in range(20):
        args = (rng.normal(size=3), rng.normal(size=3), quat_from_rotvec(rng.normal(size=3)), rng.normal(size=3),
                _target(rng))
        U_f, integrals = se3_pid_control(*args, Se3PidGains(), INERTIA, integrals, 0.002)
        np.testing.assert_array_equal(ctrl(*args, 0.002), U_f)
    np.testing.assert_array_equal(ctrl.integrals.att_rad, integrals.att_rad)


def test_se3_pid_integral_removes_a_constant_disturbance_in_closed_loop():
    """Closed loop on (2.7) with a constant external torque and force: the SO(3) and position
    integrals bring the pose back (a PD alone keeps an offset)."""
    target = PoseTarget.hold(np.zeros(3), quat_from_rotvec(np.array([0.0, math.pi / 4, 0.0])))
    dist = np.array([0.5, -0.3, 0.2, 0.05, 0.1, -0.08])
    finals = {}
    for name, gains in (("pid", Se3PidGains()), ("pd", Se3PidGains(ki_n_ms=(0, 0, 0), kRI_nm_s=0.0))):
        ctrl = Se3PidController(gains, INERTIA)
        p, v, R, w = np.array([0.3, -0.2, 0.1]), np.zeros(3), quat_to_rotmat(quat_from_rotvec([0.2, 0.5, -0.3])), np.zeros(3)
        dt = 0.01
        for _ in range(int(15.0 / dt)):
            U = ctrl(p, v, rotmat_to_quat(R), w, target, dt)
            p, v, R, w = rigid_body_step(p, v, R, w, U, INERTIA, dt, dist)
        finals[name] = (np.linalg.norm(p), np.linalg.norm(attitude_error_so3(R, target.R_d)))
    assert finals["pid"][0] < 0.01 and finals["pid"][1] < 0.005
    assert finals["pd"][0] > 0.03 and finals["pd"][1] > 0.015


# -- hybrid control ------------------------------------------------------------------------------------

CONTACT = ContactTarget(np.array([1.0, 0.0, 0.0]), np.array([0.6, 0.0, 0.0]), 10.0)


@settings(max_examples=40, deadline=None)
@given(rotvec, vec3.map(lambda x: x / max(np.linalg.norm(x), 1e-3)), vec3)
def test_null_basis_and_projector(rv, n, r):
    if abs(np.linalg.norm(n) - 1.0) > 1e-9:
        return
    A = contact_pfaffian(ContactTarget(n, r, 1.0), quat_to_rotmat(quat_from_rotvec(rv)))
    D = null_basis(A)
    M = generalized_mass(INERTIA)
    P = m_projector(D, M)
    np.testing.assert_allclose(A @ D, 0.0, atol=1e-12)
    np.testing.assert_allclose(P @ P, P, atol=1e-10)
    np.testing.assert_allclose(M @ P, (M @ P).T, atol=1e-10)  # M-orthogonal
    np.testing.assert_allclose(A @ P, 0.0, atol=1e-10)


def test_contact_pfaffian_is_the_tip_velocity_along_the_normal():
    rng = np.random.default_rng(3)
    R = quat_to_rotmat(quat_from_rotvec(rng.normal(size=3)))
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    r = rng.normal(size=3)
    v, w = rng.normal(size=3), rng.normal(size=3)
    A = contact_pfaffian(ContactTarget(n, r, 0.0), R)
    assert (A @ np.concatenate((v, w)))[0] == pytest.approx(n @ (v + R @ np.cross(w, r)))


@pytest.mark.parametrize("seed", range(3))
def test_hybrid_law_sets_the_constraint_force_to_the_command(seed):
    """With the constraint enforced (A qdd = 0), the Lagrange multiplier of M qdd + C qd + G + A^T l = w
    equals lambda_d - K_f int(...) whatever the pose errors (the projected pose terms do no work on A)."""
    rng = np.random.default_rng(seed)
    q = quat_from_rotvec(rng.normal(size=3) * 0.3)
    p, v, w = rng.normal(size=3) * 0.2, rng.normal(size=3) * 0.2, rng.normal(size=3) * 0.2
    U, integ = hybrid_control(p, v, q, w, _target(rng), CONTACT, np.array([7.0]), HybridGains(), INERTIA,
                              HybridIntegrals(), 0.01)
    R = quat_to_rotmat(q)
    wrench = np.concatenate((R @ U[:3], U[3:]))
    M = generalized_mass(INERTIA)
    A = contact_pfaffian(CONTACT, R)
    Minv = np.linalg.inv(M)
    lam = np.linalg.solve(A @ Minv @ A.T, A @ Minv @ (wrench - coriolis_gravity(INERTIA, w)))
    np.testing.assert_allclose(integ.force_n_s, [(7.0 - 10.0) * 0.01])
    np.testing.assert_allclose(lam, [10.0 - HybridGains().kf_1_s * integ.force_n_s[0]], rtol=1e-9)


def test_hybrid_with_scalar_gains_is_the_printed_law():
    """Equal entries in the 6-vector gains give the thesis's M Delta (phidd_d - K_d edot_phi - ...)
    (the position error's limit out of reach: the printed law has none)."""
    rng = np.random.default_rng(11)
    g = HybridGains(kp_1_s2=(5.0,) * 6, kd_1_s=(3.0,) * 6, ki_1_s3=(0.5,) * 6, pos_error_limit_m=100.0)
    q = quat_from_rotvec(rng.normal(size=3) * 0.3)
    p, v, w = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    t = _target(rng)
    U, integ = hybrid_control(p, v, q, w, t, CONTACT, np.array([9.0]), g, INERTIA, HybridIntegrals(), 0.01)
    R = quat_to_rotmat(q)
    M = generalized_mass(INERTIA)
    A = contact_pfaffian(CONTACT, R)
    D = null_basis(A)
    Om = np.linalg.solve(D.T @ M @ D, D.T @ M)
    RtRd = R.T @ t.R_d
    e = np.concatenate((p - t.p_w_m, attitude_error_so3(R, t.R_d)))
    ed = np.concatenate((v - t.v_w_m_s, w - RtRd @ t.omega_d_rad_s))
    ei = np.concatenate((integ.pos_m_s, integ.att_rad))
    phidd = Om @ np.concatenate((t.a_w_m_s2, RtRd @ t.omega_dot_d_rad_s2))
    printed = (M @ D @ (phidd - 3.0 * Om @ ed - 5.0 * Om @ e - 0.5 * Om @ ei) + coriolis_gravity(INERTIA, w)
               + A.T @ (np.array([10.0]) - g.kf_1_s * integ.force_n_s))
    printed[LIN] += t.force_ff_w_n
    printed[ANG] += RtRd @ t.torque_ff_b_nm
    np.testing.assert_allclose(np.concatenate((R @ U[:3], U[3:])), printed, atol=1e-9)


def test_hybrid_class_agrees_with_function():
    rng = np.random.default_rng(5)
    ctrl = HybridController(HybridGains(), INERTIA)
    integ = HybridIntegrals()
    for k in range(10):
        contact = CONTACT if k >= 3 else None
        lam = np.array([rng.normal()]) if contact else np.zeros(0)
        args = (rng.normal(size=3), rng.normal(size=3), quat_from_rotvec(rng.normal(size=3)), rng.normal(size=3),
                _target(rng), contact, lam)
        U_f, integ = hybrid_control(*args, HybridGains(), INERTIA, integ, 0.002, ctrl.c2)
        np.testing.assert_array_equal(ctrl.command(*args, 0.002), U_f)


# -- momentum observer ----------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(2))
def test_observer_converges_to_a_constant_external_wrench(seed):
    """Pure simulation of (2.7) under a wobbling control wrench and a constant external wrench:
    the estimate converges (first-order, 1/k_e = 0.125 s) to it."""
    rng = np.random.default_rng(seed)
    dist = rng.normal(size=6) * np.array([3, 3, 3, 0.3, 0.3, 0.3])
    obs = MomentumObserver(ObserverConfig(actuator_time_constant_s=0.0), INERTIA)
    p, v, R, w = np.zeros(3), rng.normal(size=3) * 0.1, np.eye(3), rng.normal(size=3) * 0.2
    dt = 0.001
    hover = INERTIA.mass_kg * GRAVITY_M_S2
    for k in range(2000):
        U = np.concatenate((R.T @ [0, 0, hover], np.zeros(3))) + 0.5 * np.sin(k * dt * np.arange(1, 7))
        obs.step(v, w, np.concatenate((R @ U[:3], U[3:])), dt)
        p, v, R, w = rigid_body_step(p, v, R, w, U, INERTIA, dt, np.concatenate((dist[LIN], dist[ANG])))
        if k == 50:
            early = np.abs(obs.wrench_e - dist).max()
    err = np.abs(obs.wrench_e - dist).max()
    assert early > 0.2 * np.abs(dist).max()  # not instantaneous: a low-pass
    assert err < 0.01 * np.abs(dist).max() + 1e-3
    A = contact_pfaffian(CONTACT, R)
    assert contact_force_estimate(A, obs.wrench_e) == pytest.approx(-(A @ dist) / (A @ A.T)[0, 0], abs=0.05)


# -- firmware wiring -------------------------------------------------------------------------------------


def test_controller_parameter_selects_the_controller():
    table = ParamTable(1, FirmwareConfig(), GeoOrigin(), StreamRates())
    assert table.values["SKL_CTRL"] == 0 and table.firmware_config().controller == "impedance"
    for value, name in ((1, "se3_pid"), (2, "hybrid")):
        table.set("SKL_CTRL", value)
        assert table.firmware_config().controller == name
    with pytest.raises(ValueError, match="SKL_CTRL"):
        table.set("SKL_CTRL", 3)

from dataclasses import replace

import numpy as np
import pytest

from companion.estimation.so3 import quat_normalize, quat_to_rotmat
from companion.messages import PoseTarget
from companion.skeleton.body import GRAVITY_M_S2, LinkInertia
from link_firmware_sim.control import ControlIntegrals, ImpedanceGains, impedance_control, vee


def _eq1_reference(p, v, q, w, target, gains, inertia, integrals, dt):
    """Paper eq. 1 (with the stabilising signs) written directly in numpy: the oracle."""
    R, Rd = quat_to_rotmat(q), quat_to_rotmat(target.q_wxyz)
    J = np.diag(inertia.inertia_kgm2)
    m = inertia.mass_kg
    e_p = p - target.p_w_m
    pos_int = np.clip(integrals.pos + e_p * dt, -gains.pos_integral_limit_ms, gains.pos_integral_limit_ms)
    f = (m * GRAVITY_M_S2 * np.array([0, 0, 1.0]) + m * target.a_w_m_s2
         - np.array(gains.kd_ns_m) * (v - target.v_w_m_s) - np.array(gains.kp_n_m) * e_p
         - np.array(gains.ki_n_ms) * pos_int + target.force_ff_w_n)
    e_R = vee(Rd.T @ R - R.T @ Rd)
    w_db = R.T @ Rd @ target.omega_d_rad_s
    e_w = w - w_db
    att_int = np.clip(integrals.att + (e_w + gains.gamma_I * e_R) * dt,
                      -gains.att_integral_limit_rad, gains.att_integral_limit_rad)
    tau = (np.cross(w, J @ w) - gains.kR_nm * e_R - gains.kw_nms * e_w - gains.kI_nm_s * att_int
           - J @ (np.cross(w, w_db) - R.T @ Rd @ target.omega_dot_d_rad_s2) + R.T @ Rd @ target.torque_ff_b_nm)
    return np.concatenate((R.T @ f, tau)), pos_int, att_int


@pytest.mark.parametrize("seed", range(20))
def test_controller_equals_eq1(seed):
    rng = np.random.default_rng(seed)
    gains = ImpedanceGains(kp_n_m=(11.0, 9.0, 13.0), kd_ns_m=(8.0, 7.0, 9.0), ki_n_ms=(0.5, 0.4, 0.3),
                           pos_integral_limit_ms=0.05, att_integral_limit_rad=0.02, pos_error_limit_m=100.0)
    inertia = LinkInertia(1.8, (0.04, 0.16, 0.17))
    target = PoseTarget(rng.normal(size=3), quat_normalize(rng.normal(size=4)), rng.normal(size=3),
                        rng.normal(size=3), rng.normal(size=3), rng.normal(size=3),
                        *(rng.normal(size=3) if seed % 2 else np.zeros(3) for _ in range(2)))
    integrals = ControlIntegrals(rng.normal(scale=0.03, size=3), rng.normal(scale=0.01, size=3))
    args = (rng.normal(size=3), rng.normal(size=3), quat_normalize(rng.normal(size=4)), rng.normal(size=3))
    U, ints = impedance_control(*args, target, gains, inertia, integrals, 0.01)
    U_ref, pos_ref, att_ref = _eq1_reference(*args, target, gains, inertia, integrals, 0.01)
    np.testing.assert_allclose(U, U_ref, atol=1e-12)
    np.testing.assert_allclose(ints.pos, pos_ref, atol=1e-15)
    np.testing.assert_allclose(ints.att, att_ref, atol=1e-15)


@pytest.mark.parametrize("seed", range(10))
def test_the_position_error_is_limited(seed):
    """pos_error_limit_m: a target beyond it acts as the point on the way to it at that distance
    (eq. 1 with p_d moved there), integral included; within it, eq. 1 unchanged."""
    rng = np.random.default_rng(100 + seed)
    gains = ImpedanceGains(ki_n_ms=(0.5, 0.4, 0.3), pos_error_limit_m=1.5)
    inertia = LinkInertia(1.8, (0.04, 0.16, 0.17))
    p, v, q, w = rng.normal(size=3), rng.normal(size=3), quat_normalize(rng.normal(size=4)), rng.normal(size=3)
    integrals = ControlIntegrals(rng.normal(scale=0.03, size=3), rng.normal(scale=0.01, size=3))
    for distance in (0.5, 1.5, 4.0, 300.0):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        far = PoseTarget(p + distance * direction, quat_normalize(rng.normal(size=4)), *rng.normal(size=(4, 3)))
        near = replace(far, p_w_m=p + min(distance, 1.5) * direction)
        U, ints = impedance_control(p, v, q, w, far, gains, inertia, integrals, 0.01)
        U_ref, pos_ref, att_ref = _eq1_reference(p, v, q, w, near, gains, inertia, integrals, 0.01)
        np.testing.assert_allclose(U, U_ref, atol=1e-9)
        np.testing.assert_allclose(ints.pos, pos_ref, atol=1e-12)
    with pytest.raises(ValueError, match="pos_error_limit_m"):
        ImpedanceGains(pos_error_limit_m=0.0)


def test_hover_at_target_needs_only_weight_compensation():
    inertia = LinkInertia(1.8, (0.04, 0.16, 0.16))
    q = quat_normalize(np.array([0.9, 0.1, -0.3, 0.2]))
    target = PoseTarget.hold(np.array([1.0, 2.0, 3.0]), q)
    U, _ = impedance_control(np.array([1.0, 2.0, 3.0]), np.zeros(3), q, np.zeros(3), target, ImpedanceGains(),
                             inertia, ControlIntegrals(), 0.002)
    np.testing.assert_allclose(U[:3], quat_to_rotmat(q).T @ [0, 0, 1.8 * GRAVITY_M_S2], atol=1e-12)
    np.testing.assert_allclose(U[3:], 0.0, atol=1e-12)


def test_position_error_pushes_back():
    inertia = LinkInertia(1.8, (0.04, 0.16, 0.16))
    target = PoseTarget.hold(np.zeros(3), np.array([1.0, 0, 0, 0]))
    U, _ = impedance_control(np.array([0.5, 0, 0]), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), target,
                             ImpedanceGains(), inertia, ControlIntegrals(), 0.002)
    assert U[0] < 0  # restoring force along -x

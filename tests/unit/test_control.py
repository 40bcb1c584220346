from dataclasses import replace

import numpy as np
import pytest

from companion.estimation.so3 import quat_normalize, quat_to_rotmat
from companion.kernels.jit import ENABLED
from companion.messages import PoseTarget
from companion.skeleton.body import GRAVITY_M_S2, LinkInertia
from link_firmware_sim.controllers.impedance import (ControlIntegrals, ImpedanceController, ImpedanceGains,
                                                     impedance_control)


@pytest.mark.skipif(not ENABLED, reason="numba not installed (or SKELETON_JIT=0)")
@pytest.mark.parametrize("seed", range(20))
def test_the_kernel_computes_eq1(seed):
    """Eq. 1's kernel (the impedance controller, compiled) against its specification
    (impedance_control), integrals beyond their limits and the whole-chain feed-forward included."""
    rng = np.random.default_rng(seed)
    gains = ImpedanceGains(kp_n_m=(11.0, 9.0, 13.0), kd_ns_m=(8.0, 7.0, 9.0), ki_n_ms=(0.5, 0.4, 0.3),
                           pos_integral_limit_ms=0.05, att_integral_limit_rad=0.02, pos_error_limit_m=100.0)
    inertia = LinkInertia(1.8, (0.04, 0.16, 0.17))
    target = PoseTarget(rng.normal(size=3), quat_normalize(rng.normal(size=4)), rng.normal(size=3),
                        rng.normal(size=3), rng.normal(size=3), rng.normal(size=3),
                        *(rng.normal(size=3) if seed % 2 else np.zeros(3) for _ in range(2)))
    integrals = ControlIntegrals(rng.normal(scale=0.03, size=3), rng.normal(scale=0.01, size=3))
    args = (rng.normal(size=3), rng.normal(size=3), quat_normalize(rng.normal(size=4)), rng.normal(size=3))
    U_ref, ints_ref = impedance_control(*args, target, gains, inertia, integrals, 0.01)
    ctrl = ImpedanceController(gains, inertia, compiled=True)
    ctrl.integrals = integrals
    U = ctrl(*args, target, 0.01)
    np.testing.assert_allclose(U, U_ref, atol=1e-12)
    np.testing.assert_allclose(ctrl.integrals.pos, ints_ref.pos, atol=1e-15)
    np.testing.assert_allclose(ctrl.integrals.att, ints_ref.att, atol=1e-15)


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
        unlimited = replace(gains, pos_error_limit_m=1e9)
        U_ref, ints_ref = impedance_control(p, v, q, w, near, unlimited, inertia, integrals, 0.01)
        np.testing.assert_allclose(U, U_ref, atol=1e-9)
        np.testing.assert_allclose(ints.pos, ints_ref.pos, atol=1e-12)
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

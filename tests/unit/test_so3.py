import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from companion.estimation import so3

finite = st.floats(-3.0, 3.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)


def _random_quats(n, seed=0):
    return so3.quat_normalize(np.random.default_rng(seed).normal(size=(n, 4)))


def test_rotmat_matches_scipy_hamilton_convention():
    q = _random_quats(64)
    expected = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy is scalar-last
    np.testing.assert_allclose(so3.quat_to_rotmat(q), expected, atol=1e-14)


def test_product_composes_rotations():
    a, b = _random_quats(32, 1), _random_quats(32, 2)
    np.testing.assert_allclose(
        so3.quat_to_rotmat(so3.quat_mul(a, b)), so3.quat_to_rotmat(a) @ so3.quat_to_rotmat(b), atol=1e-14
    )


def test_rotmat_to_quat_roundtrip():
    q = _random_quats(64, 3)
    back = so3.rotmat_to_quat(so3.quat_to_rotmat(q))
    np.testing.assert_allclose(so3.quat_distance(back, q), 0.0, atol=1e-12)
    assert np.all(back[:, 0] >= 0.0)


def test_euler_zyx_matches_scipy():
    rng = np.random.default_rng(4)
    yaw, pitch, roll = rng.uniform(-1.5, 1.5, size=(3, 20))
    q = so3.quat_from_euler_zyx(yaw, pitch, roll)
    expected = Rotation.from_euler("ZYX", np.stack((yaw, pitch, roll), axis=1)).as_matrix()
    np.testing.assert_allclose(so3.quat_to_rotmat(q), expected, atol=1e-14)
    np.testing.assert_allclose(so3.yaw_from_quat(q), yaw, atol=1e-12)


@given(vec3)
def test_exp_log_roundtrip(rv):
    angle = np.linalg.norm(rv)
    if angle > np.pi - 1e-6:
        rv = rv * (np.pi - 1e-3) / angle
    q = so3.quat_from_rotvec(rv)
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12
    np.testing.assert_allclose(so3.quat_to_rotvec(q), rv, atol=1e-9)


@given(vec3)
def test_small_angle_quaternion_is_unit(dtheta):
    q = so3.small_angle_quat(dtheta)
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12
    assert q[0] > 0.0


@given(st.integers(0, 2**32 - 1), st.floats(1e-6, 1e-2))
@settings(max_examples=50)
def test_retract_is_world_frame_left_perturbation(seed, scale):
    rng = np.random.default_rng(seed)
    q = so3.quat_normalize(rng.normal(size=4))
    dtheta = scale * rng.normal(size=3)
    R_hat = so3.quat_to_rotmat(q)
    R_new = so3.quat_to_rotmat(so3.retract(q, dtheta))
    # R = (I + S(dtheta)) R_hat to first order (DESIGN.md sec. 4).
    size = np.linalg.norm(dtheta)
    np.testing.assert_allclose(R_new, (np.eye(3) + so3.skew(dtheta)) @ R_hat, atol=size**2)
    # The normalised [1; dtheta/2] has angle 2 atan(|dtheta|/2) = |dtheta| - |dtheta|^3/12 + ...
    np.testing.assert_allclose(so3.attitude_error(so3.retract(q, dtheta), q), dtheta, atol=size**3 / 6 + 1e-15)


def test_skew_is_cross_product():
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(2, 10, 3))
    np.testing.assert_allclose((so3.skew(a) @ b[..., None])[..., 0], np.cross(a, b), atol=1e-15)


def test_normalize_rejects_zero():
    with pytest.raises(ValueError, match="zero quaternion"):
        so3.quat_normalize(np.zeros(4))


def test_distance_is_sign_invariant():
    q = _random_quats(5, 6)
    np.testing.assert_allclose(so3.quat_distance(q, -q), 0.0, atol=0)

"""The standard-message codec (companion.mavlink.standard): round trips through real MAVLink bytes,
frame tags, and the validation of what comes in."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.estimation.chain import ERR_P, ERR_TH, ERR_V
from companion.estimation.so3 import attitude_error, quat_normalize, quat_to_rotmat
from companion.mavlink.codec import decode_target_feedforward, encode_target_feedforward
from companion.mavlink.dialect import load_dialect
from companion.mavlink.frames import enu_ned, error_cov_enu_ned
from companion.mavlink.standard import (
    decode_attitude_target,
    decode_external_pose,
    decode_odometry,
    decode_position_target,
    encode_attitude_target,
    encode_odometry,
    encode_position_target,
    encode_vision_position_estimate,
    euler_zyx,
)
from companion.messages import LinkState, MessageError, PoseTarget

from ..chains import random_covariances

D = load_dialect()
_MAV = D.MAVLink(None, srcSystem=1, srcComponent=1)


def wire(msg):
    """``msg`` packed into MAVLink 2 bytes and parsed back (float32 on the wire)."""
    parser = D.MAVLink(None)
    return parser.parse_char(bytearray(msg.pack(_MAV)))


def random_state(rng, P=None) -> LinkState:
    P = random_covariances(rng, 1)[0] if P is None else P
    P[ERR_P, ERR_V] = P[ERR_V, ERR_P] = 0.0  # ODOMETRY does not carry the p-v cross terms
    P[ERR_V, ERR_TH] = P[ERR_TH, ERR_V] = 0.0  # nor the velocity-attitude ones
    return LinkState(2, 12.5, rng.normal(size=3), rng.normal(size=3), quat_normalize(rng.normal(size=4)),
                     rng.normal(size=3), P)


@pytest.mark.parametrize("seed", range(5))
def test_odometry_round_trip(seed):
    rng = np.random.default_rng(seed)
    st = random_state(rng)
    msg = wire(encode_odometry(st, 12_500_000, estimator_type=D.MAV_ESTIMATOR_TYPE_NAIVE))
    assert msg.frame_id == D.MAV_FRAME_LOCAL_NED and msg.child_frame_id == D.MAV_FRAME_BODY_FRD
    assert (msg.x, msg.y, msg.z) == pytest.approx(tuple(enu_ned(st.p_w_m)), abs=1e-5)  # NED values, NED tag
    got = decode_odometry(msg, 2)
    assert got.link == 2 and got.time_s == pytest.approx(12.5)
    np.testing.assert_allclose(got.p_w_m, st.p_w_m, atol=1e-5)
    np.testing.assert_allclose(got.v_w_m_s, st.v_w_m_s, atol=1e-5)
    np.testing.assert_allclose(attitude_error(got.q_wxyz, st.q_wxyz), 0.0, atol=1e-6)
    np.testing.assert_allclose(got.omega_b_rad_s, st.omega_b_rad_s, atol=1e-5)
    np.testing.assert_allclose(got.P, st.P, atol=1e-5 * np.abs(st.P).max())


@pytest.mark.parametrize("seed", range(3))
def test_odometry_as_px4_publishes_it_is_read(seed):
    """PX4's EKF2 ODOMETRY (its mavlink ODOMETRY stream): velocity in LOCAL_NED, the variances on
    the diagonals and NaN everywhere else, the rates' variances included. Read with the
    off-diagonal terms zero, nothing refused."""
    rng = np.random.default_rng(seed)
    st = random_state(rng)
    msg = wire(encode_odometry(st, 12_500_000, estimator_type=D.MAV_ESTIMATOR_TYPE_AUTOPILOT, px4=True))
    assert msg.child_frame_id == D.MAV_FRAME_LOCAL_NED
    assert np.isnan(msg.pose_covariance[1]) and np.isnan(msg.velocity_covariance[15])
    assert msg.pose_covariance[0] == pytest.approx(error_cov_enu_ned(st.P)[0, 0], rel=1e-6)
    np.testing.assert_allclose((msg.vx, msg.vy, msg.vz), enu_ned(st.v_w_m_s), atol=1e-5)  # NED, not body
    got = decode_odometry(msg, 2)
    np.testing.assert_allclose(got.v_w_m_s, st.v_w_m_s, atol=1e-5)
    # the variances of the state (in NED on the wire), nothing else: the frame change of a
    # diagonal covariance is diagonal (a signed permutation, its own inverse)
    expected = error_cov_enu_ned(np.diag(np.diag(error_cov_enu_ned(st.P))))
    np.testing.assert_allclose(got.P, expected, rtol=1e-5, atol=1e-12)
    assert np.count_nonzero(got.P - np.diag(np.diag(got.P))) == 0


@pytest.mark.parametrize("where, value, match", [
    ("pose", (0, math.nan), "covariance unknown"),  # MAVLink: a NaN first element is unknown
    ("pose", (15, math.nan), "covariance unknown"),  # a variance the state needs (roll)
    ("velocity", (6, math.nan), "covariance unknown"),
    ("pose", (1, math.inf), "covariance unknown"),  # an infinity is never a term left out
])
def test_an_odometry_covariance_without_a_needed_variance_is_refused(where, value, match):
    rng = np.random.default_rng(4)
    msg = encode_odometry(random_state(rng), 0, estimator_type=D.MAV_ESTIMATOR_TYPE_AUTOPILOT, px4=True)
    cov = list(getattr(msg, f"{where}_covariance"))
    cov[value[0]] = value[1]
    setattr(msg, f"{where}_covariance", cov)
    with pytest.raises(MessageError, match=match):
        decode_odometry(msg, 0)


def test_external_vision_odometry_and_vision_position_estimate_give_the_same_pose():
    rng = np.random.default_rng(7)
    st = random_state(rng)
    odo = decode_external_pose(wire(encode_odometry(st, 1000, estimator_type=D.MAV_ESTIMATOR_TYPE_VISION,
                                                    rates_known=False)))
    vpe = decode_external_pose(wire(encode_vision_position_estimate(st, 1000)))
    for pose in (odo, vpe):
        assert pose.time_s == pytest.approx(1e-3)
        np.testing.assert_allclose(pose.p_w_m, st.p_w_m, atol=1e-5)
        np.testing.assert_allclose(attitude_error(pose.q_wxyz, st.q_wxyz), 0.0, atol=1e-5)
    np.testing.assert_allclose(odo.v_w_m_s, st.v_w_m_s, atol=1e-5)
    assert vpe.v_w_m_s is None


def test_odometry_in_another_frame_or_unusable_is_rejected_with_the_field():
    rng = np.random.default_rng(1)
    msg = encode_odometry(random_state(rng), 0, estimator_type=D.MAV_ESTIMATOR_TYPE_NAIVE)
    msg.frame_id = D.MAV_FRAME_LOCAL_FRD
    with pytest.raises(MessageError, match="frame_id"):
        decode_odometry(msg, 0)
    msg = encode_odometry(random_state(rng), 0, estimator_type=D.MAV_ESTIMATOR_TYPE_NAIVE)
    msg.q = [0.5, 0.0, 0.0, 0.0]
    with pytest.raises(MessageError, match="ODOMETRY.q"):
        decode_odometry(msg, 0)
    msg = encode_odometry(random_state(rng), 0, estimator_type=D.MAV_ESTIMATOR_TYPE_NAIVE)
    msg.pose_covariance = [math.nan] * 21
    with pytest.raises(MessageError, match="covariance unknown"):
        decode_odometry(msg, 0)
    assert decode_external_pose(msg).p_w_m is not None  # external vision needs no covariance


def test_pose_target_round_trip_with_the_feedforward():
    rng = np.random.default_rng(3)
    target = PoseTarget(*(rng.normal(size=3) for _ in range(1)), quat_normalize(rng.normal(size=4)),
                        *(rng.normal(size=3) for _ in range(6)))
    p, v, a = decode_position_target(wire(encode_position_target(target, 1234, 2)))
    q, w = decode_attitude_target(wire(encode_attitude_target(target, 1234, 2)))
    wd, f, tau = decode_target_feedforward(wire(encode_target_feedforward(target, 1234, 2)))
    for got, want in ((p, target.p_w_m), (v, target.v_w_m_s), (a, target.a_w_m_s2), (w, target.omega_d_rad_s),
                      (wd, target.omega_dot_d_rad_s2), (f, target.force_ff_w_n), (tau, target.torque_ff_b_nm)):
        np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_allclose(attitude_error(q, target.q_wxyz), 0.0, atol=1e-6)


def test_masked_target_fields_are_zero_and_a_rate_only_attitude_target_is_refused():
    target = PoseTarget.hold(np.array([1.0, 2.0, 3.0]), np.array([1.0, 0, 0, 0]))
    msg = encode_position_target(replace_v(target), 0, 1)
    msg.type_mask |= 0b0000_0011_1000
    _, v, _ = decode_position_target(msg)
    assert np.all(v == 0.0)
    att = encode_attitude_target(target, 0, 1)
    att.type_mask = 0b1000_0000
    with pytest.raises(MessageError, match="attitude is masked"):
        decode_attitude_target(att)


def replace_v(target):
    from dataclasses import replace

    return replace(target, v_w_m_s=np.array([1.0, 1.0, 1.0]))


def test_euler_angles_are_mavlinks():
    from companion.estimation.so3 import quat_from_euler_zyx

    for yaw, pitch, roll in ((0.3, -0.2, 0.1), (-2.5, 1.2, -3.0)):
        q = quat_from_euler_zyx(yaw, pitch, roll)
        assert euler_zyx(q) == pytest.approx((roll, pitch, yaw), abs=1e-12)
        R = quat_to_rotmat(q)
        assert R[2, 0] == pytest.approx(-math.sin(pitch))

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import quat_normalize, quat_to_rotmat
from companion.messages import Correction, LinkState
from companion.mavlink import frames
from companion.mavlink.codec import (
    MessageError,
    decode_correction,
    decode_link_state,
    encode_correction,
    encode_link_state,
)
from companion.mavlink.dialect import load_dialect

from ..chains import random_covariances
from ..mavlink_wire import frame_and_parsed, over_mavlink

D = load_dialect()


def _state(rng):
    return LinkState(
        link=1,
        time_s=12.345678,
        p_w_m=rng.normal(size=3) * 10,
        v_w_m_s=rng.normal(size=3),
        q_wxyz=quat_normalize(rng.normal(size=4)),
        omega_b_rad_s=rng.normal(size=3),
        P=random_covariances(rng, 1)[0],
    )


def struct_size(cls) -> int:
    import struct

    return struct.calcsize(cls.unpacker.format)


@pytest.mark.parametrize("name", ["SKELETON_LINK_STATE", "SKELETON_CORRECTION", "SKELETON_AHRS_REFERENCE"])
def test_dialect_payloads_fit_mavlink2(name):
    cls = D.mavlink_map[getattr(D, f"MAVLINK_MSG_ID_{name}")]
    assert struct_size(cls) <= 255


def test_link_state_message_is_the_largest_and_fits():
    assert struct_size(D.MAVLink_skeleton_link_state_message) == 249


@given(st.integers(0, 2**32 - 1))
@settings(max_examples=40)
def test_wire_round_trip_is_exact(seed):
    rng = np.random.default_rng(seed)
    msg = encode_link_state(_state(rng), flags=3, reset_counter=7, correction_seq=9, correction_latency_us=12345)
    data, back = frame_and_parsed(msg, sysid=2)
    for field in msg.fieldnames:
        a, b = getattr(msg, field), getattr(back, field)
        # floats go through float32 on the wire: compare the float32 values exactly
        np.testing.assert_array_equal(np.float32(a) if isinstance(a, (float, list)) else a,
                                      np.float32(b) if isinstance(b, (float, list)) else b)
    assert len(data) == 12 + 249  # MAVLink 2 header (10) + CRC (2) + payload, no signing


@given(st.integers(0, 2**32 - 1))
@settings(max_examples=40)
def test_typed_link_state_round_trip(seed):
    rng = np.random.default_rng(seed)
    state = _state(rng)
    back = over_mavlink(encode_link_state(state), sysid=2)
    got = decode_link_state(back, link=1)
    assert got.time_s == pytest.approx(state.time_s, abs=1e-6)
    np.testing.assert_allclose(got.p_w_m, state.p_w_m, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got.v_w_m_s, state.v_w_m_s, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(quat_to_rotmat(got.q_wxyz), quat_to_rotmat(state.q_wxyz), atol=1e-6)
    np.testing.assert_allclose(got.omega_b_rad_s, state.omega_b_rad_s, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got.P, state.P, rtol=1e-5, atol=1e-7)


def test_correction_round_trip_and_withdrawal():
    corr = Correction(link=2, ekf_time_s=3.5, dp_w_m=np.array([0.1, -0.2, 0.3]), dv_w_m_s=np.array([0.01, 0.0, -0.02]),
                      dtheta_w_rad=np.array([0.001, 0.002, -0.003]), seq=42)
    back = over_mavlink(encode_correction(corr, target_system=3), sysid=2)
    assert back.target_system == 3 and back.valid == 1
    got = decode_correction(back, link=2)
    assert got.seq == 42 and got.ekf_time_s == pytest.approx(3.5)
    np.testing.assert_allclose(got.dp_w_m, corr.dp_w_m, rtol=1e-6)
    np.testing.assert_allclose(got.dtheta_w_rad, corr.dtheta_w_rad, rtol=1e-6)
    back = over_mavlink(encode_correction(corr, target_system=3, valid=False), sysid=2)
    assert decode_correction(back, link=2) is None


def test_covariance_packing_order_is_row_major_upper_triangle():
    P = np.arange(81, dtype=float).reshape(9, 9)
    P = P + P.T
    packed = frames.pack_upper(P)
    expected = [P[i, j] for i in range(9) for j in range(i, 9)]
    assert packed == expected
    np.testing.assert_array_equal(frames.unpack_upper(packed), P)
    msg = encode_link_state(LinkState(0, 0.0, np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3),
                                      np.eye(9) + 0.01 * np.ones((9, 9))))
    assert len(msg.covariance) == 45


def test_frame_conversions_agree_with_rotating_vectors():
    rng = np.random.default_rng(3)
    q = quat_normalize(rng.normal(size=4))
    v_b = rng.normal(size=3)
    R_enu_flu = quat_to_rotmat(q)
    R_ned_frd = quat_to_rotmat(frames.quat_enu_flu_to_ned_frd(q))
    np.testing.assert_allclose(R_ned_frd @ frames.flu_frd(v_b), frames.enu_ned(R_enu_flu @ v_b), atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(frames.quat_ned_frd_to_enu_flu(frames.quat_enu_flu_to_ned_frd(q))),
                               R_enu_flu, atol=1e-12)
    v = rng.normal(size=3)
    np.testing.assert_allclose(frames.enu_ned(frames.enu_ned(v)), v)
    assert np.linalg.det(frames.ENU_NED) == pytest.approx(1.0)
    # east in ENU is y (east) in NED; up is -z
    np.testing.assert_allclose(frames.enu_ned([1.0, 0, 0]), [0, 1.0, 0])
    np.testing.assert_allclose(frames.enu_ned([0, 0, 1.0]), [0, 0, -1.0])


def test_error_covariance_rotates_with_the_world_frame():
    rng = np.random.default_rng(4)
    P = random_covariances(rng, 1)[0]
    dx = rng.multivariate_normal(np.zeros(9), P, size=20000)
    dx_ned = np.concatenate([frames.enu_ned(dx[:, 3 * k: 3 * k + 3]) for k in range(3)], axis=1)
    np.testing.assert_allclose(np.cov(dx_ned.T), frames.error_cov_enu_ned(P), atol=0.02 * np.abs(P).max())


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda m: setattr(m, "p_ned", [float("nan"), 0.0, 0.0]), "p_ned"),
        (lambda m: setattr(m, "q", [2.0, 0.0, 0.0, 0.0]), "q"),
        (lambda m: setattr(m, "covariance", [-1.0] + [0.0] * 44), "covariance"),
    ],
)
def test_bad_link_states_are_rejected_with_the_field(mutate, field):
    msg = encode_link_state(_state(np.random.default_rng(0)))
    mutate(msg)
    with pytest.raises(MessageError, match=field):
        decode_link_state(msg, link=0)


def test_huge_attitude_correction_is_rejected():
    msg = encode_correction(Correction(0, 0.0, np.zeros(3), np.zeros(3), np.array([4.0, 0, 0])), 1)
    with pytest.raises(MessageError, match="dtheta"):
        decode_correction(msg, 0)

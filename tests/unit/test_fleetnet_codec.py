"""The Zenoh layer's wire codec, without a session: every message round-trips exactly, and a
malformed payload is refused with the reason (the same over real Zenoh sessions:
tests/integration/test_fleetnet_zenoh.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.fleetnet import codec
from companion.messages import (ChainHome, Correction, GlobalShift, GroupBoundaryReport, GroupPassiveLinks, LinkState,
                                MessageError, check_psd)

from ..chains import random_covariances
from ..fleetnet_cases import equal, load_observation, neighbour_pose, targets


# -- codec --------------------------------------------------------------------------------------------------
def _messages(rng):
    P = random_covariances(rng, 1)[0]
    info = np.linalg.inv(random_covariances(rng, 1)[0][:6, :6])
    q = rng.normal(size=4)
    return [
        LinkState(5, 12.345678, rng.normal(size=3), rng.normal(size=3), q / np.linalg.norm(q), rng.normal(size=3), P),
        Correction(2, 3.25, rng.normal(size=3), rng.normal(size=3), 0.01 * rng.normal(size=3), 4242),
        GroupBoundaryReport(1, 1_250_000, rng.normal(size=6), rng.normal(size=6), 0.5 * (info + info.T), 1234, 567),
        GroupBoundaryReport(2, 1_300_000, rng.normal(size=6), rng.normal(size=6), 0.5 * (info + info.T), 1234, 567,
                            _psd12(rng)),
        GlobalShift(1, 1_250_000, (0, 1, 3), rng.normal(size=(3, 6)), 0, 1_400_000, (10, 20, 30)),
        GlobalShift(2, 50_000, (2,), np.zeros((1, 6)), hold_us=(0,)),
        GlobalShift(0, 50_000, (0, 1, 1, 2), rng.normal(size=(4, 6)), hold_us=(1, 2, 3, 4), parts=(0, 0, 1, 0)),
        GroupBoundaryReport(1, 1_300_000, rng.normal(size=6), rng.normal(size=6), 0.5 * (info + info.T), part=1,
                            parts=2, joins_left=False, joins_right=True),
        targets(rng, (0, 1, 2, 3, 4, 5, 6)),
        targets(rng, (2, 5)),
        GroupPassiveLinks(1, 20_060_000, (2,)),
        GroupPassiveLinks(0, 5_000_000, ()),
        GroupPassiveLinks(3, 2**40, (6, 7, 9)),
        ChainHome(1, 20_000_000, rng.normal(size=3)),
    ]


def _psd12(rng) -> np.ndarray:
    """A symmetric PSD 12 x 12 of rank 9 (a single link's tip covariance is singular)."""
    A = rng.normal(size=(12, 9))
    return A @ A.T


@pytest.mark.parametrize("seed", range(3))
def test_codec_round_trip_is_exact(seed):
    for msg in _messages(np.random.default_rng(seed)):
        out = codec.decode(codec.encode(msg))
        assert type(out) is type(msg)
        if isinstance(msg, LinkState):  # unit quaternion is renormalised, covariance symmetrised
            np.testing.assert_allclose(out.q_wxyz, msg.q_wxyz, atol=1e-15)
            np.testing.assert_allclose(out.P, 0.5 * (msg.P + msg.P.T), atol=0)
            assert out.link == msg.link and out.time_s == msg.time_s
        elif isinstance(msg, GroupBoundaryReport) and msg.tip_cov_pv is not None:  # symmetrised
            np.testing.assert_allclose(out.tip_cov_pv, msg.tip_cov_pv, atol=1e-12)
            assert equal(replace(out, tip_cov_pv=None), replace(msg, tip_cov_pv=None))
        else:
            assert equal(out, msg), msg


@pytest.mark.parametrize("seed", range(3))
def test_a_neighbour_pose_round_trips_to_the_bit(seed):
    msg = neighbour_pose(np.random.default_rng(seed))
    out = codec.decode(codec.encode(msg))
    for name in ("q_cm_wxyz", "q_bc_wxyz", "q_bm_wxyz"):  # renormalised
        np.testing.assert_allclose(getattr(out, name), getattr(msg, name), atol=1e-15)
    np.testing.assert_array_equal(out.cov_c, 0.5 * (msg.cov_c + msg.cov_c.T))
    assert equal(replace(out, q_cm_wxyz=msg.q_cm_wxyz, q_bc_wxyz=msg.q_bc_wxyz, q_bm_wxyz=msg.q_bm_wxyz,
                         cov_c=msg.cov_c), msg)


@pytest.mark.parametrize("change, reason", [
    (dict(observed=3), "link 4 is not a neighbour of link 2"),
    (dict(observed=1), "link 2 is not a neighbour of link 2"),
    (dict(t_capture_s=-1.0), "before the clock's start"),
    (dict(t_capture_s=float("nan")), "t_capture_s: non-finite"),
    (dict(q_cm_wxyz=np.array([1.0, 0.1, 0.0, 0.0])), "q_cm_wxyz: quaternion norm"),
    (dict(q_bm_wxyz=np.zeros(4)), "q_bm_wxyz: quaternion norm"),
    (dict(t_cm_m=np.array([0.0, 0.0, 25.0])), "t_cm_m: magnitude 25"),
    (dict(camera_pos_b_m=np.array([6.0, 0.0, 0.0])), "camera_pos_b_m: magnitude 6"),
    (dict(marker_pos_b_m=np.array([np.inf, 0.0, 0.0])), "marker_pos_b_m: non-finite"),
    (dict(cov_c=-np.eye(6)), "cov_c: not positive definite"),
])
def test_a_neighbour_pose_that_is_not_one_is_refused_with_the_reason(change, reason):
    with pytest.raises(MessageError, match=reason):
        codec.decode(codec.encode(replace(neighbour_pose(np.random.default_rng(0)), **change)))


@pytest.mark.parametrize("seed", range(3))
def test_a_load_observation_round_trips(seed):
    msg = load_observation(np.random.default_rng(seed), vehicle=seed)
    out = codec.decode(codec.encode(msg))
    assert (out.vehicle, out.stamp_s) == (msg.vehicle, msg.stamp_s)
    np.testing.assert_array_equal(out.vehicle_in_load_m, msg.vehicle_in_load_m)
    np.testing.assert_allclose(out.load_in_body_q_wxyz, msg.load_in_body_q_wxyz, atol=1e-15)  # renormalised
    np.testing.assert_array_equal(out.joint_cov, 0.5 * (msg.joint_cov + msg.joint_cov.T))
    np.testing.assert_array_equal(out.cov_m2, out.joint_cov[:3, :3])


def test_a_load_observation_without_the_loads_attitude_does_not_travel():
    obs = load_observation(np.random.default_rng(0))
    with pytest.raises(ValueError, match="only an observation with the load's attitude"):
        codec.encode(replace(obs, load_in_body_q_wxyz=None, joint_cov=None))


# byte offsets in a LoadObservation payload: header 6, vehicle u16, stamp f64, y (3 f64), q (4 f64), joint (21 f64)
_STAMP, _Y, _Q, _JOINT = 8, 16, 40, 72


@pytest.mark.parametrize("offset, values, reason", [
    (_STAMP, [-1.0], "stamp_s: -1 s is before the clock's start"),
    (_STAMP, [float("nan")], "stamp_s: non-finite"),
    (_Y, [60.0, 0.0, 0.0], "vehicle_in_load_m: magnitude 60"),
    (_Q, [1.0, 0.2, 0.0, 0.0], "load_in_body_q_wxyz: quaternion norm"),
    (_JOINT, [-1.0], "joint_cov: not positive definite"),
])
def test_a_hostile_load_observation_is_refused_with_the_reason(offset, values, reason):
    good = bytearray(codec.encode(load_observation(np.random.default_rng(1))))
    good[offset:offset + 8 * len(values)] = np.asarray(values, dtype="<f8").tobytes()
    with pytest.raises(MessageError, match=reason):
        codec.decode(bytes(good))


def test_codec_rejects_malformed_payloads_with_the_reason():
    good = codec.encode(_messages(np.random.default_rng(0))[2])
    bad_info = GroupBoundaryReport(0, 0, np.zeros(6), np.zeros(6), -np.eye(6))
    nan_tip = GroupBoundaryReport(0, 0, np.full(6, np.nan), np.zeros(6), np.eye(6))
    cases = {
        b"": "shorter than",
        b"XXXX" + good[4:]: "magic",
        good[:4] + bytes([9]) + good[5:]: "version 9",
        good[:4] + bytes([codec.VERSION - 1]) + good[5:]:  # an older peer is refused, naming both versions
            f"version {codec.VERSION - 1}, this companion speaks version {codec.VERSION}",
        good[:5] + bytes([77]) + good[6:]: "unknown message type 77",
        good[:-3]: "truncated",
        good + b"\0": "trailing",
        codec.encode(bad_info): "info_pv: not positive definite",
        codec.encode(nan_tip): "left_tip_pv_w: non-finite",
        codec.encode(replace(nan_tip, left_tip_pv_w=np.zeros(6), tip_cov_pv=-np.eye(12))):
            "tip_cov_pv: not positive semidefinite",
        codec.encode(replace(nan_tip, left_tip_pv_w=np.zeros(6), tip_cov_pv=np.full((12, 12), np.nan))):
            "tip_cov_pv: non-finite",
        # (good has no tip covariance: flag 0, then part, parts, joins_left, joins_right)
        good[:-5] + bytes([2]) + good[-4:]: "tip_cov_pv: presence flag 2",
        good[:-4] + bytes([1, 1, 1, 1]): "part 1 of 1",
        good[:-4] + bytes([0, 2, 1, 1]): "joins_right: 1 for part 0 of 2",
        good[:-4] + bytes([1, 2, 1, 1]): "joins_left: 1 for part 1 of 2",
        good[:-4] + bytes([0, 1, 3, 1]): "joins_left: 3",
        codec.encode(GlobalShift(0, 0, (1, 1), np.zeros((2, 6)), hold_us=(0, 0))): "increasing",
        codec.encode(GlobalShift(0, 0, (1, 1), np.zeros((2, 6)), hold_us=(0, 0), parts=(1, 0))): "increasing",
        codec.encode(GlobalShift(0, 0, (2, 1), np.zeros((2, 6)), hold_us=(0, 0))): "increasing",
        codec.encode(replace(targets(np.random.default_rng(2), (0, 1)), links=(1, 1))): "ChainTargets.links",
        codec.encode(replace(targets(np.random.default_rng(2), (0, 1)), q_wxyz=np.ones((2, 4)))): r"q_wxyz\[link 1\]",
        codec.encode(replace(targets(np.random.default_rng(2), (0, 4)),
                             q_wxyz=np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0.1]]))):
            r"q_wxyz\[link 5\]: quaternion norm 1.00499 is not 1",
        codec.encode(replace(targets(np.random.default_rng(2), (0, 1)), a_w_m_s2=np.full((2, 3), np.inf))):
            "a_w_m_s2: non-finite",
        codec.encode(GroupPassiveLinks(1, 0, (3, 2))): "GroupPassiveLinks.links",
        codec.encode(replace(_messages(np.random.default_rng(3))[0], time_s=float("nan"))): "LinkState.time_s: non-finite",
        codec.encode(replace(_messages(np.random.default_rng(3))[1], ekf_time_s=float("inf"))):
            "Correction.ekf_time_s: non-finite",
        codec.encode(GroupPassiveLinks(1, 0, (2, 2))): "GroupPassiveLinks.links",
        codec.encode(ChainHome(1, 0, np.array([0.0, np.nan, 0.0]))): "ChainHome.offset_w_m: non-finite",
        codec.encode(ChainHome(1, 0, np.array([0.0, 0.0, 60.0]))): "ChainHome.offset_w_m: magnitude 60 exceeds 50",
    }
    for payload, reason in cases.items():
        with pytest.raises(MessageError, match=reason):
            codec.decode(payload)
    rng = np.random.default_rng(1)
    for _ in range(300):  # random bytes behind a valid header never raise anything else
        body = rng.integers(0, 256, size=int(rng.integers(0, 400)), dtype=np.uint8).tobytes()
        try:
            codec.decode(good[:6] + body)
        except MessageError:
            pass


def _psd_by_eigenvalues(m: np.ndarray) -> bool:
    """check_psd's rule written out: the smallest eigenvalue no lower than -1e-9 times the largest."""
    eig = np.linalg.eigvalsh(0.5 * (m + m.T))
    return eig[0] >= -1e-9 * max(float(np.abs(eig).max()), 1e-300)


@pytest.mark.parametrize("name, matrix, accepted", [
    ("positive definite", np.diag([1.0, 2.0, 3.0]), True),
    ("singular (no Cholesky factor)", np.diag([1.0, 1.0, 0.0]), True),
    ("negative eigenvalue at rounding", np.diag([1.0, 1.0, -1e-12]), True),
    ("indefinite", np.diag([1.0, 1.0, -1e-3]), False),
    ("negative definite", -np.eye(3), False),
    ("zero", np.zeros((3, 3)), True),
])
def test_a_covariance_is_positive_semidefinite_by_its_eigenvalues(name, matrix, accepted):
    assert _psd_by_eigenvalues(matrix) == accepted
    if accepted:
        np.testing.assert_array_equal(check_psd("P", matrix), matrix)
    else:
        with pytest.raises(MessageError, match="P: not positive semidefinite"):
            check_psd("P", matrix)


@given(st.integers(0, 2**32 - 1), st.integers(1, 12), st.floats(-1e-6, 1e-6))
@settings(max_examples=200, deadline=None)
def test_check_psd_decides_as_the_eigenvalue_rule(seed, n, shift):
    """Random low-rank covariances, shifted a little either way: the Cholesky shortcut accepts
    exactly what the eigenvalue rule accepts."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, int(rng.integers(1, n + 1))))
    m = a @ a.T + shift * np.eye(n)
    if _psd_by_eigenvalues(m):
        check_psd("P", m)
    else:
        with pytest.raises(MessageError):
            check_psd("P", m)


@pytest.mark.parametrize("k", range(len(_messages(np.random.default_rng(4)))))
def test_every_cut_of_a_payload_is_refused_as_truncated(k):
    payload = codec.encode(_messages(np.random.default_rng(4))[k])
    for end in range(len(payload)):
        with pytest.raises(MessageError, match="shorter than|truncated"):
            codec.decode(payload[:end])

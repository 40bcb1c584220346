"""A faulty link's position through a carried link (companion.engine.bridge): the two tips the
carried link joins are its length apart, nothing more."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.engine.bridge import bridge_correction, bridged_position
from companion.estimation.chain import ERR_P
from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat
from companion.messages import LinkState

rotvecs = st.lists(st.floats(-1.5, 1.5), min_size=3, max_size=3).map(np.array)
D = np.array([[0.4, 0.0, 0.0], [0.5, 0.0, 0.0], [0.3, 0.0, 0.0]])


def _chain(rv):
    """Three links joined tip to tip at attitudes ``rv`` (rotation vectors), the first centred at
    (1, 2, 3): their centres and attitudes."""
    q = np.array([quat_from_rotvec(r) for r in rv])
    R = quat_to_rotmat(q)
    p = [np.array([1.0, 2.0, 3.0])]
    for i in (1, 2):
        p.append(p[-1] + R[i - 1] @ D[i - 1] + R[i] @ D[i])
    return np.array(p), q


@settings(max_examples=60, deadline=None)
@given(rotvecs, rotvecs, rotvecs, st.floats(-0.8, 0.8))
def test_a_faulty_link_off_along_the_carried_link_is_put_back_and_one_in_place_is_left(r0, r1, r2, off):
    """For any attitudes of three joined links: the end links in place are left where they are; one
    displaced by ``off`` along the line between the carried link's tips is put back exactly (either
    side)."""
    p, q = _chain([r0, r1, r2])
    fixed, u = bridged_position(p[0], q[0], D[0], D[1], p[2], q[2], D[2], True)
    np.testing.assert_allclose(fixed, p[2], atol=1e-12)
    moved, _ = bridged_position(p[0], q[0], D[0], D[1], p[2] + off * u, q[2], D[2], True)
    np.testing.assert_allclose(moved, p[2], atol=1e-12)
    back, w = bridged_position(p[2], q[2], D[2], D[1], p[0] + off * u, q[0], D[0], False)
    np.testing.assert_allclose(w, -u, atol=1e-12)
    np.testing.assert_allclose(back, p[0], atol=1e-12)


def test_nothing_is_corrected_across_the_carried_link():
    """A faulty link off across the line of the carried link's tips (the carried link swung) is
    moved only along that line: the correction has no component across it, and none in velocity
    or attitude; its covariance keeps the faulty link's across the line and takes the healthy
    link's along it; the healthy state is carried to the faulty one's stamp with its velocity."""
    q = np.array([1.0, 0.0, 0.0, 0.0])
    d = np.array([[0.5, 0.0, 0.0]] * 3)
    P = np.diag([0.04] * 3 + [0.01] * 3 + [1e-3] * 3)
    healthy = LinkState(0, 9.99, np.array([-1.01, 0.0, 2.0]), np.array([1.0, 0.0, 0.0]), q, np.zeros(3), P)
    # the healthy link's right tip at (-0.5, 0, 2) at 10 s, the faulty one's left tip at (0.8, 0.4, 2): 1.36 m
    faulty = LinkState(2, 10.0, np.array([1.3, 0.4, 2.0]), np.array([0.2, 0.0, 0.0]), q, np.zeros(3), 9.0 * P)
    corr, state = bridge_correction(faulty, healthy, d, True, seq=7)
    r = np.array([0.8 - (-0.5), 0.4, 0.0])  # faulty's left tip less the healthy's right tip
    u = r / np.linalg.norm(r)
    np.testing.assert_allclose(corr.dp_w_m, (1.0 - np.linalg.norm(r)) * u, atol=1e-12)
    assert not corr.dv_w_m_s.any() and not corr.dtheta_w_rad.any() and corr.ekf_time_s == 10.0 and corr.seq == 7
    tips = (state.p_w_m - d[2]) - np.array([-0.5, 0.0, 2.0])
    np.testing.assert_allclose(np.linalg.norm(tips), 1.0)  # the carried link's length apart
    Pp = state.P[ERR_P, ERR_P]
    np.testing.assert_allclose(u @ Pp @ u, 0.04)
    across = np.cross(u, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(across @ Pp @ across, 0.36)
    np.testing.assert_allclose(state.P[3:, 3:], faulty.P[3:, 3:])
    np.testing.assert_allclose(state.v_w_m_s, faulty.v_w_m_s)

"""A faulty link's position through a carried link (companion.engine.bridge): the geometry of a bent
chain, and the correction's parts."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.engine.bridge import BRIDGE_ATT_STD_RAD, bridge_correction, bridged_position
from companion.estimation.chain import ERR_P
from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat
from companion.messages import LinkState

rotvecs = st.lists(st.floats(-1.5, 1.5), min_size=3, max_size=3).map(np.array)


def _chain(rv, d):
    """Three links joined tip to tip at attitudes ``rv`` (rotation vectors), the first centred at
    (1, 2, 3): their centres and attitudes."""
    q = np.array([quat_from_rotvec(r) for r in rv])
    R = quat_to_rotmat(q)
    p = [np.array([1.0, 2.0, 3.0])]
    for i in (1, 2):
        p.append(p[-1] + R[i - 1] @ d[i - 1] + R[i] @ d[i])
    return np.array(p), q


@settings(max_examples=60, deadline=None)
@given(rotvecs, rotvecs, rotvecs, st.floats(0.2, 1.0))
def test_the_bridge_puts_a_link_where_the_chain_does(r0, r1, r2, half):
    """For any attitudes of three joined links, the third link's centre through the middle one from
    the first (and the first's from the third) is where the chain has it."""
    d = np.array([[half, 0.0, 0.0], [0.5, 0.0, 0.0], [0.4, 0.0, 0.0]])
    p, q = _chain([r0, r1, r2], d)
    np.testing.assert_allclose(bridged_position(p[0], q[0], d[0], q[1], d[1], q[2], d[2], True), p[2], atol=1e-12)
    np.testing.assert_allclose(bridged_position(p[2], q[2], d[2], q[1], d[1], q[0], d[0], False), p[0], atol=1e-12)


def test_a_bridge_corrects_the_position_only_with_the_spread_of_the_carried_attitude():
    """The correction moves the faulty link's position to the bridged one, stamped on its state,
    leaves its velocity and attitude, and its position covariance is the healthy link's plus the
    carried link's attitude spread at its length; the healthy state is carried to the faulty
    one's stamp with its velocity."""
    d = np.array([[0.5, 0.0, 0.0]] * 3)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    P = np.diag([0.04] * 3 + [0.01] * 3 + [1e-3] * 3)
    healthy = LinkState(0, 9.99, np.array([-1.01, 0.0, 2.0]), np.array([1.0, 0.0, 0.0]), q, np.zeros(3), P)
    faulty = LinkState(2, 10.0, np.array([2.3, 0.4, 2.0]), np.array([0.2, 0.0, 0.0]), q, np.zeros(3), 9.0 * P)
    corr, state = bridge_correction(faulty, healthy, q, d, True, seq=7)
    np.testing.assert_allclose(corr.dp_w_m, [1.0 - 2.3, -0.4, 0.0], atol=1e-12)
    assert not corr.dv_w_m_s.any() and not corr.dtheta_w_rad.any() and corr.ekf_time_s == 10.0 and corr.seq == 7
    np.testing.assert_allclose(state.P[ERR_P, ERR_P], (0.04 + (1.0 * BRIDGE_ATT_STD_RAD) ** 2) * np.eye(3))
    np.testing.assert_allclose(state.P[3:, 3:], faulty.P[3:, 3:])
    np.testing.assert_allclose(state.v_w_m_s, faulty.v_w_m_s)

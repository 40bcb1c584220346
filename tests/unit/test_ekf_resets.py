"""The EKF's resets on persistent rejection (link_firmware_sim.estimators): a clean discontinuity
in the state and its covariance, when they are due, and the firmware's use of them (an estimate
that ran off is put back on its reference and reports it)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_euler_zyx
from link_firmware_sim.estimators.ekf import (E_P, E_TH, E_V, X_P, X_Q, X_V, EkfConfig, ekf_init,
                                              ekf_reset_attitude, ekf_reset_position, ekf_reset_velocity)
from link_firmware_sim.estimators.link_ekf import LinkEkf

from .test_gps_health import GRAVITY_UP, _hovering_firmware

Q_YAW_40 = quat_from_euler_zyx(np.radians(40.0), 0.0, 0.0)


@pytest.mark.parametrize("reset, xs, es, value, var", [
    (ekf_reset_position, X_P, E_P, np.array([5.0, -1.0, 2.0]), 0.04),
    (ekf_reset_velocity, X_V, E_V, np.array([0.5, 0.2, -0.1]), np.array([0.1, 0.1, 0.2])),
    (ekf_reset_attitude, X_Q, E_TH, Q_YAW_40, 0.04),
])
def test_a_reset_is_a_clean_discontinuity(reset, xs, es, value, var):
    x, P = ekf_init(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), EkfConfig())
    B = np.random.default_rng(0).normal(size=P.shape)
    P = P + 0.01 * B @ B.T  # positive definite, correlations everywhere
    x2, P2 = reset(x, P, value, var)
    np.testing.assert_allclose(x2[xs], value)
    np.testing.assert_allclose(P2[es, es], np.diag(np.broadcast_to(var, 3)))
    others = [i for i in range(P.shape[0]) if i not in range(es.start, es.stop)]
    assert np.all(P2[es][:, others] == 0) and np.all(P2[others][:, es] == 0)
    np.testing.assert_array_equal(P2[np.ix_(others, others)], P[np.ix_(others, others)])
    assert np.all(np.linalg.eigvalsh(P2) > 0)
    rest = np.ones(x.size, bool)
    rest[xs] = False
    np.testing.assert_array_equal(x2[rest], x[rest])


@pytest.mark.parametrize("reset, bad", [(ekf_reset_velocity, [0.0, np.nan, 0.0]), (ekf_reset_velocity, [1.0, 2.0]),
                                        (ekf_reset_attitude, [0.0, 0.0, 0.0, 0.0]),
                                        (ekf_reset_attitude, [1.0, 0.0, np.inf, 0.0])])
def test_a_reset_to_a_bad_value_is_refused(reset, bad):
    x, P = ekf_init(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), EkfConfig())
    with pytest.raises(ValueError, match="reset: expected"):
        reset(x, P, bad, 0.04)


@pytest.mark.parametrize("compiled", [False, True])
def test_a_reset_is_due_after_that_many_rejections_in_a_row(compiled):
    ekf = LinkEkf(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), EkfConfig(att_reset_rejections=3),
                  compiled=compiled)
    far = quat_from_euler_zyx(np.radians(150.0), 0.0, 0.0)
    for _ in range(2):
        assert not ekf.update_attitude(far).accepted and not ekf.attitude_reset_due
    ekf.update_attitude(np.array([1.0, 0, 0, 0]))  # an accepted one starts the count again
    for _ in range(3):
        ekf.update_attitude(far)
    assert ekf.attitude_reset_due
    assert np.degrees(ekf.reset_attitude(far)) == pytest.approx(150.0, abs=0.5)
    assert not ekf.attitude_reset_due and ekf.resets == 1
    ekf.count_attitude(0, 2)  # the fused ticks' counts: the rejected ones after the accepted ones
    ekf.count_attitude(1, 1)
    assert ekf.rejected_run["att"] == 1
    ekf.count_attitude(0, 1)
    assert ekf.rejected_run["att"] == 2
    ekf.count_attitude(2, 0)
    assert ekf.rejected_run["att"] == 0
    never = LinkEkf(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), EkfConfig(att_reset_rejections=0))
    never.count_attitude(0, 1000)
    assert not never.attitude_reset_due


def test_the_firmware_resets_an_attitude_that_ran_off_to_its_reference():
    """The estimate 150 deg off in yaw (a gyro that stuck, say): every reference is rejected, the
    26th resets the attitude to it (STATUSTEXT), and the next ones are fused again."""
    fw, q = _hovering_firmware()
    fw.ekf.x[X_Q] = quat_from_euler_zyx(np.radians(150.0), 0.0, 0.0)
    for k in range(500):
        t = k / 500
        if k % 10 == 0:
            fw.on_attitude(t, q)
        fw.on_imu(t, np.zeros(3), GRAVITY_UP)
    texts = [e.text for e in fw.events if e.kind == "reset"]
    assert texts == ["EKF attitude reset: jumped 150 deg"], texts
    assert fw.ekf.rejected["att"] == EkfConfig().att_reset_rejections and fw.ekf.accepted["att"] > 10
    np.testing.assert_allclose(np.abs(fw.ekf.q_wxyz @ q), 1.0, atol=1e-3)


def test_the_firmware_resets_a_velocity_that_ran_off_to_the_gps():
    fw, q = _hovering_firmware()
    fw.ekf.x[X_V] = [6.0, 0.0, 0.0]
    rng = np.random.default_rng(3)
    for k in range(1500):
        t = k / 500
        if k % 50 == 0:
            fw.on_gps(t, rng.normal(0, 0.1, 3), rng.normal(0, 0.03, 3))
        if k % 10 == 0:
            fw.on_attitude(t, q)
        fw.on_imu(t, np.zeros(3), GRAVITY_UP)
    texts = [e.text for e in fw.events if e.kind == "reset"]
    assert any(s.startswith("EKF velocity reset: jumped") for s in texts), texts
    assert np.linalg.norm(fw.ekf.v_w_m_s) < 0.3


def test_a_due_attitude_reset_takes_the_step_by_step_path():
    fw, _ = _hovering_firmware()
    fw.ekf.count_attitude(0, EkfConfig().att_reset_rejections)
    assert fw.ekf.attitude_reset_due and not fw._fused_applies(0.0)


def test_reset_counts_must_be_whole_numbers():
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="att_reset_rejections must be a whole number"):
            EkfConfig(att_reset_rejections=bad)

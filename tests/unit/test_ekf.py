import numpy as np
import pytest

from companion.estimation.so3 import attitude_error, quat_distance, quat_normalize, retract, yaw_from_quat
from link_firmware_sim.estimators.ekf import (
    E_BA,
    E_BG,
    E_P,
    E_TH,
    E_V,
    NE,
    X_BA,
    X_BG,
    X_P,
    X_Q,
    X_V,
    EkfConfig,
    EkfNoise,
    ekf_init,
    ekf_predict,
    ekf_update_attitude,
    ekf_update_heading,
    ekf_update_position,
    ekf_update_velocity,
    error_transition,
    heading_jacobian,
    inject_error,
)
from link_firmware_sim.estimators import LinkEkf
from sitl.synthetic import ChainMotion, Sensors, SensorModel, chain_truth


def _error(x_true, x_hat):
    e = np.zeros(NE)
    e[E_P] = x_true[X_P] - x_hat[X_P]
    e[E_V] = x_true[X_V] - x_hat[X_V]
    e[E_TH] = attitude_error(x_true[X_Q], x_hat[X_Q])
    e[E_BA] = x_true[X_BA] - x_hat[X_BA]
    e[E_BG] = x_true[X_BG] - x_hat[X_BG]
    return e


@pytest.mark.parametrize("seed", range(5))
def test_error_state_transition_matches_nominal_propagation(seed):
    """F maps a small error to the error between two propagated nominal states."""
    rng = np.random.default_rng(seed)
    x, _ = ekf_init(rng.normal(size=3), rng.normal(size=3), quat_normalize(rng.normal(size=4)))
    x[X_BA] = 0.1 * rng.normal(size=3)
    x[X_BG] = 0.01 * rng.normal(size=3)
    gyro, accel, dt = rng.normal(size=3), rng.normal(size=3) + [0, 0, 9.8], 0.01
    noise = EkfNoise(0.0, 0.0, 0.0, 0.0, 0.0)
    F = error_transition(x, gyro, accel, dt)
    zero = np.zeros((NE, NE))
    x_hat1, _ = ekf_predict(x, zero, gyro, accel, dt, noise)
    for k in range(NE):
        dx0 = np.zeros(NE)
        dx0[k] = 1e-5
        x_true1, _ = ekf_predict(inject_error(x, dx0), zero, gyro, accel, dt, noise)
        # Agreement up to terms of second order in dt (rotation of the bias errors over one
        # step) and in the error size.
        np.testing.assert_allclose(_error(x_true1, x_hat1), F @ dx0, atol=1e-5 * dt**2 * 5 + 1e-12)
    _, P1 = ekf_predict(x, np.eye(NE), gyro, accel, dt, noise)
    np.testing.assert_allclose(P1, F @ F.T, atol=1e-15)


def test_heading_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = quat_normalize(rng.normal(size=4))
        H = heading_jacobian(q)
        h = 1e-6
        fd = np.array(
            [
                (yaw_from_quat(retract(q, h * e)) - yaw_from_quat(retract(q, -h * e))) / (2 * h)
                for e in np.eye(3)
            ]
        )
        np.testing.assert_allclose(H, fd, atol=1e-6)


def _run_link_ekf(sensor_model, seed, duration=20.0, init_error=True):
    motion = ChainMotion(n_links=2)
    dt = 0.01
    truth = chain_truth(motion, np.arange(int(duration / dt) + 1) * dt)
    rng = np.random.default_rng(seed)
    sensors = Sensors(sensor_model, 2, rng)
    p0 = truth.p[0] + (np.array([2.0, -1.5, 1.0]) if init_error else 0.0)
    q0 = retract(truth.q[0], np.array([0.2, -0.1, 0.3])) if init_error else truth.q[0]
    ekfs = [LinkEkf(p0[i], truth.v[0, i] + 0.5, q0[i]) for i in range(2)]
    errors = []
    for k in range(truth.t.size - 1):
        gyro, accel = sensors.imu(truth, k)
        for i, e in enumerate(ekfs):
            e.predict(gyro[i], accel[i], dt)
        if (k + 1) % 10 == 0:
            pos, vel = sensors.gps(truth, k + 1)
            for i, e in enumerate(ekfs):
                e.update_position(pos[i])
                e.update_velocity(vel[i])
        att = sensors.attitude(truth, k + 1)
        for i, e in enumerate(ekfs):
            e.update_attitude(att[i])
            e.update_heading(float(yaw_from_quat(att[i])))
        errors.append(
            [
                max(np.linalg.norm(e.p_w_m - truth.p[k + 1, i]) for i, e in enumerate(ekfs)),
                max(quat_distance(e.q_wxyz, truth.q[k + 1, i]) for i, e in enumerate(ekfs)),
                max(np.linalg.norm(e.v_w_m_s - truth.v[k + 1, i]) for i, e in enumerate(ekfs)),
            ]
        )
    return ekfs, np.array(errors)


def test_noiseless_trajectory_converges_to_truth():
    ekfs, err = _run_link_ekf(SensorModel.noiseless(), seed=0)
    assert err[0, 0] > 1.0  # started far away
    final = err[-500:]  # last 5 s
    assert final[:, 0].max() < 2e-3  # m
    assert final[:, 1].max() < 2e-3  # quaternion distance
    assert final[:, 2].max() < 5e-3  # m/s
    for e in ekfs:
        assert e.rejected["pos"] == 0  # a converging filter does not gate good data
        np.testing.assert_array_equal(e.P, e.P.T)
        assert np.linalg.eigvalsh(e.P[:9, :9]).min() > 0


def test_noisy_filter_beats_raw_gps():
    model = SensorModel(pos_drift_amp_m=0.0, att_drift_amp_rad=0.0)
    _, err = _run_link_ekf(model, seed=3, init_error=False)
    # Raw GPS position error is ~sqrt(3 * 0.1) = 0.55 m; the filter averages it down.
    assert np.mean(err[500:, 0]) < 0.35


def test_functional_core_and_class_agree():
    rng = np.random.default_rng(4)
    cfg = EkfConfig(noise=EkfNoise(accel_bias_m2_s5=1e-4, gyro_bias_rad2_s3=1e-6), init_accel_bias_var=0.01,
                    init_gyro_bias_var=1e-4)
    p0, v0, q0 = rng.normal(size=3), rng.normal(size=3), quat_normalize(rng.normal(size=4))
    # the numpy path, bit for bit (the compiled one agrees to rounding: tests/unit/test_fast_paths.py)
    ekf = LinkEkf(p0, v0, q0, cfg, compiled=False)
    x, P = ekf_init(p0, v0, q0, cfg)
    for k in range(200):
        gyro, accel = rng.normal(scale=0.3, size=3), rng.normal(size=3) + [0, 0, 9.8]
        ekf.predict(gyro, accel, 0.002)
        x, P = ekf_predict(x, P, gyro, accel, 0.002, cfg.noise)
        if k % 20 == 0:
            z = x[X_P] + rng.normal(scale=0.3, size=3)
            ekf.update_position(z)
            x, P, _ = ekf_update_position(x, P, z, cfg.gps_pos_var_m2, cfg.gate_sigma)
            zv = x[X_V] + rng.normal(scale=0.3, size=3)
            ekf.update_velocity(zv)
            x, P, _ = ekf_update_velocity(x, P, zv, cfg.gps_vel_var_m2_s2, cfg.gate_sigma)
        if k % 5 == 0:
            zq = retract(x[X_Q], rng.normal(scale=0.05, size=3))
            ekf.update_attitude(zq)
            x, P, _ = ekf_update_attitude(x, P, zq, cfg.att_var_rad2, cfg.gate_sigma)
            ekf.update_heading(0.3)
            x, P, _ = ekf_update_heading(x, P, 0.3, cfg.heading_var_rad2, cfg.gate_sigma)
    np.testing.assert_array_equal(ekf.x, x)
    np.testing.assert_array_equal(ekf.P, P)
    p, v, q, w, P9 = ekf.sckf_view()
    np.testing.assert_array_equal(P9, P[:9, :9])
    np.testing.assert_array_equal(w, ekf.last_gyro_b_rad_s - x[X_BG])


def test_innovation_gate_rejects_outliers_and_keeps_state():
    ekf = LinkEkf(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]))
    x_before, P_before = ekf.x.copy(), ekf.P.copy()
    info = ekf.update_position(np.array([100.0, 0.0, 0.0]))
    assert not info.accepted and info.test_ratio > 1.0
    assert ekf.rejected["pos"] == 1 and ekf.accepted["pos"] == 0
    np.testing.assert_array_equal(ekf.x, x_before)
    np.testing.assert_array_equal(ekf.P, P_before)
    info = ekf.update_position(np.array([0.5, 0.0, 0.0]))
    assert info.accepted and ekf.accepted["pos"] == 1
    assert 0.0 < ekf.x[0] < 0.5


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda x, P: ekf_update_position(x, P, [np.nan, 0, 0], 0.1), "position"),
        (lambda x, P: ekf_update_velocity(x, P, [0, 0], 0.1), "velocity"),
        (lambda x, P: ekf_update_attitude(x, P, [1, 0, 0, np.inf], 0.1), "attitude"),
        (lambda x, P: ekf_update_heading(x, P, np.nan, 0.1), "heading"),
        (lambda x, P: ekf_predict(x, P, np.zeros(3), np.zeros(3), 0.0, EkfNoise()), "dt_s"),
    ],
)
def test_bad_measurements_raise_clear_errors(call, match):
    x, P = ekf_init(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]))
    with pytest.raises(ValueError, match=match):
        call(x, P)


def test_config_is_validated():
    with pytest.raises(ValueError, match="gps_pos_var_m2"):
        EkfConfig(gps_pos_var_m2=-1.0)
    with pytest.raises(ValueError, match="att_rad2_s"):
        EkfNoise(att_rad2_s=np.nan)


@pytest.mark.parametrize("block", [E_P, E_V, E_TH])
def test_block_update_equals_the_general_joseph_update(block):
    from link_firmware_sim.estimators.ekf import kalman_update as _update
    from link_firmware_sim.estimators.ekf import kalman_update_block as _update_block

    rng = np.random.default_rng(7)
    A = rng.normal(size=(NE, NE))
    P = A @ A.T * 0.01 + 0.01 * np.eye(NE)
    x, _ = ekf_init(rng.normal(size=3), rng.normal(size=3), quat_normalize(rng.normal(size=4)))
    H = np.zeros((3, NE))
    H[:, block] = np.eye(3)
    Rm = np.diag([0.1, 0.2, 0.3])
    r = rng.normal(scale=0.1, size=3)
    xa, Pa, ia = _update(x, P, r, H, Rm, 5.0)
    xb, Pb, ib = _update_block(x, P, r, block, Rm, 5.0)
    assert ia.accepted and ib.accepted and ia.test_ratio == pytest.approx(ib.test_ratio)
    np.testing.assert_allclose(xb, xa, atol=1e-14)
    np.testing.assert_allclose(Pb, Pa, atol=1e-14)


def test_tilt_and_heading_take_their_own_noise_and_the_class_agrees_with_the_functions():
    """``att_yaw_*``: the heading axis of the world-frame attitude error gets its own process
    density and reference variance; a reference that is off in tilt and heading by the same angle
    corrects the tilt far more when the heading is the noisier, as the functional update does."""
    from link_firmware_sim.estimators.ekf import E_TH, EkfConfig, EkfNoise, attitude_variance, ekf_update_attitude
    from companion.estimation.so3 import quat_from_rotvec

    noise = EkfNoise(att_rad2_s=1e-5, att_yaw_rad2_s=4e-4)
    d = noise.densities
    assert d[E_TH].tolist() == [1e-5, 1e-5, 4e-4] and EkfNoise().densities[E_TH].tolist() == [0.01] * 3
    cfg = EkfConfig(noise=noise, att_var_rad2=0.001, att_yaw_var_rad2=0.1, init_att_var_rad2=0.01)
    assert attitude_variance(cfg).tolist() == [0.001, 0.001, 0.1] and attitude_variance(EkfConfig()) == 0.04
    with pytest.raises(ValueError, match="att_yaw_var_rad2"):
        EkfConfig(att_yaw_var_rad2=-1.0)
    with pytest.raises(ValueError, match="att_yaw_rad2_s"):
        EkfNoise(att_yaw_rad2_s=float("nan"))
    ekf = LinkEkf(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), cfg)
    x0, P0 = ekf.x.copy(), ekf.P.copy()
    z = quat_from_rotvec(np.array([0.05, 0.0, 0.05]))  # 0.05 rad off in roll and in heading
    ekf.update_attitude(z)
    x1, P1, _ = ekf_update_attitude(x0, P0, z, np.array([0.001, 0.001, 0.1]), cfg.gate_sigma)
    np.testing.assert_allclose(ekf.x, x1, atol=1e-15)
    np.testing.assert_allclose(ekf.P, P1, atol=1e-15)
    assert P1[E_TH.start, E_TH.start] < 0.1 * P0[E_TH.start, E_TH.start] < P1[E_TH.start + 2, E_TH.start + 2]
    dtheta = attitude_error(ekf.q_wxyz, np.array([1.0, 0, 0, 0]))
    assert dtheta[0] > 0.04 and 0 < dtheta[2] < 0.01  # the tilt follows the reference, the heading barely

"""The slung load's pose filters (companion.load) and metrics: model Jacobians against
finite differences, eq. 8 against Newton-Euler in the world frame, EKF vs UKF, late images,
consistency and accuracy on the synthetic scenario (``sitl/load_synthetic.py``, no MuJoCo)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.estimation.so3 import attitude_error, quat_from_rotvec, quat_mul, quat_normalize, quat_to_rotmat, skew
from companion.load import estimate as le
from companion.load import filter as lf
from companion.load import kalman as lk
from companion.load import measurements as ms
from companion.load import metrics as lm
from companion.load import model as m
from companion.load import unfiltered as lu
from sitl.scenarios.slung_load.synthetic import SlungLoadSim, run_estimators, simulate_truth, summarize, synthesize

SIM = SlungLoadSim(duration_s=4.0, sim_dt_s=0.005)
PARAMS = SIM.load_params()


@pytest.fixture(scope="module")
def truth():
    return simulate_truth(SIM)


def _random_state(rng, n=3):
    x = np.zeros(m.nominal_dim(n))
    x[m.NOM_POS] = rng.normal(0.0, 0.3, 3)
    x[m.NOM_VEL] = rng.normal(0.0, 0.5, 3)
    x[m.NOM_QUAT] = quat_normalize(np.array([1.0, 0, 0, 0]) + rng.normal(0.0, 0.3, 4))
    x[m.NOM_OMEGA] = rng.normal(0.0, 0.5, 3)
    x[m.nominal_tension_slice(n)] = rng.uniform(2.0, 5.0, n)
    vehicles = x[m.NOM_POS] + np.array([[0.7, 0.0, 1.0], [-0.35, 0.6, 1.0], [-0.35, -0.6, 1.0]]) + rng.normal(0, 0.1, (3, 3))
    return x, vehicles


def _vehicles(pos, vel=None, stamp=0.0, sigma=0.02):
    n = len(pos)
    return m.VehicleStates(stamp, pos, np.zeros((n, 3)) if vel is None else vel,
                           np.broadcast_to(np.eye(3) * sigma**2, (n, 3, 3)))


# --- model --------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(4))
def test_dynamics_jacobian_matches_finite_differences(seed):
    rng = np.random.default_rng(seed)
    x, pv = _random_state(rng)
    A = m.error_dynamics_jacobian(x, pv, PARAMS)
    N, eps = m.error_dim(3), 1e-6
    acc0, alpha0 = m.load_accelerations(x, pv, PARAMS)
    for j in range(N):
        dx = np.zeros(N)
        dx[j] = eps
        acc_p, alpha_p = m.load_accelerations(m.boxplus(x, dx), pv, PARAMS)
        acc_m, alpha_m = m.load_accelerations(m.boxplus(x, -dx), pv, PARAMS)
        np.testing.assert_allclose(A[m.ERR_VEL, j], (acc_p - acc_m) / (2 * eps), atol=1e-6, err_msg=f"col {j}")
        np.testing.assert_allclose(A[m.ERR_OMEGA, j], (alpha_p - alpha_m) / (2 * eps), atol=1e-5, err_msg=f"col {j}")
    # the kinematic rows against one integration step: F = I + A h + (A h)^2/2 vs FD of the step
    h = 1e-3
    veh = _vehicles(pv)
    x1 = m.propagate_nominal(x, veh, 0.0, h, PARAMS, h)
    F = np.eye(N) + A * h + 0.5 * (A * h) @ (A * h)
    F_fd = np.empty((N, N))
    for j in range(N):
        dx = np.zeros(N)
        dx[j] = eps
        F_fd[:, j] = (m.boxminus(m.propagate_nominal(m.boxplus(x, dx), veh, 0.0, h, PARAMS, h), x1)
                      - m.boxminus(m.propagate_nominal(m.boxplus(x, -dx), veh, 0.0, h, PARAMS, h), x1)) / (2 * eps)
    np.testing.assert_allclose(F, F_fd, atol=5e-5)  # O(h^2 |A|) from the midpoint vs the start-point A


@pytest.mark.parametrize("seed", range(3))
def test_measurement_jacobians_match_finite_differences(seed):
    rng = np.random.default_rng(10 + seed)
    x, pv = _random_state(rng)
    N, eps = m.error_dim(3), 1e-6
    H, Ht = ms.vehicle_in_load_jacobian(x, pv[1])
    HL, U = ms.cable_length_jacobian(x, pv, PARAMS)
    for j in range(N):
        dx = np.zeros(N)
        dx[j] = eps
        xp, xm = m.boxplus(x, dx), m.boxplus(x, -dx)
        np.testing.assert_allclose(H[:, j], (ms.vehicle_in_load(xp, pv[1]) - ms.vehicle_in_load(xm, pv[1])) / (2 * eps),
                                   atol=1e-7)
        np.testing.assert_allclose(HL[:, j], (ms.cable_lengths(xp, pv, PARAMS) - ms.cable_lengths(xm, pv, PARAMS)) / (2 * eps),
                                   atol=1e-7)
    for j in range(3):  # w.r.t. the vehicle's position
        dt = np.zeros(3)
        dt[j] = eps
        np.testing.assert_allclose(Ht[:, j], (ms.vehicle_in_load(x, pv[1] + dt) - ms.vehicle_in_load(x, pv[1] - dt)) / (2 * eps),
                                   atol=1e-7)


def test_observation_from_pnp_inverts_marker_in_camera_and_its_covariance_is_first_order():
    rng = np.random.default_rng(3)
    x, pv = _random_state(rng)
    load = m.Pose3(x[m.NOM_POS], x[m.NOM_QUAT])
    vehicle = m.Pose3(pv[0], quat_from_rotvec(rng.normal(0, 0.2, 3)))
    cam, marker = SIM.camera_in_body(), m.Pose3([0.05, -0.02, 0.1], quat_from_rotvec([0.0, 0.0, 0.4]))
    R_cm, t_cm = ms.marker_in_camera(load, vehicle, cam, marker)
    cov6 = np.diag([1e-4, 2e-4, 5e-5, 1e-6, 2e-6, 4e-6])
    obs = ms.observation_from_pnp(0, 0.0, R_cm, t_cm, cov6, cam, marker)
    np.testing.assert_allclose(obs.vehicle_in_load_m, ms.vehicle_in_load(x, pv[0]), atol=1e-12)  # eq. 4
    # the load's attitude in the body frame, with the vehicle's attitude, is the load's in the world
    np.testing.assert_allclose(attitude_error(quat_mul(vehicle.q_wxyz, obs.load_in_body_q_wxyz), load.q_wxyz), 0.0,
                               atol=1e-12)
    # covariance: Monte Carlo of the exact map agrees with the first-order one, [dy; dphi] jointly
    e = rng.multivariate_normal(np.zeros(6), cov6, size=1000)
    samples = []
    for ei in e:
        o = ms.observation_from_pnp(0, 0.0, quat_to_rotmat(quat_from_rotvec(ei[:3])) @ R_cm, t_cm + ei[3:], cov6, cam,
                                    marker)
        samples.append(np.r_[o.vehicle_in_load_m, attitude_error(o.load_in_body_q_wxyz, obs.load_in_body_q_wxyz)])
    _assert_cov_close(np.cov(np.array(samples).T), obs.joint_cov, 0.15)  # 1000 samples: ~0.03 sampling error
    np.testing.assert_array_equal(obs.joint_cov[:3, :3], obs.cov_m2)


def _vehicles_with_attitude(rng, pv, stamp=0.0):
    n = len(pv)
    return m.VehicleStates(stamp, pv, rng.normal(0, 0.3, (n, 3)), np.broadcast_to(np.eye(3) * 4e-4, (n, 3, 3)),
                           quat_from_rotvec(rng.normal(0, 0.3, (n, 3))), np.broadcast_to(np.eye(3) * 1e-5, (n, 3, 3)),
                           rng.normal(0, 0.5, (n, 3)))


@pytest.mark.parametrize("seed", range(3))
def test_image_and_cable_measurement_jacobians_match_finite_differences(seed):
    """The assembled measurements (eq. 4 with the marker's attitude; the taut cables) against
    their own models: ``H`` is the derivative of ``h(x [+] dx)`` at ``dx = 0``, and the attitude
    rows are zero at the estimate."""
    rng = np.random.default_rng(20 + seed)
    x, pv = _random_state(rng)
    vehicles = _vehicles_with_attitude(rng, pv, stamp=-0.01)
    load = m.Pose3(x[m.NOM_POS], x[m.NOM_QUAT])
    R_cm, t_cm = ms.marker_in_camera(load, m.Pose3(pv[2], vehicles.q_wxyz[2]), SIM.camera_in_body(),
                                     SIM.marker_in_load())
    obs = ms.observation_from_pnp(2, 0.0, R_cm, t_cm, np.eye(6) * 1e-5, SIM.camera_in_body(), SIM.marker_in_load())
    image = ms.image_measurement(x, obs, vehicles)
    cables = ms.cable_measurement(x, vehicles, 0.0, PARAMS, 0.005, 0.0)
    assert image.dof == 6 and cables.dof == 3
    np.testing.assert_allclose(image.h(x)[3:], 0.0, atol=1e-15)
    N, eps = m.error_dim(3), 1e-6
    for meas in (image, cables):
        for j in range(N):
            dx = np.zeros(N)
            dx[j] = eps
            fd = (meas.h(m.boxplus(x, dx)) - meas.h(m.boxplus(x, -dx))) / (2 * eps)
            np.testing.assert_allclose(meas.H[:, j], fd, atol=1e-7)
        assert np.all(np.linalg.eigvalsh(meas.R) > 0)
    # without attitudes (or switched off): eq. 4 alone
    assert ms.image_measurement(x, obs, vehicles, attitude=False).dof == 3
    plain = m.VehicleStates(vehicles.stamp_s, vehicles.pos_w_m, vehicles.vel_w_m_s, vehicles.pos_cov_m2)
    assert ms.image_measurement(x, obs, plain).dof == 3


def test_vehicle_attitudes_are_carried_to_the_capture_time_and_validated():
    rng = np.random.default_rng(4)
    _, pv = _random_state(rng)
    v = _vehicles_with_attitude(rng, pv)
    dt = 0.02
    np.testing.assert_allclose(v.attitudes_at(dt), quat_mul(v.q_wxyz, quat_from_rotvec(v.rate_b_rad_s * dt)), atol=1e-12)
    np.testing.assert_allclose(v.attitudes_at(v.stamp_s), v.q_wxyz, atol=1e-15)
    with pytest.raises(ValueError, match="both or neither"):
        m.VehicleStates(0.0, pv, np.zeros((3, 3)), v.pos_cov_m2, v.q_wxyz)
    with pytest.raises(ValueError, match="unit"):
        m.VehicleStates(0.0, pv, np.zeros((3, 3)), v.pos_cov_m2, 2 * v.q_wxyz, v.att_cov_rad2)
    with pytest.raises(ValueError, match="no attitudes"):
        m.VehicleStates(0.0, pv, np.zeros((3, 3)), v.pos_cov_m2).attitudes_at(0.0)


@given(st.integers(0, 10_000))
@settings(max_examples=25, deadline=None)
def test_eq8_matches_newton_euler_in_the_world_frame(seed):
    """Eq. 8 in the body frame against the same physics written independently in the world frame."""
    rng = np.random.default_rng(seed)
    x, pv = _random_state(rng)
    acc, alpha = m.load_accelerations(x, pv, PARAMS)
    R = quat_to_rotmat(x[m.NOM_QUAT])
    T = x[m.nominal_tension_slice(3)]
    arms_w = PARAMS.attach_b_m @ R.T
    forces = np.array([Ti * (pv[i] - x[m.NOM_POS] - arms_w[i]) / np.linalg.norm(pv[i] - x[m.NOM_POS] - arms_w[i])
                       for i, Ti in enumerate(T)])
    np.testing.assert_allclose(acc, forces.sum(0) / PARAMS.mass_kg + [0, 0, -PARAMS.gravity_m_s2], atol=1e-12)
    J_w = R @ PARAMS.inertia_b_kg_m2 @ R.T
    w_w = R @ x[m.NOM_OMEGA]
    tau_w = sum(np.cross(a, f) for a, f in zip(arms_w, forces))
    wdot_w = np.linalg.solve(J_w, tau_w - np.cross(w_w, J_w @ w_w))
    np.testing.assert_allclose(R @ alpha, wdot_w, atol=1e-10)


def test_static_tensions_hold_the_load_at_rest(truth):
    x = truth.x[0].copy()
    x[m.NOM_VEL] = 0.0
    x[m.NOM_OMEGA] = 0.0
    x[13:] = m.static_tensions(x, truth.vehicle_pos_w_m[0], PARAMS)
    acc, alpha = m.load_accelerations(x, truth.vehicle_pos_w_m[0], PARAMS)
    np.testing.assert_allclose(acc, 0.0, atol=1e-9)
    np.testing.assert_allclose(alpha, 0.0, atol=1e-9)
    assert np.all(x[13:] > 0)


@given(st.integers(0, 10_000))
@settings(max_examples=30, deadline=None)
def test_boxplus_boxminus_roundtrip(seed):
    rng = np.random.default_rng(seed)
    x, _ = _random_state(rng)
    dx = rng.normal(0.0, 0.5, m.error_dim(3))
    np.testing.assert_allclose(m.boxminus(m.boxplus(x, dx), x), dx, atol=1e-10)


@pytest.mark.parametrize("bad", [
    dict(mass_kg=0.0), dict(inertia_b_kg_m2=[1.0, -1.0, 1.0]), dict(attach_b_m=np.zeros((3, 2))),
    dict(cable_length_m=[1.0, 1.0]), dict(cable_length_m=[1.0, 0.0, 1.0]),
])
def test_load_params_validate(bad):
    good = dict(mass_kg=1.0, inertia_b_kg_m2=[0.02, 0.02, 0.03], attach_b_m=PARAMS.attach_b_m, cable_length_m=[1.0] * 3)
    with pytest.raises(ValueError):
        m.LoadParams(**{**good, **bad})


@pytest.mark.parametrize("bad", [dict(accel_noise_m_s2_rthz=-1.0), dict(max_step_s=0.0), dict(gate_probability=0.0),
                                 dict(gate_probability=1.0), dict(cable_length_sigma_m=float("nan")),
                                 dict(cable_taut_fraction=1.0), dict(vehicle_bias_std_m=(0.01, -0.01)),
                                 dict(vehicle_bias_std_m=(0.01,))])
def test_filter_config_validates(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        le.LoadFilterConfig(**bad)


def test_gate_follows_the_measurements_degrees_of_freedom():
    cfg = le.LoadFilterConfig()
    assert cfg.gate_chi2(3) == pytest.approx(16.266, abs=1e-3) and cfg.gate_chi2(6) == pytest.approx(22.458, abs=1e-3)
    assert le.LoadFilterConfig(gate_probability=None).gate_chi2(6) is None


def test_the_vehicles_common_bias_adds_to_the_position_covariance_only(truth):
    est, _ = _start(truth, k=100)
    cfg = le.LoadFilterConfig(vehicle_bias_std_m=(0.03, 0.06))
    out = le.with_vehicle_bias(est, cfg)
    added = out.P - est.P
    np.testing.assert_allclose(added[m.ERR_POS, m.ERR_POS], np.diag([0.03**2, 0.03**2, 0.06**2]) / 3)
    added[m.ERR_POS, m.ERR_POS] = 0.0
    assert not added.any() and np.array_equal(out.x, est.x)
    assert le.with_vehicle_bias(est, le.LoadFilterConfig()) is est


# --- filters ------------------------------------------------------------------------------------


def _start(truth, k=0, sigma_pos=1e-4, sigma_att=1e-4):
    v = m.VehicleStates(float(truth.t_s[k]), truth.vehicle_pos_w_m[k], truth.vehicle_vel_w_m_s[k],
                        np.broadcast_to(np.eye(3) * 1e-4, (3, 3, 3)))
    est = le.initial_estimate(v.stamp_s, truth.x[k, m.NOM_POS], truth.x[k, m.NOM_QUAT], v, PARAMS,
                              pos_sigma_m=sigma_pos, vel_sigma_m_s=sigma_pos, att_sigma_rad=sigma_att,
                              omega_sigma_rad_s=sigma_att, tension_sigma_n=1e-3)
    return est, v


def _update(kind, est, obs, vehicles, cfg):
    """One image's update as the time line applies it."""
    meas = ms.image_measurement(est.x, obs, vehicles, attitude=cfg.marker_attitude)
    return lk.correct(kind, est, meas, cfg, cfg.gate_chi2(meas.dof))


def _assert_cov_close(Pa, Pb, tol):
    """Entries compared on the scale of their standard deviations: |Pa - Pb|_ij / sqrt(Pb_ii Pb_jj)."""
    s = np.sqrt(np.diag(Pb))
    assert np.max(np.abs(Pa - Pb) / np.outer(s, s)) < tol


def test_ekf_and_ukf_agree_when_nearly_linear(truth):
    cfg = le.LoadFilterConfig(max_step_s=0.02)
    est, v = _start(truth, k=200)
    pe = lk.ekf_predict(est, v, est.stamp_s + 0.02, PARAMS, cfg)
    pu = lk.ukf_predict(est, v, est.stamp_s + 0.02, PARAMS, cfg)
    np.testing.assert_allclose(m.boxminus(pu.x, pe.x), 0.0, atol=1e-7)  # second order in the 1e-4 spread
    _assert_cov_close(pu.P, pe.P, 1e-3)  # F from A at the start vs the midpoint step's exact Jacobian
    y = ms.vehicle_in_load(pe.x, v.positions_at(pe.stamp_s)[1]) + [0.01, -0.02, 0.005]
    obs = m.LoadObservation(1, pe.stamp_s, y, np.eye(3) * 4e-4)
    ue, nis_e, ok_e = _update("ekf", pe, obs, v, cfg)
    uu, nis_u, ok_u = _update("ukf", pu, obs, v, cfg)
    assert ok_e and ok_u
    assert nis_u == pytest.approx(nis_e, rel=1e-4)
    np.testing.assert_allclose(m.boxminus(uu.x, ue.x), 0.0, atol=1e-7)
    _assert_cov_close(uu.P, ue.P, 1e-3)
    # and they are different filters once the spread is not small (the report's were identical)
    wide, _ = _start(truth, k=200, sigma_pos=0.3, sigma_att=0.5)
    de = m.boxminus(lk.ukf_predict(wide, v, wide.stamp_s + 0.2, PARAMS, cfg).x,
                    lk.ekf_predict(wide, v, wide.stamp_s + 0.2, PARAMS, cfg).x)
    assert np.abs(de).max() > 1e-4


def test_the_ukf_correction_keeps_the_covariance_positive_far_from_linear():
    """Wide, correlated priors (metres, radians: sigma points whose attitudes pass pi) and the
    taut cables' lengths: ``P - K S K^T`` loses positive semi-definiteness in most of these
    draws (131 of 200), the update from the sigma points' own covariance in none."""
    cfg = le.LoadFilterConfig()
    sig = np.r_[[3.0] * 3, [1.0] * 3, [1.0] * 3, [1.0] * 3, [5.0] * 3]
    for seed in range(40):
        rng = np.random.default_rng(seed)
        x, pv = _random_state(rng)
        A = rng.normal(size=(15, 15))
        P = A @ np.diag(sig**2) @ A.T / 15 + np.diag(sig**2) * 1e-3
        meas = ms.cable_measurement(x, _vehicles(pv, sigma=1.0), 0.0, PARAMS, 0.005, 0.0)
        new = lk.ukf_correct(le.LoadEstimate(0.0, x, P), meas, cfg, None)[0]
        assert np.all(np.isfinite(new.P)) and np.linalg.eigvalsh(new.P).min() > -1e-9 * np.abs(new.P).max(), seed


def test_class_matches_the_functional_api_in_order(truth):
    cfg = le.LoadFilterConfig()
    meas = synthesize(truth, dataclasses.replace(SIM, latency_s=0.0, latency_jitter_s=0.0), seed=5)
    est, _ = _start(truth, sigma_pos=0.05, sigma_att=0.05)
    vehicles = meas.vehicles[:40]
    images = [o for _, o in meas.images if o.stamp_s < vehicles[-1].stamp_s]
    f = lf.LoadPoseFilter("ekf", PARAMS, cfg, dataclasses.replace(est, stamp_s=vehicles[0].stamp_s))
    def cables(est, v):  # after every accepted image: the taut cables' lengths
        meas = ms.cable_measurement(est.x, v, est.stamp_s, PARAMS, cfg.cable_length_sigma_m, cfg.cable_taut_fraction)
        return lk.ekf_correct(est, meas, None)[0]

    manual = f.estimate
    pending = list(images)
    f.push_vehicles(vehicles[0])
    for prev, v in zip(vehicles, vehicles[1:]):
        for o in [o for o in pending if o.stamp_s <= v.stamp_s]:
            pending.remove(o)
            f.push_observation(o)
            manual = lk.ekf_predict(manual, prev, o.stamp_s, PARAMS, cfg)
            # an image at a sample's stamp is applied with that sample (images first at equal stamps)
            sample = v if o.stamp_s >= v.stamp_s else prev
            manual, _, ok = _update("ekf", manual, o, sample, cfg)
            manual = cables(manual, sample) if ok else manual
        manual = lk.ekf_predict(manual, prev, v.stamp_s, PARAMS, cfg)
        got = f.push_vehicles(v)
    assert f.stats.late == 0 and f.stats.accepted > 20
    np.testing.assert_array_equal(got.x, manual.x)
    np.testing.assert_array_equal(got.P, manual.P)


def test_the_fixed_lag_estimate_is_the_estimate_of_that_time_with_the_late_images_in(truth):
    """In order, ``estimate_at`` a past sample's time is what the filter said then; with late
    images, it has them in; beyond the kept history it refuses."""
    cfg = le.LoadFilterConfig(vehicle_bias_std_m=(0.01, 0.015))
    meas = synthesize(truth, dataclasses.replace(SIM, latency_s=0.1, latency_jitter_s=0.0), seed=3)
    est, _ = _start(truth, sigma_pos=0.05, sigma_att=0.05)
    vehicles = meas.vehicles[:40]
    f = lf.LoadPoseFilter("ekf", PARAMS, cfg, dataclasses.replace(est, stamp_s=vehicles[0].stamp_s))
    said, arrivals = {}, list(meas.images)
    for v in vehicles:
        while arrivals and arrivals[0][0] <= v.stamp_s:
            f.push_observation(arrivals.pop(0)[1])
        said[v.stamp_s] = f.push_vehicles(v)
    t_last, t_past = vehicles[-1].stamp_s, vehicles[-11].stamp_s  # 0.2 s ago: the 0.1 s late images are in
    np.testing.assert_array_equal(f.estimate_at(t_last).x, said[t_last].x)
    np.testing.assert_array_equal(f.estimate_at(t_last).P, said[t_last].P)
    late = f.estimate_at(t_past)
    assert f.stats.late > 0 and not np.array_equal(late.x, said[t_past].x)
    err = lambda e, t: np.linalg.norm(e.pos_w_m - truth.x[truth.index(t), m.NOM_POS])  # noqa: E731
    assert np.trace(late.pos_cov_m2) < np.trace(said[t_past].pos_cov_m2)  # the images of that time are in
    assert np.all(np.diag(late.pos_cov_m2) >= np.array([0.01**2, 0.01**2, 0.015**2]) / 3)  # the vehicles' bias
    assert err(late, t_past) < 0.1
    with pytest.raises(ValueError, match="outside the kept history"):
        f.estimate_at(t_last + 0.1)
    with pytest.raises(ValueError, match="outside the kept history"):
        f.estimate_at(vehicles[0].stamp_s - 1.0)


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_late_images_give_the_in_order_result(truth, kind):
    sim = dataclasses.replace(SIM, latency_s=0.1, latency_jitter_s=0.15)
    meas = synthesize(truth, sim, seed=2)
    n_samples = 60 if kind == "ekf" else 30  # 1.2 s / 0.6 s
    meas = dataclasses.replace(meas, vehicles=meas.vehicles[:n_samples])
    cfg = le.LoadFilterConfig()
    kw = dict(kinds=(kind,), open_loop=False, unfiltered=False)
    late = run_estimators(truth, meas, sim, cfg, seed=2, **kw)
    in_order = run_estimators(truth, meas, sim, cfg, seed=2, deliver_in_order=True, **kw)
    assert late.stats[kind]["late"] > n_samples // 3 and in_order.stats[kind]["late"] == 0
    assert late.stats[kind]["replayed_events"] > n_samples
    assert late.stats[kind]["accepted"] == in_order.stats[kind]["accepted"] > n_samples // 3
    a, b = late.final[kind], in_order.final[kind]
    np.testing.assert_allclose(m.boxminus(a.x, b.x), 0.0, atol=1e-9)
    np.testing.assert_allclose(a.P, b.P, atol=1e-12)
    if kind == "ekf":  # images older than the kept history are dropped, not applied
        tight = run_estimators(truth, meas, sim, dataclasses.replace(cfg, lag_s=0.12), seed=2, **kw)
        assert tight.stats[kind]["dropped_too_late"] > 0


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_filters_beat_unfiltered_and_are_consistent(truth, seed):
    """Images delivered in order here (late delivery: the test above); EKF on two seeds, UKF on one."""
    cfg = le.LoadFilterConfig()
    meas = synthesize(truth, SIM, seed)
    run = run_estimators(truth, meas, SIM, cfg, seed, kinds=("ekf", "ukf") if seed == 0 else ("ekf",),
                         deliver_in_order=True)
    s = summarize(run)
    err = s["load_pose_err"]
    for kind in run.final:
        if kind == "open_loop":
            continue
        assert err[kind]["pos_rms_m"] < err["unfiltered"]["pos_rms_m"]
        assert err[kind]["att_rms_deg"] < err["unfiltered"]["att_rms_deg"]
        assert err[kind]["pos_rms_m"] < err["open_loop"]["pos_rms_m"]
        assert err[kind]["pos_rms_m"] < 0.05 and err[kind]["att_rms_deg"] < 3.0
        assert 6.0 / 3.0 < s["pose_nees_mean"][kind] < 6.0 * 1.5  # chi2(6) mean within bounds
        keep = run.t_s >= 1.0
        e = np.concatenate((run.pos_gt_w_m - run.pos_w_m[kind], attitude_error(run.q_gt_wxyz, run.q_wxyz[kind])),
                           axis=1)[keep]
        sig = np.sqrt(np.diagonal(run.P_pose[kind], axis1=1, axis2=2))[keep]
        assert np.mean(np.abs(e) < 3 * sig) > 0.97  # 99.7 % expected; some margin for the model mismatch


@pytest.mark.slow
def test_gate_rejects_pnp_spikes(truth):
    sim = dataclasses.replace(SIM, outlier_prob=0.08, outlier_m=1.0, duration_s=SIM.duration_s)
    meas = synthesize(truth, sim, seed=4)
    assert meas.outliers > 5
    kw = dict(kinds=("ekf",), open_loop=False, unfiltered=False, deliver_in_order=True)
    gated = run_estimators(truth, meas, sim, le.LoadFilterConfig(), 4, **kw)
    raw = run_estimators(truth, meas, sim, le.LoadFilterConfig(gate_probability=None), 4, **kw)
    assert gated.stats["ekf"]["rejected"] >= meas.outliers
    assert gated.stats["ekf"]["rejected"] < 2 * meas.outliers + 5
    e_g = summarize(gated)["load_pose_err"]["ekf"]
    e_r = summarize(raw)["load_pose_err"]["ekf"]
    assert e_g["pos_rms_m"] < 0.5 * e_r["pos_rms_m"]


# --- unfiltered solve and metrics ---------------------------------------------------------------


@given(st.integers(0, 10_000))
@settings(max_examples=30, deadline=None)
def test_solve_load_pose_recovers_the_pose(seed):
    rng = np.random.default_rng(seed)
    q = quat_normalize(rng.normal(size=4))
    p = rng.normal(0, 2, 3)
    y = rng.normal(0, 1, (4, 3))
    t = y @ quat_to_rotmat(q).T + p
    p_hat, q_hat = lu.solve_load_pose(y, t, rng.uniform(0.5, 2.0, 4))
    np.testing.assert_allclose(p_hat, p, atol=1e-8)
    assert lm.pose_error_series(p_hat[None], q_hat[None], p[None], q[None])[1][0] < 1e-5


def test_solve_load_pose_rejects_collinear_vehicles():
    y = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    with pytest.raises(ValueError, match="collinear"):
        lu.solve_load_pose(y, y + 1.0)
    with pytest.raises(ValueError, match="three"):
        lu.solve_load_pose(y[:2], y[:2])


def test_pose_error_series_and_load_pose_err():
    angles = np.radians([0.0, 10.0, 45.0, 120.0])
    q_gt = np.tile([1.0, 0, 0, 0], (4, 1))
    axis = np.array([0.6, 0.0, 0.8])
    q_est = quat_from_rotvec(angles[:, None] * axis)
    p_gt = np.zeros((4, 3))
    p_est = np.array([[0.0, 0, 0], [0.03, 0.04, 0], [np.nan] * 3, [0, 0, 1.0]])
    pos, att = lm.pose_error_series(p_est, q_est, p_gt, q_gt)
    np.testing.assert_allclose(pos[[0, 1, 3]], [0.0, 0.05, 1.0], atol=1e-12)
    np.testing.assert_allclose(att[[0, 1, 3]], [0.0, 10.0, 120.0], atol=1e-6)
    assert np.isnan(pos[2]) and np.isnan(att[2])
    # rotation matrices give the same as quaternions
    np.testing.assert_allclose(lm.pose_error_series(p_gt, quat_to_rotmat(q_est), p_gt, quat_to_rotmat(q_gt))[1],
                               np.degrees(angles), atol=1e-6)
    out = lm.load_pose_err({"ekf": (p_est, q_est), "ukf": (p_gt, q_gt)}, p_gt, q_gt)
    assert set(out) == {"ekf", "ukf"}
    assert out["ekf"]["n_samples"] == 3 and out["ekf"]["coverage"] == pytest.approx(0.75)
    assert out["ekf"]["pos_rms_m"] == pytest.approx(np.sqrt((0.05**2 + 1.0) / 3))
    assert out["ekf"]["att_rms_deg"] == pytest.approx(np.sqrt((100.0 + 120.0**2) / 3), rel=1e-6)
    assert out["ukf"]["pos_rms_m"] == 0.0


def test_pnp_error_table_counts_spikes_and_detections():
    rng = np.random.default_rng(0)
    R = quat_to_rotmat(quat_normalize(rng.normal(size=(20, 4))))
    t = rng.normal(0, 1, (20, 3)) + [0, 0, 2]
    t_est = t + 0.01
    t_est[[3, 7]] += [0, 0, 2.0]  # P3P-like spikes
    table = lm.pnp_error_table({
        "p3p": dict(t_est_m=t_est, R_est=R, t_gt_m=t, R_gt=R, detected=np.r_[np.ones(20), np.zeros(5)].astype(bool),
                    time_s=np.full(25, 0.004)),
        "ippe_square": dict(t_est_m=t + 0.01, R_est=R @ quat_to_rotmat(quat_from_rotvec([0, 0, np.radians(2.0)])),
                            t_gt_m=t, R_gt=R),
    })
    assert table["p3p"]["spikes"] == 2 and table["ippe_square"]["spikes"] == 0
    assert table["p3p"]["detection_rate"] == pytest.approx(0.8)
    assert table["p3p"]["time_ms"]["mean_ms"] == pytest.approx(4.0)
    assert table["ippe_square"]["att_rms_deg"] == pytest.approx(2.0, rel=1e-6)
    assert table["ippe_square"]["pos_rms_m"] == pytest.approx(0.01 * np.sqrt(3))


def test_pose_nees_is_chi2_for_samples_from_the_covariance():
    rng = np.random.default_rng(1)
    P = np.diag([1e-4, 4e-4, 1e-4, 1e-3, 1e-3, 4e-3])
    e = rng.multivariate_normal(np.zeros(6), P, size=4000)
    q_gt = quat_mul(quat_from_rotvec(e[:, 3:]), np.tile([1.0, 0, 0, 0], (4000, 1)))
    nees = lm.pose_nees(np.zeros((4000, 3)), np.tile([1.0, 0, 0, 0], (4000, 1)), np.broadcast_to(P, (4000, 6, 6)),
                        e[:, :3], q_gt)
    assert nees.mean() == pytest.approx(6.0, rel=0.05)


def test_skew_helper_is_the_repos():
    # the model reuses companion's SO(3) helpers; its cross product agrees with them
    a, b = np.random.default_rng(2).normal(size=(2, 5, 3))
    np.testing.assert_allclose(m.cross(a, b), np.einsum("nij,nj->ni", skew(a), b), atol=1e-14)


@given(st.floats(0.0, 60.0))
@settings(max_examples=25)
def test_the_camera_free_pose_is_the_rigging_below_the_vehicles_wherever_the_formation_is(t):
    """Vehicles standing in their formation at time t: the camera-free pose is the nominal hang
    below the formation's centre, yawed with it (the baseline the camera filters are measured against)."""
    from companion.load.config import LoadConfig
    from companion.load.formation import formation_state

    load = LoadConfig()
    f = formation_state(t, load.formation)
    got, want = load.camera_free_pose(f.pos_w_m), load.nominal_pose(f.center_w_m, f.phi_rad)
    assert np.allclose(got.pos_m, want.pos_m, atol=1e-9)
    assert np.linalg.norm(attitude_error(got.q_wxyz, want.q_wxyz)) < 1e-9


@given(st.integers(0, 10_000))
@settings(max_examples=25)
def test_the_whitened_pose_error_squared_is_the_nees(seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(4, 6, 6))
    P = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(6)
    p_gt, p_est = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    q_gt = quat_normalize(rng.normal(size=(4, 4)))
    q_est = np.array([quat_mul(quat_from_rotvec(0.1 * rng.normal(size=3)), q) for q in q_gt])
    w = lm.pose_error_whitened(p_est, q_est, P, p_gt, q_gt)
    e = np.concatenate((p_gt - p_est, attitude_error(q_gt, q_est)), axis=-1)
    assert np.allclose(np.sum(w * w, axis=-1), [ei @ np.linalg.solve(Pi, ei) for ei, Pi in zip(e, P)])
    assert np.allclose(lm.pose_nees(p_est, q_est, P, p_gt, q_gt), np.sum(w * w, axis=-1))


@pytest.mark.parametrize("restart", [None, "tracker"])
def test_an_estimate_that_is_no_longer_finite_restarts_the_filter_once_even_when_replayed(truth, monkeypatch, restart):
    """A prediction whose numbers overflowed (vehicle positions that contradict the cables, every
    image rejected) restarts the filter at that event from ``restart`` (default: at rest at the
    last finite pose), counted once: a late image's replay over it does not count it again."""
    cfg = le.LoadFilterConfig()
    meas = synthesize(truth, dataclasses.replace(SIM, latency_s=0.0, latency_jitter_s=0.0), seed=5)
    est, _ = _start(truth, sigma_pos=0.05, sigma_att=0.05)
    vehicles = meas.vehicles[:30]
    fresh = []

    def start_again(t_s, v):
        fresh.append(t_s)
        return le.initial_estimate(t_s, truth.x[0, m.NOM_POS], truth.x[0, m.NOM_QUAT], v, PARAMS)

    f = lf.LoadPoseFilter("ekf", PARAMS, cfg, dataclasses.replace(est, stamp_s=vehicles[0].stamp_s),
                          restart=start_again if restart else None)
    t_bad = vehicles[10].stamp_s
    predict = lf.predict

    def overflowing(kind, e, v, t_to, params, c):  # the prediction to t_bad overflows
        out = predict(kind, e, v, t_to, params, c)
        return dataclasses.replace(out, x=np.full_like(out.x, np.nan)) if t_to == t_bad else out

    monkeypatch.setattr(lf, "predict", overflowing)
    for v in vehicles[:20]:
        got = f.push_vehicles(v)
    assert f.stats.restarts == 1 and np.all(np.isfinite(got.x)) and np.all(np.isfinite(got.P))
    if restart:
        assert fresh == [t_bad]
    late = next(o for _, o in meas.images if vehicles[5].stamp_s < o.stamp_s < t_bad)
    f.push_observation(late)  # rolls back before t_bad and replays over it
    assert f.stats.late == 1 and f.stats.restarts == 1


def test_the_whitened_pose_error_is_nan_where_the_covariance_or_the_estimate_is_not_usable():
    """A diverged filter's samples (a covariance not finite or not positive definite, an estimate
    not finite) whiten to NaN; the others as before."""
    P = np.broadcast_to(np.diag([1e-4, 4e-4, 1e-4, 1e-3, 1e-3, 4e-3]), (4, 6, 6)).copy()
    P[1, 0, 0] = -1.0
    P[2, 3, 3] = np.inf
    pos, q = np.zeros((4, 3)), np.tile([1.0, 0, 0, 0], (4, 1))
    pos[3, 0] = np.nan
    gt = np.full((4, 3), 0.01)
    w = lm.pose_error_whitened(pos, q, P, gt, q)
    assert np.isnan(w[1:]).all() and np.allclose(w[0], [1.0, 0.5, 1.0, 0.0, 0.0, 0.0])


def test_an_image_refused_for_a_singular_innovation_is_counted_apart_from_the_mean_nis(truth, monkeypatch):
    """Its NIS is infinite: counted in ``singular`` and left out of the mean NIS, which stays
    finite through a late image's replay over it (an infinite sum less itself read NaN)."""
    cfg = le.LoadFilterConfig()
    meas = synthesize(truth, dataclasses.replace(SIM, latency_s=0.0, latency_jitter_s=0.0), seed=5)
    est, _ = _start(truth, sigma_pos=0.05, sigma_att=0.05)
    vehicles = meas.vehicles[:30]
    images = [o for _, o in meas.images if o.stamp_s < vehicles[19].stamp_s]
    bad = images[len(images) // 2]
    correct = lf.correct

    def singular_once(kind, e, mm, c, gate):
        if e.stamp_s == bad.stamp_s and mm.dof == 6:
            raise np.linalg.LinAlgError("Singular matrix")
        return correct(kind, e, mm, c, gate)

    monkeypatch.setattr(lf, "correct", singular_once)
    f = lf.LoadPoseFilter("ekf", PARAMS, cfg, dataclasses.replace(est, stamp_s=vehicles[0].stamp_s))
    pending = [o for o in images if o is not images[1]]
    for v in vehicles[:20]:
        for o in [o for o in pending if o.stamp_s <= v.stamp_s]:
            pending.remove(o)
            f.push_observation(o)
        f.push_vehicles(v)
    assert f.stats.singular == 1 and np.isfinite(f.stats.mean_nis)
    f.push_observation(images[1])  # late: the replay passes the singular image again
    assert f.stats.late == 1 and f.stats.singular == 1 and np.isfinite(f.stats.mean_nis)

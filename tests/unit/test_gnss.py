"""The receiver-like GNSS model (sitl.plant.sensors, profiles m8 and rtk): stationary Gauss-Markov
biases with their stds and time constants, a common mode shared by all links, seeded."""

import math

import numpy as np
import pytest

from sitl.plant.sensors import PROFILES, LinkSensors

#: the chain scenario the tests load with another sensor profile (``settings``, as ``--set`` does)
THREE_LINK = "configs/sitl/chain/three_link.toml"


def _run(profile, n, seconds, rate_hz=10.0, seed=0):
    sensors = LinkSensors(PROFILES[profile], n, np.random.default_rng(seed))
    p = np.zeros((n, 3))
    out_p, out_v = [], []
    for k in range(int(seconds * rate_hz)):
        pos, vel = sensors.gps(k / rate_hz, p, p)
        out_p.append(pos)
        out_v.append(vel)
    return np.array(out_p), np.array(out_v)


def test_m8_biases_have_their_stds_time_constants_and_common_mode():
    g = PROFILES["m8"].gps
    pos, vel = _run("m8", 300, 120.0)
    # over links and time: the per-link and common biases add in variance, the white noise too
    want_h = math.sqrt(g.bias_horizontal_std_m ** 2 + g.pos_horizontal_std_m ** 2)
    diff = pos - pos.mean(axis=1, keepdims=True)  # the common mode removed
    assert np.std(diff[..., 0]) == pytest.approx(want_h, rel=0.1)
    assert np.std(diff[..., 2]) == pytest.approx(math.sqrt(g.bias_vertical_std_m ** 2 + g.pos_vertical_std_m ** 2),
                                                 rel=0.1)
    common = pos.mean(axis=1)  # every link shares it: the per-link parts average out over 300 links
    assert np.std(common[:, 0]) > 0.3 and np.max(np.abs(np.diff(common[:, 0]))) < 0.3  # slow, not white
    # the per-link bias decorrelates over its time constant (lag of 60 s at 10 Hz)
    x = diff[..., 0]
    lag = int(g.bias_time_constant_s * 10)
    rho = np.mean(x[:-lag] * x[lag:]) / np.mean(x * x)
    assert rho == pytest.approx(math.exp(-1.0) * g.bias_horizontal_std_m ** 2 / want_h ** 2, abs=0.12)
    # velocity: white plus its own slow part, never the position bias's derivative
    assert np.std(vel[..., 0]) == pytest.approx(math.hypot(g.vel_std_m_s, g.vel_bias_std_m_s), rel=0.1)


def test_seeded_and_the_older_profiles_draw_as_before():
    a, _ = _run("m8", 3, 5.0, seed=4)
    b, _ = _run("m8", 3, 5.0, seed=4)
    np.testing.assert_array_equal(a, b)
    s = LinkSensors(PROFILES["outdoor"], 3, np.random.default_rng(0))
    assert s._gm == [] and s._vel_bias is None  # no extra draws: outdoor flights are unchanged
    rtk, _ = _run("rtk", 50, 30.0)
    assert np.std(rtk[..., 0]) < 0.02


def test_the_m8_tuning_reports_the_receivers_bias_it_cannot_see():
    """m8_ekf_config: outdoor's gains with the receiver's correlated velocity error in the GPS
    velocity variance, and the bias's variance (per-link plus common mode) added to the reported
    position block only; a scenario on that receiver (m8, m8_baro_mag: a barometer
    is referenced to the EKF's height, bias and all) gets it unless its [firmware.ekf] says otherwise."""
    from dataclasses import replace

    from link_firmware_sim.estimators import E_P, EkfConfig, LinkEkf, m8_ekf_config, outdoor_ekf_config
    from sitl.scenario import load_scenario

    g = PROFILES["m8"].gps
    cfg = m8_ekf_config()
    h = g.bias_horizontal_std_m ** 2 + g.common_horizontal_std_m ** 2
    v = g.bias_vertical_std_m ** 2 + g.common_vertical_std_m ** 2
    assert cfg.gps_bias_var_m2 == pytest.approx((h, v), rel=0.01)
    # outdoor's gains, with the receiver's correlated velocity error in its velocity variance
    assert replace(cfg, gps_bias_var_m2=(0.0, 0.0), gps_vel_var_m2_s2=0.0025) == outdoor_ekf_config()
    assert cfg.gps_vel_var_m2_s2 > g.vel_std_m_s ** 2 / 2 + 10 * g.vel_bias_std_m_s ** 2
    plain = LinkEkf(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), outdoor_ekf_config())
    biased = LinkEkf(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), cfg)
    P0, P1 = plain.sckf_view()[4], biased.sckf_view()[4]
    extra = P1 - P0
    assert np.allclose(extra[E_P, E_P], np.diag([cfg.gps_bias_var_m2[0]] * 2 + [cfg.gps_bias_var_m2[1]]))
    extra[E_P, E_P] = 0.0
    assert not extra.any() and np.array_equal(biased.P, plain.P)  # the filter itself is untouched
    with pytest.raises(ValueError, match="gps_bias_var_m2"):
        EkfConfig(gps_bias_var_m2=(-1.0, 0.0))
    m8 = load_scenario(THREE_LINK, settings={"sensors.profile": "m8"})
    assert m8.firmware.ekf == cfg
    baro_mag = load_scenario(THREE_LINK, settings={"sensors.profile": "m8_baro_mag"})
    assert baro_mag.firmware.ekf == cfg
    assert baro_mag.companion.gnss_common_pos_var_m2 == m8.companion.gnss_common_pos_var_m2
    # the companion takes the receivers' common mode out of the step (tests/unit/test_engine.py)
    assert m8.companion.gnss_common_pos_var_m2 == pytest.approx(
        (g.common_horizontal_std_m ** 2, g.common_vertical_std_m ** 2))
    assert load_scenario(THREE_LINK).firmware.ekf == outdoor_ekf_config()
    assert load_scenario(THREE_LINK).companion.gnss_common_pos_var_m2 == (0.0, 0.0)
    own = load_scenario(THREE_LINK, settings={"sensors.profile": "m8", "firmware.ekf.gps_pos_var_m2": 0.7})
    assert own.firmware.ekf == replace(outdoor_ekf_config(), gps_pos_var_m2=0.7)
    assert own.companion.gnss_common_pos_var_m2 == (0.0, 0.0)  # its links report no bias


@pytest.mark.parametrize("profile, firmware, bound_m", [
    ("outdoor", {}, 2.0), ("rtk", {}, 2.0), ("m8", {}, 5.0), ("m8_baro_mag", {}, 5.0),
    ("m8", {"firmware.correction_max_dp_m": 3.5}, 3.5),  # the scenario's own bound stays
])
def test_the_correction_bound_covers_the_receivers_own_bias(profile, firmware, bound_m):
    """A link's correction is its offset from where the chain puts it, its receiver's own bias
    among it: on metre-level receivers the firmware accepts three times that bias's RMS, rounded up
    (m8: 3 sqrt(2 0.8^2 + 1.2^2) = 4.95 m), where the default 2 m would refuse about one correction
    in ten of a three-link chain's (each link's bias less the chain's mean, drawn here)."""
    from sitl.scenario import load_scenario

    scenario = load_scenario(THREE_LINK, settings={"sensors.profile": profile, **firmware})
    assert scenario.firmware.correction_max_dp_m == bound_m
    if profile == "m8" and not firmware:
        g = PROFILES["m8"].gps
        std = np.array([g.bias_horizontal_std_m, g.bias_horizontal_std_m, g.bias_vertical_std_m])
        bias = np.random.default_rng(0).normal(size=(20000, 3, 3)) * std  # (draw, link, axis)
        offset = np.linalg.norm(bias - bias.mean(axis=1, keepdims=True), axis=-1)
        assert 0.05 < np.mean(offset > 2.0) < 0.15 and np.mean(offset > bound_m) < 1e-4


@pytest.mark.parametrize("profile, drift_m_s", [("outdoor", 1.0), ("m8", 1.0), ("m8_baro_mag", 1.0), ("paper", 1.5)])
def test_the_gps_consistency_threshold_a_profile_flies_passes_its_healthy_receiver_and_finds_a_drift(
        profile, drift_m_s):
    """The consistency test's threshold a scenario gets for its profile
    (sitl.scenario.PROFILE_GPS_DRIFT_MAX_M_S) passes every fix of a hovering healthy receiver and
    fails a drift of ``drift_m_s`` within 2.5 s; at the default 0.5 m/s the m8 and paper receivers
    fail in health (a false GPS glitch)."""
    from sitl.scenario import load_scenario
    from link_firmware_sim.estimators import GpsHealth, GpsHealthConfig

    config = load_scenario(THREE_LINK, settings={"sensors.profile": profile}).firmware.gps
    n, rate_hz = 3, 10.0
    pos, vel = _run(profile, n, 300.0, rate_hz)

    def drifts(cfg, pos):
        health = [GpsHealth(cfg, 0.0) for _ in range(n)]
        out = np.zeros(pos.shape[:2])
        for k in range(pos.shape[0]):
            for i in range(n):
                health[i].consistent(k / rate_hz, pos[k, i], vel[k, i])
                out[k, i] = health[i].drift_m_s
        return out

    healthy = drifts(config, pos)
    assert healthy.max() <= config.drift_max_m_s
    if profile != "outdoor":
        assert config.drift_max_m_s > GpsHealthConfig().drift_max_m_s
        assert (healthy > GpsHealthConfig().drift_max_m_s).any()
    ramp = pos[:400].copy()
    ramp[300:, :, 1] += drift_m_s * np.arange(1, 101)[:, None] / rate_hz  # north from 30 s
    found = drifts(config, ramp)[300:] > config.drift_max_m_s
    assert found.any(axis=0).all() and found.argmax(axis=0).max() / rate_hz < 2.5

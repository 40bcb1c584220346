"""Firmware GPS health (link_firmware_sim.estimators.gps_health) and its use in the firmware: faults on
rejected, drifting and missing fixes, recovery, the reset after the timeout without aiding, the
link-state flag, and the EKF's position reset."""

import numpy as np
import pytest

from companion.messages import STATE_FLAG_EKF_OK, STATE_FLAG_GPS_FAULT, Correction
from companion.skeleton.body import LinkInertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.estimators.ekf import E_P, E_V, X_P, EkfConfig, ekf_init, ekf_reset_position
from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware
from link_firmware_sim.estimators.gps_health import FULL_WINDOW, GpsHealth, GpsHealthConfig

GRAVITY_UP = np.array([0.0, 0.0, 9.80665])


def test_rejections_raise_a_fault_that_clears_after_recover_s():
    h = GpsHealth(GpsHealthConfig(recover_s=2.0))
    assert [e.kind for e in h.on_fix(0.1, True, aided=False)] == [] and not h.fault
    events = h.on_fix(0.2, False, aided=False)
    assert [e.kind for e in events] == ["fault"] and h.fault and "rejected" in events[0].text
    assert h.on_fix(0.3, False, aided=False) == []  # one fault, not one per fix
    t = 0.4
    while t < 2.35:  # accepted again, but not yet for 2 s
        assert h.on_fix(t, True, aided=False) == [] and h.fault
        t += 0.1
    assert [e.kind for e in h.on_fix(2.5, True, aided=False)] == ["recovered"] and not h.fault
    assert h.faults == 1 and h.rejected == 2 and h.fault_seconds(3.0) == pytest.approx(2.3)


def test_a_rejection_during_recovery_restarts_it():
    h = GpsHealth(GpsHealthConfig(recover_s=1.0))
    h.on_fix(0.0, False, aided=False)
    h.on_fix(0.5, True, aided=False)
    h.on_fix(1.0, False, aided=False)
    h.on_fix(1.1, True, aided=False)
    assert h.on_fix(2.0, True, aided=False) == [] and h.fault
    assert [e.kind for e in h.on_fix(2.1, True, aided=False)] == ["recovered"]


def test_no_fix_for_the_timeout_is_a_fault():
    h = GpsHealth(GpsHealthConfig(timeout_s=1.0, recover_s=0.5), t0_s=0.0)
    h.on_fix(0.1, True, aided=False)
    assert h.on_tick(1.0) == [] and not h.fault
    events = h.on_tick(1.1)
    assert [e.kind for e in events] == ["fault"] and "lost" in events[0].text and h.reason == "lost"
    assert h.on_tick(1.5) == []
    h.on_fix(3.0, True, aided=False)
    assert [e.kind for e in h.on_fix(3.5, True, aided=False)] == ["recovered"]


@pytest.mark.parametrize("aided", [False, True])
def test_reset_after_reset_s_only_without_other_aiding(aided):
    h = GpsHealth(GpsHealthConfig(reset_s=3.0))
    kinds = []
    for k in range(1, 80):  # 10 Hz fixes, all rejected, for 7.9 s
        kinds += [e.kind for e in h.on_fix(k * 0.1, False, aided=aided)]
    if aided:
        assert kinds == ["fault"] and h.resets == 0
    else:  # every 3 s of rejection (the run restarts at each reset)
        assert kinds == ["fault", "reset", "reset"] and h.resets == 2


def _fixes(rng, t, p0, ramp_m_s=0.0, std=0.15):
    pos = p0 + np.array([0.0, ramp_m_s * t, 0.0]) + rng.normal(0.0, std, 3)
    vel = rng.normal(0.0, 0.05, 3)
    return pos, vel


def test_consistency_catches_a_slow_ramp_and_passes_noise():
    rng = np.random.default_rng(3)
    h = GpsHealth(GpsHealthConfig(drift_max_m_s=0.5, drift_window_s=2.0))
    p0 = np.array([1.0, 2.0, 3.0])
    # 60 s of fixes with the outdoor profile's white noise and a 0.3 m/s drift: consistent
    for k in range(600):
        t = 0.1 * k
        pos, vel = _fixes(rng, t, p0)
        pos[0] += 0.5 * np.sin(2 * np.pi * 0.1 * t)  # the profile's fastest drift: 0.31 m/s peak
        assert h.consistent(t, pos, vel), (t, h.drift_m_s)
    # a 1 m/s ramp (the velocity says still): caught within 1.5 s
    h = GpsHealth(GpsHealthConfig(drift_max_m_s=0.5, drift_window_s=2.0))
    caught = None
    for k in range(100):
        t = 0.1 * k
        pos, vel = _fixes(rng, t, p0, ramp_m_s=1.0 if t >= 5.0 else 0.0)
        if t >= 5.0:
            pos[1] -= 5.0
        if not h.consistent(t, pos, vel):
            caught = t
            break
    assert caught is not None and 5.0 <= caught <= 6.5, caught


def _drift_from_scratch(fixes, t_s, window_s):
    """The consistency test's figure with the window rebuilt from the list of fixes (the
    specification of the buffers :class:`GpsHealth` keeps from fix to fix); ``None`` when the
    window is too short to test."""
    win = [f for f in fixes if not f[0] < t_s - window_s]
    if len(win) < 5 or win[-1][0] - win[0][0] < FULL_WINDOW * window_s:
        return None
    t = np.array([w[0] for w in win])
    p = np.stack([np.asarray(w[1], dtype=float)[:2] for w in win])
    v = np.stack([np.asarray(w[2], dtype=float)[:2] for w in win])
    track = np.zeros_like(p)
    np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t)[:, None], axis=0, out=track[1:])
    off = p - track
    tc = t - t.mean()
    return float(np.linalg.norm(tc @ (off - off.mean(axis=0)) / (tc @ tc)))


@pytest.mark.parametrize("rate_hz,window_s", [(10.0, 2.0), (5.0, 1.0), (50.0, 3.0), (20.0, 0.4)])
def test_the_kept_window_gives_the_figure_of_the_window_rebuilt_each_fix(rate_hz, window_s):
    """Bit for bit, over windows that fit the buffers and one that makes them grow (150 fixes),
    with jittered stamps, a gap longer than the window and a drifting fix stream."""
    rng = np.random.default_rng(11)
    h = GpsHealth(GpsHealthConfig(drift_max_m_s=0.5, drift_window_s=window_s))
    fixes, t, tested = [], 0.0, 0
    for k in range(400):
        t += (1.0 + 0.2 * rng.uniform(-1, 1)) / rate_hz + (4.0 * window_s if k == 200 else 0.0)
        pos, vel = rng.normal(size=3) + [0.3 * t, 0.0, 0.0], rng.normal(scale=0.1, size=3)
        fixes.append((t, pos, vel))
        ok = h.consistent(t, pos, vel)
        want = _drift_from_scratch(fixes, t, window_s)
        if want is None:
            assert ok
        else:
            tested += 1
            assert h.drift_m_s == want and ok == (want <= 0.5), (k, h.drift_m_s, want)
    assert tested > 150


@pytest.mark.parametrize("speed_m_s,ramp_s", [(9.0, 1.0), (5.0, 1.0), (8.8, 2.0)])
def test_hard_acceleration_with_a_consistent_gps_is_not_drift(speed_m_s, ramp_s):
    """A link going from rest to speed_m_s in ramp_s (smoothstep), its GPS exact: the positions
    follow the velocities, so no drift (a slope against the window's mean velocity read 0.70 /
    0.39 / 0.39 m/s here, the first over the 0.5 m/s limit: a false fault)."""
    h = GpsHealth(GpsHealthConfig(drift_max_m_s=0.5, drift_window_s=2.0))
    worst = 0.0
    for k in range(60):
        t = 0.1 * k
        s = min(max((t - 1.0) / ramp_s, 0.0), 1.0)
        vel = speed_m_s * s * s * (3.0 - 2.0 * s)
        dist = speed_m_s * (ramp_s * (s**3 - 0.5 * s**4) + max(t - 1.0 - ramp_s, 0.0))  # its integral
        assert h.consistent(t, [dist, 0.0, 0.0], [vel, 0.0, 0.0]), (t, h.drift_m_s)
        worst = max(worst, h.drift_m_s)
    assert worst < 0.05 * speed_m_s / ramp_s, worst  # the trapezoids' error: 0.1 s steps


def test_position_reset_is_a_clean_discontinuity():
    cfg = EkfConfig()
    x, P = ekf_init(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), cfg)
    B = np.random.default_rng(0).normal(size=P.shape)
    P = P + 0.01 * B @ B.T  # positive definite, correlations everywhere
    x2, P2 = ekf_reset_position(x, P, [5.0, -1.0, 2.0], 0.04)
    np.testing.assert_allclose(x2[X_P], [5.0, -1.0, 2.0])
    np.testing.assert_allclose(P2[E_P, E_P], 0.04 * np.eye(3))
    assert np.all(P2[E_P, E_V] == 0) and np.all(P2[E_V, E_P] == 0)
    np.testing.assert_array_equal(P2[E_V, E_V], P[E_V, E_V])
    np.testing.assert_allclose(P2, P2.T)
    assert np.all(np.linalg.eigvalsh(P2) > 0)  # the Schur complement of a PD matrix stays PD


def _hovering_firmware(config: FirmwareConfig = FirmwareConfig()):
    fw = LinkFirmware(1, config, LinkInertia(1.8, (0.04, 0.16, 0.16)), RotorGeometry.odar())
    q = np.array([1.0, 0.0, 0.0, 0.0])
    fw.initialize(0.0, np.zeros(3), np.zeros(3), q)
    return fw, q


def _fly(fw, q, t0, t1, rng, glitch=lambda t: np.zeros(3), fix=lambda t: True, correction=None):
    """Still link, 500 Hz IMU, 10 Hz GPS (with ``glitch`` added), 50 Hz attitude."""
    k0, k1 = int(round(t0 * 500)), int(round(t1 * 500))
    for k in range(k0, k1):
        t = k / 500
        if k % 50 == 0 and fix(t):
            fw.on_gps(t, rng.normal(0, 0.1, 3) + glitch(t), rng.normal(0, 0.03, 3))
        if k % 10 == 0:
            fw.on_attitude(t, q)
        if correction is not None and k % 25 == 0:
            fw.on_correction(t, correction(t))
        fw.on_imu(t, np.zeros(3), GRAVITY_UP)


def test_firmware_flags_a_step_glitch_keeps_its_estimate_and_reports_it():
    rng = np.random.default_rng(0)
    fw, q = _hovering_firmware()
    _fly(fw, q, 0.0, 5.0, rng)
    assert fw.flags(5.0) & STATE_FLAG_GPS_FAULT == 0 and not fw.events
    step = np.array([10.0, 0.0, 0.0])
    _fly(fw, q, 5.0, 8.0, rng, glitch=lambda t: step)
    assert fw.flags(8.0) & STATE_FLAG_GPS_FAULT and fw.flags(8.0) & STATE_FLAG_EKF_OK
    assert [e.kind for e in fw.events] == ["fault"]
    assert np.linalg.norm(fw.ekf.p_w_m) < 0.3  # no position fused during the fault
    fw.events.clear()
    _fly(fw, q, 8.0, 14.0, rng)  # the glitch is gone: back after the window and recover_s
    assert [e.kind for e in fw.events] == ["recovered"] and fw.flags(14.0) & STATE_FLAG_GPS_FAULT == 0
    assert fw.gps_health.resets == 0


def test_firmware_resets_to_gps_after_the_timeout_only_when_nothing_else_aids_it():
    cfg = FirmwareConfig(gps=GpsHealthConfig(reset_s=3.0))
    step = np.array([0.0, 8.0, 0.0])
    rng = np.random.default_rng(1)
    fw, q = _hovering_firmware(cfg)
    _fly(fw, q, 0.0, 3.0, rng)
    _fly(fw, q, 3.0, 8.0, rng, glitch=lambda t: step)
    assert [e.kind for e in fw.events] == ["fault", "reset"] and "jumped 8" in fw.events[1].text
    assert np.linalg.norm(fw.ekf.p_w_m - step) < 0.5 and fw.ekf.resets == 1
    # the same with the companion's corrections arriving: no reset
    rng = np.random.default_rng(1)
    fw, q = _hovering_firmware(cfg)
    corr = lambda t: Correction(1, t, np.zeros(3), np.zeros(3), np.zeros(3), seq=1)
    _fly(fw, q, 0.0, 3.0, rng, correction=corr)
    _fly(fw, q, 3.0, 8.0, rng, glitch=lambda t: step, correction=corr)
    assert [e.kind for e in fw.events] == ["fault"] and fw.ekf.resets == 0


def test_firmware_outage_is_a_fault():
    rng = np.random.default_rng(2)
    fw, q = _hovering_firmware()
    _fly(fw, q, 0.0, 2.0, rng)
    _fly(fw, q, 2.0, 4.0, rng, fix=lambda t: False)
    assert [e.kind for e in fw.events] == ["fault"] and "lost" in fw.events[0].text
    assert fw.flags(4.0) & STATE_FLAG_GPS_FAULT


def test_a_fix_that_repeats_bit_for_bit_in_flight_is_stuck():
    """GpsHealth.repeats: a fix repeated exactly for stuck_s (0.5 s) in flight is stuck until one
    differs; on the ground the watch starts afresh (a still link of a noiseless simulation repeats
    its fixes honestly); stuck_s 0 never finds one."""
    p, v = np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.0, 0.0])
    h = GpsHealth(GpsHealthConfig(stuck_s=0.5))
    found = [h.repeats(k / 10, p, v, in_flight=True) for k in range(10)]
    assert found == [False] * 5 + [True] * 5
    assert not h.repeats(1.0, p + 1e-9, v, in_flight=True)  # a hair apart: a live receiver
    assert h.report(1.0)["stuck"]["episodes"] == 1
    ground = GpsHealth(GpsHealthConfig(stuck_s=0.5))
    assert not any(ground.repeats(k / 10, p, v, in_flight=False) for k in range(20))
    off = GpsHealth(GpsHealthConfig(stuck_s=0.0))
    assert not any(off.repeats(k / 10, p, v, in_flight=True) for k in range(20))
    with pytest.raises(ValueError):
        GpsHealthConfig(stuck_s=-1.0)


@pytest.mark.parametrize("case", ["stuck", "live", "on_ground", "check_off"])
def test_firmware_fuses_nothing_of_a_stuck_fix(case):
    """A still link whose receiver repeats one fix (0.3 m off, as a held noisy fix is) from 1 s to
    4 s: in flight the firmware takes it as stuck after SKL_GPS_STUCK (one "fix stuck" fault), fuses
    neither its position nor its velocity, and recovers once live fixes are back. With live fixes,
    on the ground (not armed), or with the check off, no fault and the fixes fused."""
    cfg = FirmwareConfig()
    if case == "check_off":
        cfg = FirmwareConfig(gps=GpsHealthConfig(stuck_s=0.0))
    fw = LinkFirmware(1, cfg, LinkInertia(1.8, (0.04, 0.16, 0.16)), RotorGeometry.odar())
    q = np.array([1.0, 0.0, 0.0, 0.0])
    fw.initialize(0.0, np.zeros(3), np.array([0.0, 0.0, 1.0]), q)  # armed while moving: in flight
    if case != "on_ground":
        assert fw.arm(0.0) and fw.airborne
    rng = np.random.default_rng(3)
    held = (np.array([0.3, 0.0, 0.0]), np.zeros(3))
    fused = {}
    for k in range(1, 8 * 500):
        t = k / 500
        if k % 50 == 0:
            if case != "live" and 1.0 <= t < 4.0:
                fw.on_gps(t, *held)
            else:
                fw.on_gps(t, rng.normal(0, 0.02, 3), rng.normal(0, 0.02, 3))
            if t in (1.5, 4.0):
                fused[t] = (fw.ekf.accepted["pos"] + fw.ekf.rejected["pos"], fw.ekf.accepted["vel"])
        if k % 10 == 0:
            fw.on_attitude(t, q)
        fw.on_imu(t, np.zeros(3), GRAVITY_UP)
    faults = [e.text for e in fw.events if e.kind == "fault"]
    if case == "stuck":
        assert faults == ["GPS glitch: fix stuck, repeats itself"] and not fw.gps_health.fault
        assert fused[4.0] == fused[1.5]  # neither position nor velocity of the stuck fixes
        assert fw.gps_report(8.0)["stuck"]["episodes"] == 1
    else:
        assert faults == [] and fused[4.0][1] - fused[1.5][1] >= 25

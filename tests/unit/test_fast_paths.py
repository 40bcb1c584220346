"""Oracle tests: the compiled kernels (link_firmware_sim.kernels, sitl.kernels.rotor) against the numpy
specification on random inputs (seeded), agreeing to 1e-12 (the companion's:
``tests/unit/test_companion_kernels.py``).

Without numba (an onboard install) the compiled path is the numpy one and these tests are skipped;
with it, the first run compiles the kernels (about 20 s on a 2-core VM, then cached on disk).
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from companion.estimation.so3 import quat_normalize
from companion.messages import PoseTarget
from companion.skeleton.body import LinkInertia
from companion.skeleton.rotors import RotorGeometry, RotorParams
from companion.kernels.jit import ENABLED
from link_firmware_sim import fused as fused_ticks
from link_firmware_sim.allocation import AllocationParams, Allocator
from link_firmware_sim.controllers.impedance import (ControlIntegrals, ImpedanceController, ImpedanceGains,
                                                     impedance_control)
from link_firmware_sim.estimators import ekf as E
from link_firmware_sim.estimators import link_ekf
from link_firmware_sim.fused import HilBuffers
from link_firmware_sim.kernels import hil_records
from link_firmware_sim.kernels.layouts import IO_AHRS_ACCEPTED, IO_AHRS_Q
from sitl.plant.rotor import RotorBank
from sitl.plant.sensors import PROFILES, LinkSensors

from .firmware_segments import flight_events

pytestmark = pytest.mark.skipif(not ENABLED, reason="numba not installed (or SKELETON_JIT=0)")

TOL = dict(rtol=1e-12, atol=1e-12)
N_CASES = 40


def _spd(rng, n: int) -> np.ndarray:
    A = rng.normal(size=(n, n)) * rng.uniform(0.01, 1.0)
    return A @ A.T + rng.uniform(1e-4, 0.1) * np.eye(n)


def _state(rng, baro: bool) -> tuple[np.ndarray, np.ndarray]:
    x = np.concatenate((rng.normal(size=3) * 5, rng.normal(size=3), quat_normalize(rng.normal(size=4)),
                        rng.normal(size=3) * 0.1, rng.normal(size=3) * 0.01))
    if baro:
        x = np.concatenate((x, [rng.normal()]))
    return x, _spd(rng, E.NE_BARO if baro else E.NE)


def _noise(rng) -> E.EkfNoise:
    return E.EkfNoise(*rng.uniform(0, 0.1, size=5), att_yaw_rad2_s=rng.uniform(0, 0.1), baro_bias_m2_s=rng.uniform(0, 1e-3))


def _same_update(a, b) -> None:
    (xa, Pa, ia), (xb, Pb, ib) = a, b
    assert ia.accepted == ib.accepted
    np.testing.assert_allclose(ia.test_ratio, ib.test_ratio, **TOL)
    np.testing.assert_allclose(xa, xb, **TOL)
    np.testing.assert_allclose(Pa, Pb, **TOL)
    np.testing.assert_array_equal(Pb, Pb.T)  # symmetric, exactly


@pytest.mark.parametrize("baro", [False, True])
def test_predict_matches_numpy(baro):
    rng = np.random.default_rng(11 + baro)
    for _ in range(N_CASES):
        x, P = _state(rng, baro)
        gyro, accel = rng.normal(size=3) * rng.choice([1e-9, 1.0]), rng.normal(size=3) * 5
        dt, noise = rng.uniform(1e-4, 0.02), _noise(rng)
        xa, Pa = E.ekf_predict(x, P, gyro, accel, dt, noise)
        xb, Pb = link_ekf.predict(x, P, gyro, accel, dt, E.EkfConfig(noise=noise), compiled=True)
        np.testing.assert_allclose(xb, xa, **TOL)
        np.testing.assert_allclose(Pb, Pa, **TOL)
        np.testing.assert_array_equal(Pb, Pb.T)
    with pytest.raises(ValueError, match="dt_s"):
        link_ekf.predict(x, P, gyro, accel, 0.0, E.EkfConfig(noise=noise), compiled=True)


@pytest.mark.parametrize("kind", ["position", "velocity", "attitude", "heading", "baro", "mag"])
def test_updates_match_numpy(kind):
    rng = np.random.default_rng(["position", "velocity", "attitude", "heading", "baro", "mag"].index(kind))
    accepted = rejected = 0
    for _ in range(N_CASES):
        x, P = _state(rng, baro=kind == "baro")
        gate = rng.choice([0.5, 5.0])  # a tight gate rejects some
        if kind == "position":
            m = E.position_measurement(x, x[E.X_P] + rng.normal(size=3), rng.uniform(0.01, 1.0))
        elif kind == "velocity":
            m = E.velocity_measurement(x, x[E.X_V] + rng.normal(size=3), rng.uniform(0.01, 1.0, size=3))
        elif kind == "attitude":
            m = E.attitude_measurement(x, quat_normalize(x[E.X_Q] + 0.5 * rng.normal(size=4)), rng.uniform(1e-3, 0.1))
        elif kind == "heading":
            m = E.heading_measurement(x, rng.uniform(-np.pi, np.pi), rng.uniform(1e-3, 0.1))
        elif kind == "baro":
            m = E.baro_measurement(x, x[2] + x[16] + rng.normal(), rng.uniform(1e-3, 0.1), rng.choice([0.0, 1.0]))
        else:
            m = E.mag_heading_measurement(x, rng.normal(size=3), rng.uniform(-0.3, 0.3), rng.uniform(1e-3, 0.1))
        ref = E.kalman_apply(x, P, m, gate)  # the specification
        _same_update(ref, link_ekf.fuse(x, P, m, gate, compiled=True))
        accepted += ref[2].accepted
        rejected += not ref[2].accepted
    assert accepted and rejected  # both branches compared


def test_link_ekf_class_agrees_with_functions():
    """The thin class with the compiled kernels against the functional numpy core over a sequence."""
    rng = np.random.default_rng(5)
    cfg = E.EkfConfig(noise=_noise(rng))
    q0 = quat_normalize(rng.normal(size=4))
    fast = link_ekf.LinkEkf(np.zeros(3), np.zeros(3), q0, cfg, compiled=True)
    x, P = E.ekf_init(np.zeros(3), np.zeros(3), q0, cfg)
    for k in range(60):
        g, a = rng.normal(size=3) * 0.1, rng.normal(size=3) + [0, 0, 9.8]
        fast.predict(g, a, 0.002)
        x, P = E.ekf_predict(x, P, g, a, 0.002, cfg.noise)
        if k % 5 == 0:
            z = rng.normal(size=3) * 0.3
            fast.update_position(z)
            x, P, _ = E.ekf_update_position(x, P, z, cfg.gps_pos_var_m2, cfg.gate_sigma)
        if k % 7 == 0:
            m = np.array([0.2, 0.0, -0.4]) + 0.01 * rng.normal(size=3)
            fast.update_mag(m)
            x, P, _ = E.ekf_update_mag_heading(x, P, m, cfg.mag_declination_rad, cfg.mag_heading_var_rad2,
                                               cfg.gate_sigma)
    np.testing.assert_allclose(fast.x, x, **TOL)
    np.testing.assert_allclose(fast.P, P, **TOL)


def _target(rng) -> PoseTarget:
    return PoseTarget(rng.normal(size=3), quat_normalize(rng.normal(size=4)), *(rng.normal(size=(6, 3))))


def test_impedance_control_matches_numpy():
    rng = np.random.default_rng(7)
    for _ in range(N_CASES):
        gains = ImpedanceGains(tuple(rng.uniform(0, 20, 3)), tuple(rng.uniform(0, 10, 3)), tuple(rng.uniform(0, 2, 3)),
                               *rng.uniform(0, 5, 4), pos_integral_limit_ms=rng.uniform(0.01, 2),
                               att_integral_limit_rad=rng.uniform(0.01, 1))
        inertia = LinkInertia(rng.uniform(0.5, 3), tuple(rng.uniform(0.01, 0.5, 3)))
        integ = ControlIntegrals(rng.normal(size=3), rng.normal(size=3))  # beyond the limits too: clamps
        args = (rng.normal(size=3), rng.normal(size=3), quat_normalize(rng.normal(size=4)), rng.normal(size=3),
                _target(rng), gains, inertia, integ, rng.uniform(1e-4, 0.02))
        Ua, ia = impedance_control(*args)
        ctrl = ImpedanceController(gains, inertia, compiled=True)
        ctrl.integrals = integ
        Ub, ib = ctrl(*args[:5], args[-1]), ctrl.integrals
        np.testing.assert_allclose(Ub, Ua, **TOL)
        np.testing.assert_allclose(ib.pos, ia.pos, **TOL)
        np.testing.assert_allclose(ib.att, ia.att, **TOL)


@pytest.mark.parametrize("removed", [None, (2, 0.0), (5, 0.8)])
@pytest.mark.parametrize("scale_to_limit", [True, False])
@pytest.mark.parametrize("selective", [True, False])
def test_allocation_matches_numpy(selective, scale_to_limit, removed):
    """A sequence of wrenches (the modulation's state carries over), many near a rotor's zero,
    every seventh one beyond the rotors' limit (scaled to it, or clipped), with the weight of a
    tilted link kept whole (and every third time nothing or a wrench beyond the rotors kept);
    with every rotor, and with one left out as failed at its test thrust (``removed``)."""
    rng = np.random.default_rng(3)
    geometry = RotorGeometry.odar()
    params = AllocationParams(selective_mapping=selective, scale_to_limit=scale_to_limit)
    ref, fast = Allocator(geometry, params, compiled=False), Allocator(geometry, params, compiled=True)
    if removed is not None:
        assert ref.remove_rotor(*removed) and fast.remove_rotor(*removed)
    near = saturated = 0
    U = np.array([0.0, 0.0, 17.6, 0.0, 0.0, 0.0])
    for k in range(300):
        U = U + rng.normal(size=6) * [0.5, 0.5, 0.5, 0.05, 0.05, 0.05]
        V = U * rng.uniform(1.5, 4.0) if k % 7 == 6 else U
        tilt = rng.normal(size=3) * 0.3
        keep = (None, np.concatenate((17.6 * tilt / max(1.0, np.linalg.norm(tilt)) + [0, 0, 17.6], np.zeros(3))),
                np.array([90.0, 0, 0, 0, 0, 0]))[k % 3]
        a, b = ref.allocate(V, keep), fast.allocate(V, keep)
        assert (fast.scale, fast.saturated) == (b.scale, b.saturated)
        for name in ("command_n", "lambda_o", "lambda_alpha", "lambda_beta", "lambda_gamma", "wrench"):
            np.testing.assert_allclose(getattr(b, name), getattr(a, name), **TOL, err_msg=name)
        np.testing.assert_allclose(b.e, a.e, **TOL)
        np.testing.assert_allclose(b.scale, a.scale, **TOL)
        assert (b.near_zero, b.saturated) == (a.near_zero, a.saturated)
        np.testing.assert_allclose(fast.xi_pre, ref.xi_pre, **TOL)
        near += a.near_zero != (-1, -1)
        saturated += a.saturated
        if removed is not None:
            assert a.command_n[removed[0]] == removed[1]
    if selective:
        assert near > 10  # the selective mapping's branches were exercised
    assert saturated > 20  # and the limit's
    np.testing.assert_array_equal(fast.command(U), fast.allocate(U).command_n)
    with pytest.raises(ValueError):
        fast.command(np.full(6, np.nan))
    with pytest.raises(ValueError, match="keep"):
        fast.command(U, np.full(6, np.nan))


@pytest.mark.parametrize("min_thrust_n,dwell_s", [(0.0, 0.0), (0.35, 0.25)])
def test_rotor_bank_matches_numpy(min_thrust_n, dwell_s):
    """The rotor/ESC model through reversals, stops and restarts."""
    rng = np.random.default_rng(9)
    params = RotorParams(min_thrust_n=min_thrust_n, restart_dwell_s=dwell_s)
    ref, fast = RotorBank(16, params, compiled=False), RotorBank(16, params, compiled=True)
    signs = rng.choice([-1.0, 1.0], size=16)
    for k in range(2400):
        if k % 2 == 0:  # a firmware tick: a new command, reversing every 0.6 s
            cmd = rng.normal(size=16) * 0.3 + (2.0 if k % 1200 < 600 else -2.0) * signs
            ref.set_command(cmd)
            fast.set_command(cmd)
            assert fast._steady == ref._steady
        a, b = ref.step(0.001), fast.step(0.001)
        np.testing.assert_allclose(b, a, **TOL)
    np.testing.assert_array_equal(fast.zero_crossings, ref.zero_crossings)
    assert ref.zero_crossings.sum() > 0


@pytest.mark.parametrize("profile,n_links", [("outdoor", 3), ("m8", 7), ("paper", 1)])
def test_imu_kernel_matches_numpy_bit_for_bit(profile, n_links):
    """LinkSensors.imu compiled against its numpy code: the same draws, the same bias walks and
    samples, bit for bit, over many ticks and two tick lengths."""
    rng = np.random.default_rng(4)
    ref, fast = (LinkSensors(PROFILES[profile], n_links, np.random.default_rng(11), compiled=c) for c in (False, True))
    np.testing.assert_array_equal(fast.gyro_bias, ref.gyro_bias)
    for k in range(400):
        force, omega = rng.normal(size=(n_links, 3)) * 9.8, rng.normal(size=(n_links, 3))
        dt = 0.002 if k % 3 else 0.004
        (g0, a0), (g1, a1) = ref.imu(force, omega, dt), fast.imu(force, omega, dt)
        np.testing.assert_array_equal(g1, g0)
        np.testing.assert_array_equal(a1, a0)
    np.testing.assert_array_equal(fast.accel_bias, ref.accel_bias)
    np.testing.assert_array_equal(fast.gyro_bias, ref.gyro_bias)
    start = LinkSensors(PROFILES[profile], n_links, np.random.default_rng(11))
    assert np.abs(fast.gyro_bias - start.gyro_bias).max() > 0  # (the walks moved the biases)


def test_attitude_update_kernel_matches_numpy():
    """LinkEkf.update_attitude's compiled path (measurement model and update in one kernel) against
    ekf_update_attitude: accepted and gated updates, per-axis variance, the errors it raises."""
    rng = np.random.default_rng(21)
    accepted = rejected = 0
    for k in range(N_CASES):
        x, P = _state(rng, baro=k % 4 == 0)
        cfg = E.EkfConfig(att_var_rad2=rng.uniform(1e-3, 0.1), att_yaw_var_rad2=rng.choice([None, 0.02]),
                          gate_sigma=rng.choice([0.5, 5.0]))
        fast, ref = (link_ekf.LinkEkf(np.zeros(3), np.zeros(3), [1.0, 0, 0, 0], cfg, compiled=c) for c in (True, False))
        for e in (fast, ref):
            e.x, e.P = x.copy(), P.copy()
        z = x[E.X_Q] + rng.uniform(0.01, 1.5) * rng.normal(size=4)  # not normalised: the update normalises
        a, b = fast.update_attitude(z), ref.update_attitude(z)
        assert a.accepted == b.accepted
        np.testing.assert_allclose(a.test_ratio, b.test_ratio, **TOL)
        np.testing.assert_allclose(a.innovation, b.innovation, **TOL)
        np.testing.assert_allclose(fast.x, ref.x, **TOL)
        np.testing.assert_allclose(fast.P, ref.P, **TOL)
        np.testing.assert_array_equal(fast.P, fast.P.T)
        assert (fast.accepted, fast.rejected) == (ref.accepted, ref.rejected)
        accepted += b.accepted
        rejected += not b.accepted
    assert accepted and rejected
    for bad, match in (([0.0, 0, 0, 0], "zero quaternion"), ([np.nan, 1, 0, 0], "finite"), ([1.0, 0, 0], "4 finite")):
        with pytest.raises(ValueError, match=match):
            fast.update_attitude(np.array(bad))


def _firmware_pair():
    from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware

    inertia, geometry = LinkInertia(1.8, (0.01, 0.2, 0.2)), RotorGeometry.odar()
    fused, stepwise = (LinkFirmware(0, FirmwareConfig(), inertia, geometry) for _ in range(2))
    stepwise.fused_tick = False
    return fused, stepwise


def test_fused_tick_matches_step_by_step(monkeypatch):
    """LinkFirmware.on_imu through the one-kernel tick (_tick_fused) against the step-by-step path
    (predict, updates, control estimate, eq. 1, allocation) over a flight segment: corrections
    arriving and fading, GPS and attitude updates queued (an attitude reference alone through
    attitude_tick_kernel), new targets, a target 30 m off (the rotors at their limit: the wrench
    scaled, reported), a stale target (the fallback)."""

    rng = np.random.default_rng(23)
    fused, stepwise = _firmware_pair()
    by_attitude_kernel = []
    kernel = fused_ticks.attitude_tick_kernel
    monkeypatch.setattr(fused_ticks, "attitude_tick_kernel", lambda *a: by_attitude_kernel.append(1) or kernel(*a))
    taken = []
    plain = fused._tick_fused

    def tick_fused(*a):  # records whether the fused path ran, returns its command
        out = plain(*a)
        taken.append(out is not None)
        return out

    fused._tick_fused = tick_fused
    q0 = quat_normalize(np.array([1.0, 0.02, -0.01, 0.1]))
    p0 = np.array([0.3, -0.2, 1.5])
    for fw in (fused, stepwise):
        fw.initialize(0.0, p0, np.zeros(3), q0)
        fw.arm(0.0)
    t = 0.0
    for k in range(1, 800):
        t = k * 0.002
        # targets at 10 Hz, then a far one: stale after 1 s (from tick 752)
        events = flight_events(rng, k, p0, q0, targets_until=200, far_at=251, gps_every=5, attitude_every=2)
        gyro, accel = rng.normal(size=3) * 0.05, np.array([0.0, 0.0, 9.81]) + rng.normal(size=3) * 0.1
        for fw in (fused, stepwise):
            for name, args in events:
                getattr(fw, name)(*args)
        a, b = fused.on_imu(t, gyro, accel), stepwise.on_imu(t, gyro, accel)
        np.testing.assert_allclose(a, b, **TOL, err_msg=f"tick {k}")
        np.testing.assert_allclose(fused.ekf.x, stepwise.ekf.x, **TOL)
        np.testing.assert_allclose(fused.ekf.P, stepwise.ekf.P, **TOL)
        np.testing.assert_allclose(fused.integrals.pos, stepwise.integrals.pos, **TOL)
        np.testing.assert_allclose(fused.integrals.att, stepwise.integrals.att, **TOL)
        np.testing.assert_allclose(fused.allocator.xi_pre, stepwise.allocator.xi_pre, **TOL)
        np.testing.assert_allclose(fused.thrust_total_n, stepwise.thrust_total_n, **TOL)
        np.testing.assert_allclose(fused.allocator.scale, stepwise.allocator.scale, **TOL)
        assert fused.allocator.saturated == stepwise.allocator.saturated
        assert fused.time_s == stepwise.time_s and fused.airborne == stepwise.airborne
    limit = fused.thrust_limit.report()
    assert limit == stepwise.thrust_limit.report() and limit["episodes"] == 1 and limit["min_scale"] < 0.9, limit
    assert fused.ekf.accepted == stepwise.ekf.accepted and fused.ekf.rejected == stepwise.ekf.rejected
    assert fused.correction_weight(t) == stepwise.correction_weight(t)
    n_fused = sum(taken)
    assert 300 < n_fused < len(taken)  # most ticks fused, the stale-target ones through the fallback
    assert len(by_attitude_kernel) > 150, len(by_attitude_kernel)  # ticks 2, 4, 6, 8 of every 10 while fused
    last = fused.wrench_guard.command.copy()
    for fw in (fused, stepwise):  # a wrench that is not finite: refused on both paths, the commands held
        fw.set_target(t, PoseTarget.hold(np.full(3, np.nan), q0))
        np.testing.assert_allclose(fw.on_imu(t + 0.002, gyro, accel), last, **TOL)
        assert fw.wrench_guard.refused == 1 and fw.wrench_guard.holding


def test_record_tick_matches_the_decoding_path():
    """LinkFirmware.on_hil_record (hil_tick_kernel: a same-host simulator-link packet's bytes to its
    answer's) against the decoding path the other ticks take (simlink.decode_packet,
    hil.decode_hil_sensor, hil.decode_ahrs, on_attitude, on_imu, hil.encode_actuators,
    simlink.encode_packet) over a flight segment: corrections, measurements queued (those ticks are
    left to the decoding path), attitude references in the packet (accepted, and one 40 deg off
    rejected by the gate), new targets, one 30 m off (the rotors at their limit, the controls
    clipped to -1..1): the answer byte for byte, the commands, the state and the EKF's counts bit
    for bit. Then what the kernel must leave to the decoders, with nothing changed or written: a
    non-finite or out-of-range sample, a barometer or magnetometer sample, another kind, a reference not finite, not
    of norm 1 or without its sample, the records in another order or with a GPS fix, a cut packet,
    the fused tick off."""
    from companion.estimation.so3 import quat_from_rotvec, quat_mul
    from companion.mavlink.codec import seconds
    from link_firmware_sim.vehicle import hil
    from link_firmware_sim.vehicle.simlink import decode_packet, encode_packet

    assert hil_records.HIL_BARO_MAG_BITS == hil._BARO_MAG_BITS
    assert hil_records.AHRS_NORM_TOLERANCE == hil.AHRS_NORM_TOLERANCE
    assert (hil_records.IMU_ACCEL_MAX_M_S2, hil_records.IMU_GYRO_MAX_RAD_S) == (hil.IMU_ACCEL_MAX_M_S2,
                                                                              hil.IMU_GYRO_MAX_RAD_S)
    rng = np.random.default_rng(29)
    record, decoding = _firmware_pair()
    decoding.fused_tick = True  # its ticks through on_imu (fused when it can: the same kernel's numbers)
    tmax = 4.0  # under the allocator's limit: the normalised controls reach the clip
    q0 = quat_normalize(np.array([1.0, 0.02, -0.01, 0.1]))
    p0 = np.array([0.3, -0.2, 1.5])
    for fw in (record, decoding):
        fw.initialize(0.0, p0, np.zeros(3), q0)
        fw.arm(0.0)
        fw.set_target(0.0, PoseTarget.hold(p0, q0))
    taken, clipped, references = 0, 0, np.zeros(2, dtype=int)
    for k in range(1, 500):
        t = k * 0.002
        events = flight_events(rng, k, p0, q0, targets_until=500, far_at=301, gps_every=25, attitude_every=35)
        for fw in (record, decoding):
            for name, args in events:
                getattr(fw, name)(*args)
        gyro, accel = rng.normal(size=3) * 0.05, np.array([0.0, 0.0, 9.81]) + rng.normal(size=3) * 0.1
        msgs = [hil.encode_hil_sensor(t, accel, gyro)]
        if k % 3 == 1:  # an attitude reference in the packet, 40 deg off at tick 202
            off = quat_from_rotvec(np.radians([0.0, 40.0, 0.0])) if k == 202 else quat_normalize(
                np.array([1.0, *(rng.normal(size=3) * 0.01)]))
            msgs.insert(0, hil.encode_ahrs(t, quat_mul(q0, off)))
        packet = encode_packet(msgs)
        decoded = decode_packet(packet)
        reference = hil.decode_ahrs(decoded[0]) if len(msgs) == 2 else None
        if reference is not None:
            decoding.on_attitude(*reference)
        t_s, g, a = hil.decode_hil_sensor(decoded[-1])
        expected = decoding.on_imu(t_s, g, a)
        expected_answer = encode_packet([hil.encode_actuators(t_s, expected, tmax, True)])
        buffers = HilBuffers(tmax, 128, 1025)
        answer = buffers.answer
        buffers.io[IO_AHRS_ACCEPTED:IO_AHRS_Q + 4] = 7.0  # (zeroed by the call)
        handed, last_s = [], record.time_s  # the answer, handed over before the tick's bookkeeping
        command = record.on_hil_record(t_s, np.frombuffer(packet, dtype=np.uint8), buffers,
                                       lambda ans: handed.append((ans.tobytes(), record.time_s)))
        if command is None:  # measurements queued: the decoding path, nothing written
            assert record._pending and not answer.any() and not handed, f"tick {k}"
            if reference is not None:
                record.on_attitude(*reference)
            command = record.on_imu(t_s, g, a)
        else:
            taken += 1
            assert answer.tobytes() == expected_answer, f"tick {k}"
            assert handed == [(expected_answer, last_s)] and last_s < t_s == record.time_s, f"tick {k}"
            clipped += int(np.any(np.abs(expected) > tmax))
            accepted, rejected, t_us, q = buffers.ahrs()
            if reference is None:
                assert accepted == rejected == 0, f"tick {k}"
            else:  # counted, and the reference as the decoder gives it
                references += (accepted, rejected)
                assert accepted + rejected == 1, f"tick {k}"
                assert seconds(t_us) == reference[0], f"tick {k}"
                np.testing.assert_array_equal(q, reference[1], err_msg=f"tick {k}")
        assert (record.ekf.accepted, record.ekf.rejected) == (decoding.ekf.accepted, decoding.ekf.rejected)
        np.testing.assert_array_equal(command, expected, err_msg=f"tick {k}")
        np.testing.assert_array_equal(record.ekf.x, decoding.ekf.x)
        np.testing.assert_array_equal(record.ekf.P, decoding.ekf.P)
        np.testing.assert_array_equal(record.ekf.last_gyro_b_rad_s, decoding.ekf.last_gyro_b_rad_s)
        np.testing.assert_array_equal(record.integrals.pos, decoding.integrals.pos)
        np.testing.assert_array_equal(record.integrals.att, decoding.integrals.att)
        np.testing.assert_array_equal(record.allocator.xi_pre, decoding.allocator.xi_pre)
        assert record.thrust_total_n == decoding.thrust_total_n
        assert (record.allocator.scale, record.allocator.saturated) == (decoding.allocator.scale,
                                                                        decoding.allocator.saturated)
        assert record.time_s == decoding.time_s and record.airborne == decoding.airborne
        assert record.events == decoding.events
    assert record.thrust_limit.report() == decoding.thrust_limit.report()
    assert 300 < taken < 499 and clipped > 10, (taken, clipped)
    assert references[0] > 100 and references[1] == 1, references  # fused in the kernel: accepted, rejected

    t = 500 * 0.002
    sample = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 9.81]), np.zeros(3))
    nan = hil.encode_hil_sensor(t, np.array([0.0, np.nan, 9.81]), np.zeros(3))
    inf = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 9.81]), np.array([0.0, 0.0, np.inf]))
    huge = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 1e30]), np.zeros(3))  # beyond the IMU bounds
    spin = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 9.81]), np.array([0.0, 1.5 * hil.IMU_GYRO_MAX_RAD_S, 0.0]))
    baro = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 9.81]), np.zeros(3), baro_alt_m=120.0)
    mag = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 9.81]), np.zeros(3), mag_flu_gauss=np.array([0.2, 0.0, -0.4]))
    gps = hil.encode_hil_gps(t, p0, np.zeros(3), hil.GeoOrigin())
    left = [encode_packet([m]) for m in (nan, inf, huge, spin, baro, mag, gps)]
    ahrs = hil.encode_ahrs(t, q0)
    left += [encode_packet(m) for m in ([ahrs], [sample, ahrs], [gps, ahrs, sample], [ahrs, baro], [ahrs, nan])]
    for q in ([np.nan, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.05], [0.0, 0.0, 0.0, 0.0]):  # the decoder rejects
        ahrs.q = q
        left.append(encode_packet([ahrs, sample]))
    left.append(encode_packet([sample])[:-1])
    before = (record.ekf.x.copy(), record.ekf.P.copy(), record.time_s, record.allocator.xi_pre.copy())
    for packet in left:
        buffers = HilBuffers(tmax, 128, 1025)
        assert record.on_hil_record(t, np.frombuffer(packet, dtype=np.uint8), buffers) is None
        assert not buffers.answer.any()
        for x, y in zip((record.ekf.x, record.ekf.P, record.time_s, record.allocator.xi_pre), before):
            np.testing.assert_array_equal(x, y)
    packet = np.frombuffer(encode_packet([sample]), dtype=np.uint8)
    short = HilBuffers(tmax, 128, 1025)
    short.bufs = (*short.bufs[:3], np.zeros(hil_records.HIL_ACTUATOR_RECORD["size"] - 1, dtype=np.uint8))
    short.answer = short.bufs[3]  # an answer buffer too small
    assert record.on_hil_record(t, packet, short) is None and not short.answer.any()
    record.fused_tick = False
    assert record.on_hil_record(t, packet, HilBuffers(tmax, 128, 1025)) is None
    record.fused_tick = True
    assert record.on_hil_record(t, packet, HilBuffers(tmax, 128, 1025)) is not None


def test_numpy_fallback_without_jit():
    """SKELETON_JIT=0 (as an install without numba): the numpy path runs, with one log line."""
    code = ("import logging; logging.basicConfig(level=logging.INFO)\n"
            "from companion.kernels import jit\n"
            "from link_firmware_sim.estimators import LinkEkf\n"
            "from link_firmware_sim.controllers import ImpedanceController, ImpedanceGains\n"
            "from companion.skeleton.body import LinkInertia\n"
            "import numpy as np\n"
            "assert not jit.ENABLED\n"
            "e = LinkEkf(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]))\n"
            "assert not e.compiled and ImpedanceController(ImpedanceGains(), LinkInertia(1.8, (0.1, 0.2, 0.2))).tick_state is None\n")
    env = dict(os.environ, SKELETON_JIT="0")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "numpy path runs" in out.stderr


def test_the_warm_up_loads_every_signature_the_firmware_uses():
    """link_firmware_sim.kernels.warm compiles each kernel for the argument types the firmware and
    the vehicle pass: after it, a flight segment through every path (the EKF's updates with and
    without the barometer's offset, the step-by-step and fused ticks, an attitude reference queued,
    the record tick, the allocator and eq. 1 called alone) compiles nothing new."""
    from companion.messages import Correction
    from link_firmware_sim.vehicle import hil
    from link_firmware_sim.kernels import allocation, ekf, impedance, tick, warm
    from link_firmware_sim.vehicle.simlink import encode_packet

    warm.warm_up()
    kernels = (ekf.ekf_predict_kernel, ekf.update_block_kernel, ekf.update_rows_kernel, ekf.attitude_update_kernel,
               impedance.impedance_kernel, allocation.allocate_kernel, tick.tick_kernel, tick.attitude_tick_kernel,
               tick.hil_tick_kernel, hil_records.sensor_record_at)
    before = [list(k.signatures) for k in kernels]
    fw, stepwise = _firmware_pair()
    z3, q = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
    accel = np.array([0.0, 0.0, 9.8])
    for f in (fw, stepwise):
        f.initialize(0.0, z3, z3, q)
        f.arm(0.0)
        f.set_target(0.0, PoseTarget.hold(z3, q))
        for k in range(1, 4):
            f.on_imu(0.002 * k, z3, accel)
            f.on_correction(0.002 * k, Correction(0, 0.0, z3 + 0.01, z3, z3))
            f.on_attitude(0.002 * k, q)
            f.on_gps(0.002 * k, z3, z3)
            f.on_baro(0.002 * k, 0.0)
            f.on_mag(0.002 * k, np.array([0.2, 0.0, -0.4]))
        f.on_imu(0.008, z3, accel)  # (the measurements queued last: applied)
        f.ekf.update_heading(0.0)
        f.hover_command(q)
    rec = np.frombuffer(encode_packet([hil.encode_hil_sensor(0.01, accel, z3)]), dtype=np.uint8)
    assert fw.on_hil_record(0.01, rec, HilBuffers(8.0, 128, 1025)) is not None
    hil_records.sensor_record_at(rec, len(rec))
    fw.allocator.allocate(np.array([0.0, 0.0, 17.6, 0.0, 0.0, 0.0]))
    ImpedanceController(ImpedanceGains(), fw.inertia)(z3, z3, q, z3, PoseTarget.hold(z3, q), 0.002)
    for k, sigs in zip(kernels, before):
        assert list(k.signatures) == sigs, k.__name__

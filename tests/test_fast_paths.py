"""Oracle tests: the compiled kernels (link_firmware_sim._fast, sitl.rotor) against the numpy
specification on random inputs (seeded), agreeing to 1e-12.

Without numba (an onboard install) the compiled path is the numpy one and these tests are skipped;
with it, the first run compiles the kernels (about 20 s on a 2-core VM, then cached on disk).
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from companion.estimation.so3 import quat_normalize, quat_to_rotmat
from companion.messages import PoseTarget
from companion.skeleton.body import LinkInertia
from companion.skeleton.rotors import RotorGeometry, RotorParams
from link_firmware_sim import _fast
from link_firmware_sim import ekf as E
from link_firmware_sim.allocation import AllocationParams, Allocator
from link_firmware_sim.control import ControlIntegrals, ImpedanceGains, impedance_control, impedance_control_compiled
from sitl.rotor import RotorBank

pytestmark = pytest.mark.skipif(not _fast.ENABLED, reason="numba not installed (or SKELETON_JIT=0)")

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
        xb, Pb = E._predict_compiled(x, P, gyro, accel, dt, noise)
        np.testing.assert_allclose(xb, xa, **TOL)
        np.testing.assert_allclose(Pb, Pa, **TOL)
        np.testing.assert_array_equal(Pb, Pb.T)
    with pytest.raises(ValueError, match="dt_s"):
        E._predict_compiled(x, P, gyro, accel, 0.0, noise)


@pytest.mark.parametrize("kind", ["position", "velocity", "attitude", "heading", "baro", "mag"])
def test_updates_match_numpy(kind):
    rng = np.random.default_rng(["position", "velocity", "attitude", "heading", "baro", "mag"].index(kind))
    accepted = rejected = 0
    for _ in range(N_CASES):
        x, P = _state(rng, baro=kind == "baro")
        gate = rng.choice([0.5, 5.0])  # a tight gate rejects some
        if kind == "position":
            args, fn = (x[E.X_P] + rng.normal(size=3), rng.uniform(0.01, 1.0), gate), E._position
        elif kind == "velocity":
            args, fn = (x[E.X_V] + rng.normal(size=3), rng.uniform(0.01, 1.0, size=3), gate), E._velocity
        elif kind == "attitude":
            args, fn = (quat_normalize(x[E.X_Q] + 0.5 * rng.normal(size=4)), rng.uniform(1e-3, 0.1), gate), E._attitude
        elif kind == "heading":
            args, fn = (rng.uniform(-np.pi, np.pi), rng.uniform(1e-3, 0.1), gate), E._heading
        elif kind == "baro":
            args, fn = (x[2] + x[16] + rng.normal(), rng.uniform(1e-3, 0.1), gate, rng.choice([0.0, 1.0])), E._baro
        else:
            args, fn = (rng.normal(size=3), rng.uniform(-0.3, 0.3), rng.uniform(1e-3, 0.1), gate), E._mag_heading
        ref = fn(x, P, *args, E._NUMPY)
        _same_update(ref, fn(x, P, *args, E._COMPILED))
        accepted += ref[2].accepted
        rejected += not ref[2].accepted
    assert accepted and rejected  # both branches compared


def test_link_ekf_class_agrees_with_functions():
    """The thin class with the compiled kernels against the functional numpy core over a sequence."""
    rng = np.random.default_rng(5)
    cfg = E.EkfConfig(noise=_noise(rng))
    q0 = quat_normalize(rng.normal(size=4))
    fast = E.LinkEkf(np.zeros(3), np.zeros(3), q0, cfg, compiled=True)
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
        Ub, ib = impedance_control_compiled(*args)
        np.testing.assert_allclose(Ub, Ua, **TOL)
        np.testing.assert_allclose(ib.pos, ia.pos, **TOL)
        np.testing.assert_allclose(ib.att, ia.att, **TOL)


@pytest.mark.parametrize("scale_to_limit", [True, False])
@pytest.mark.parametrize("selective", [True, False])
def test_allocation_matches_numpy(selective, scale_to_limit):
    """A sequence of wrenches (the modulation's state carries over), many near a rotor's zero,
    every seventh one beyond the rotors' limit (scaled to it, or clipped), with the weight of a
    tilted link kept whole (and every third time nothing or a wrench beyond the rotors kept)."""
    rng = np.random.default_rng(3)
    geometry = RotorGeometry.odar()
    params = AllocationParams(selective_mapping=selective, scale_to_limit=scale_to_limit)
    ref, fast = Allocator(geometry, params, compiled=False), Allocator(geometry, params, compiled=True)
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


def test_attitude_update_kernel_matches_numpy():
    """LinkEkf.update_attitude's compiled path (measurement model and update in one kernel) against
    ekf_update_attitude: accepted and gated updates, per-axis variance, the errors it raises."""
    rng = np.random.default_rng(21)
    accepted = rejected = 0
    for k in range(N_CASES):
        x, P = _state(rng, baro=k % 4 == 0)
        cfg = E.EkfConfig(att_var_rad2=rng.uniform(1e-3, 0.1), att_yaw_var_rad2=rng.choice([None, 0.02]),
                          gate_sigma=rng.choice([0.5, 5.0]))
        fast, ref = (E.LinkEkf(np.zeros(3), np.zeros(3), [1.0, 0, 0, 0], cfg, compiled=c) for c in (True, False))
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


def _flight_events(rng, k: int, p0, q0, *, targets_until: int, far_at: int, gps_every: int,
                   attitude_every: int) -> list:
    """The firmware calls ``(name, args)`` of tick ``k`` (time ``k * 2 ms``) of a flight segment: a
    new target every 50 ticks before ``targets_until``, one 30 m off at ``far_at`` (the rotors at
    their limit), corrections, GPS fixes and attitude references."""
    from companion.messages import Correction

    t = k * 0.002
    events = []
    if k % 50 == 1 and k < targets_until:
        target = PoseTarget(p0 + rng.normal(size=3) * 0.2, quat_normalize(q0 + rng.normal(size=4) * 0.05),
                            *(rng.normal(size=(6, 3)) * 0.3))
        events.append(("set_target", (t, target)))
    if k == far_at:
        events.append(("set_target", (t, PoseTarget.hold(p0 + np.array([30.0, -10.0, 20.0]), q0))))
    if k % 97 == 3:
        events.append(("on_correction", (t, Correction(0, t - 0.01, rng.normal(size=3) * 0.05,
                                                         rng.normal(size=3) * 0.02, rng.normal(size=3) * 0.005,
                                                         seq=k))))
    if k % gps_every == 0:
        events.append(("on_gps", (t, p0 + rng.normal(size=3) * 0.3, rng.normal(size=3) * 0.05)))
    if k % attitude_every == 0:
        events.append(("on_attitude", (t, quat_normalize(q0 + rng.normal(size=4) * 0.01))))
    return events


def test_fused_tick_matches_step_by_step(monkeypatch):
    """LinkFirmware.on_imu through the one-kernel tick (_tick_fused) against the step-by-step path
    (predict, updates, control estimate, eq. 1, allocation) over a flight segment: corrections
    arriving and fading, GPS and attitude updates queued (an attitude reference alone through
    attitude_tick_kernel), new targets, a target 30 m off (the rotors at their limit: the wrench
    scaled, reported), a stale target (the fallback)."""

    rng = np.random.default_rng(23)
    fused, stepwise = _firmware_pair()
    by_attitude_kernel = []
    kernel = _fast.attitude_tick_kernel
    monkeypatch.setattr(_fast, "attitude_tick_kernel", lambda *a: by_attitude_kernel.append(1) or kernel(*a))
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
        events = _flight_events(rng, k, p0, q0, targets_until=200, far_at=251, gps_every=5, attitude_every=2)
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
        np.testing.assert_allclose(fused._thrust_total_n, stepwise._thrust_total_n, **TOL)
        np.testing.assert_allclose(fused.allocator.scale, stepwise.allocator.scale, **TOL)
        assert fused.allocator.saturated == stepwise.allocator.saturated
        assert fused.time_s == stepwise.time_s and fused._airborne == stepwise._airborne
    limit = fused.thrust_limit.report()
    assert limit == stepwise.thrust_limit.report() and limit["episodes"] == 1 and limit["min_scale"] < 0.9, limit
    assert fused.ekf.accepted == stepwise.ekf.accepted and fused.ekf.rejected == stepwise.ekf.rejected
    assert fused.correction_weight(t) == stepwise.correction_weight(t)
    n_fused = sum(taken)
    assert 300 < n_fused < len(taken)  # most ticks fused, the stale-target ones through the fallback
    assert len(by_attitude_kernel) > 150, len(by_attitude_kernel)  # ticks 2, 4, 6, 8 of every 10 while fused
    with pytest.raises(ValueError, match="finite"):  # the allocator's check, on the fused path too
        fused.set_target(t, PoseTarget.hold(np.full(3, np.nan), q0))
        fused.on_imu(t + 0.002, gyro, accel)


def test_record_tick_matches_the_decoding_path():
    """LinkFirmware.on_hil_record (hil_tick_kernel: a same-host simulator-link packet's bytes to its
    answer's) against the decoding path the other ticks take (simlink.decode_packet,
    hil.decode_hil_sensor, hil.decode_ahrs, on_attitude, on_imu, hil.encode_actuators,
    simlink.encode_packet) over a flight segment: corrections, measurements queued (those ticks are
    left to the decoding path), attitude references in the packet (accepted, and one 40 deg off
    rejected by the gate), new targets, one 30 m off (the rotors at their limit, the controls
    clipped to -1..1): the answer byte for byte, the commands, the state and the EKF's counts bit
    for bit. Then what the kernel must leave to the decoders, with nothing changed or written: a
    non-finite sample, a barometer or magnetometer sample, another kind, a reference not finite, not
    of norm 1 or without its sample, the records in another order or with a GPS fix, a cut packet,
    the fused tick off."""
    from companion.estimation.so3 import quat_from_rotvec, quat_mul
    from companion.mavlink.codec import seconds
    from link_firmware_sim import hil
    from link_firmware_sim.simlink import decode_packet, encode_packet

    assert _fast.HIL_BARO_MAG_BITS == hil._BARO_MAG_BITS
    assert _fast.AHRS_NORM_TOLERANCE == hil.AHRS_NORM_TOLERANCE
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
        events = _flight_events(rng, k, p0, q0, targets_until=500, far_at=301, gps_every=25, attitude_every=35)
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
        answer = np.zeros(_fast.HIL_ACTUATOR_RECORD["size"], dtype=np.uint8)
        fused = np.full(_fast.AHRS_OUT_SIZE, 7.0)  # (zeroed by the call)
        handed, last_s = [], record.time_s  # the answer, handed over before the tick's bookkeeping
        command = record.on_hil_record(t_s, np.frombuffer(packet, dtype=np.uint8), answer, tmax, 128,
                                       lambda ans: handed.append((ans.tobytes(), record.time_s)), fused)
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
            out = _fast.AHRS_OUT
            if reference is None:
                assert not fused.any(), f"tick {k}"
            else:  # counted, and the reference as the decoder gives it
                references += fused[[out["accepted"], out["rejected"]]].astype(int)
                assert fused[out["accepted"]] + fused[out["rejected"]] == 1, f"tick {k}"
                assert seconds(int(fused[out["t_us"]])) == reference[0], f"tick {k}"
                np.testing.assert_array_equal(fused[out["q"]], reference[1], err_msg=f"tick {k}")
        assert (record.ekf.accepted, record.ekf.rejected) == (decoding.ekf.accepted, decoding.ekf.rejected)
        np.testing.assert_array_equal(command, expected, err_msg=f"tick {k}")
        np.testing.assert_array_equal(record.ekf.x, decoding.ekf.x)
        np.testing.assert_array_equal(record.ekf.P, decoding.ekf.P)
        np.testing.assert_array_equal(record.ekf.last_gyro_b_rad_s, decoding.ekf.last_gyro_b_rad_s)
        np.testing.assert_array_equal(record.integrals.pos, decoding.integrals.pos)
        np.testing.assert_array_equal(record.integrals.att, decoding.integrals.att)
        np.testing.assert_array_equal(record.allocator.xi_pre, decoding.allocator.xi_pre)
        assert record._thrust_total_n == decoding._thrust_total_n
        assert (record.allocator.scale, record.allocator.saturated) == (decoding.allocator.scale,
                                                                        decoding.allocator.saturated)
        assert record.time_s == decoding.time_s and record._airborne == decoding._airborne
        assert record.events == decoding.events
    assert record.thrust_limit.report() == decoding.thrust_limit.report()
    assert 300 < taken < 499 and clipped > 10, (taken, clipped)
    assert references[0] > 100 and references[1] == 1, references  # fused in the kernel: accepted, rejected

    t = 500 * 0.002
    sample = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 9.81]), np.zeros(3))
    nan = hil.encode_hil_sensor(t, np.array([0.0, np.nan, 9.81]), np.zeros(3))
    inf = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 9.81]), np.array([0.0, 0.0, np.inf]))
    baro = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 9.81]), np.zeros(3), baro_alt_m=120.0)
    mag = hil.encode_hil_sensor(t, np.array([0.0, 0.0, 9.81]), np.zeros(3), mag_flu_gauss=np.array([0.2, 0.0, -0.4]))
    gps = hil.encode_hil_gps(t, p0, np.zeros(3), hil.GeoOrigin())
    left = [encode_packet([m]) for m in (nan, inf, baro, mag, gps)]
    ahrs = hil.encode_ahrs(t, q0)
    left += [encode_packet(m) for m in ([ahrs], [sample, ahrs], [gps, ahrs, sample], [ahrs, baro], [ahrs, nan])]
    for q in ([np.nan, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.05], [0.0, 0.0, 0.0, 0.0]):  # the decoder rejects
        ahrs.q = q
        left.append(encode_packet([ahrs, sample]))
    left.append(encode_packet([sample])[:-1])
    before = (record.ekf.x.copy(), record.ekf.P.copy(), record.time_s, record.allocator.xi_pre.copy())
    for packet in left:
        answer = np.zeros(_fast.HIL_ACTUATOR_RECORD["size"], dtype=np.uint8)
        assert record.on_hil_record(t, np.frombuffer(packet, dtype=np.uint8), answer, tmax, 128) is None
        assert not answer.any()
        for x, y in zip((record.ekf.x, record.ekf.P, record.time_s, record.allocator.xi_pre), before):
            np.testing.assert_array_equal(x, y)
    packet = np.frombuffer(encode_packet([sample]), dtype=np.uint8)
    short = np.zeros(_fast.HIL_ACTUATOR_RECORD["size"] - 1, dtype=np.uint8)  # an answer buffer too small
    assert record.on_hil_record(t, packet, short, tmax, 128) is None and not short.any()
    record.fused_tick = False
    assert record.on_hil_record(t, packet, np.zeros(82, dtype=np.uint8), tmax, 128) is None
    record.fused_tick = True
    assert record.on_hil_record(t, packet, np.zeros(82, dtype=np.uint8), tmax, 128) is not None


def test_cross_is_numpys():
    """so3.cross: np.cross's numbers (exactly) for single vectors, stacks and broadcasts."""
    from companion.estimation.so3 import cross

    rng = np.random.default_rng(29)
    for a_shape, b_shape in (((3,), (3,)), ((5, 3), (5, 3)), ((4, 3), (3,)), ((2, 1, 3), (1, 6, 3))):
        a, b = rng.normal(size=a_shape), rng.normal(size=b_shape)
        np.testing.assert_array_equal(cross(a, b), np.cross(a, b))


def test_trajectory_poses_batch_is_pose():
    """ChainTrajectory.poses (the five instants of a target in one evaluation) equals pose() per time."""
    from companion.trajectory import ChainTrajectory, TrajectoryConfig

    traj = ChainTrajectory(TrajectoryConfig(kind="bend", bend_start_s=1.0, bend_ramp_s=1.0), 4, 1.0, [0.0, 0.0, 0.3])
    times = [0.5, 1.2, 2.0, 3.7, 9.1]
    p, q, R = traj.poses(times)
    for i, t in enumerate(times):
        pi, qi = traj.pose(t)
        np.testing.assert_array_equal(p[i], pi)
        np.testing.assert_array_equal(q[i], qi)
    np.testing.assert_array_equal(R, quat_to_rotmat(q))


@pytest.mark.parametrize("n_links", [1, 2, 3, 4, 7])
@pytest.mark.parametrize("kind", ["bend", "figure8", "hover", "rest"])
def test_trajectory_kernel_matches_numpy(n_links, kind):
    """ChainTrajectory.target_arrays by the kernel equals its numpy specification: poses, attitudes,
    velocity and acceleration to 1e-12 (here bit for bit, as it happens), the body rate to 1e-12,
    its derivative to 1e-9 (central differences over h = 1 ms carry R's rounding, 1e-16 between the
    two forms of R(q), as 1e-16 / h^2); random headings, pitches, link lengths, start points and
    times before, during and after the take-off and the bend's ramp, ``targets`` on the kernel."""
    from companion.trajectory import ChainTrajectory, TrajectoryConfig

    rng = np.random.default_rng(n_links * 10 + len(kind))
    for _ in range(10):
        cfg = TrajectoryConfig(kind=kind, takeoff_start_s=rng.uniform(0, 2), takeoff_duration_s=rng.uniform(1, 6),
                               takeoff_altitude_m=rng.uniform(1, 4), yaw_deg=rng.uniform(-180, 180),
                               pitch_deg=rng.uniform(-30, 30), bend_start_s=rng.uniform(2, 8),
                               bend_amplitude_deg=rng.uniform(5, 40), bend_period_s=rng.uniform(4, 12),
                               bend_ramp_s=rng.uniform(0, 6), figure8_start_s=rng.uniform(2, 8))
        traj = ChainTrajectory(cfg, n_links, rng.uniform(0.3, 2.0), rng.normal(size=3))
        for t in rng.uniform(0, 30, size=8):
            got, want = traj.target_arrays(t, compiled=True), traj.target_arrays(t, compiled=False)
            for name, g, w, atol in zip(("p", "q", "R", "v", "a", "w", "w_dot"), got, want, [1e-12] * 6 + [1e-9]):
                assert g.shape == w.shape, name
                np.testing.assert_allclose(g, w, rtol=0, atol=atol, err_msg=name)
            targets = traj.targets(t)
            np.testing.assert_array_equal(np.array([x.omega_dot_d_rad_s2 for x in targets]), got[6])


def test_numpy_fallback_without_jit():
    """SKELETON_JIT=0 (as an install without numba): the numpy path runs, with one log line."""
    code = ("import logging; logging.basicConfig(level=logging.INFO)\n"
            "from link_firmware_sim import _fast, ekf, allocation\n"
            "import numpy as np\n"
            "assert not _fast.ENABLED\n"
            "e = ekf.LinkEkf(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]))\n"
            "assert e._la is ekf._NUMPY\n")
    env = dict(os.environ, SKELETON_JIT="0")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "numpy path runs" in out.stderr


@pytest.mark.parametrize("n_links", [1, 2, 3, 5, 7])
def test_feedforward_kernel_matches_numpy(n_links):
    """companion.kernels.dynamics.feedforward_kernel (the chain's inverse dynamics after the passive joint
    torques) against ChainModel.solve's numpy specification: random motions, every link flying and
    with an end or a middle link passive, to 1e-12 of the largest wrench."""
    pytest.importorskip("pinocchio")
    from companion.skeleton.body import SkeletonConfig
    from companion.skeleton.dynamics import ChainModel

    model = ChainModel(SkeletonConfig(n_links=n_links))
    rng = np.random.default_rng(31 + n_links)
    for _ in range(N_CASES // 2):
        q = quat_normalize(rng.normal(size=(n_links, 4)))
        motion = (rng.normal(size=(n_links, 3)) * 3, quat_to_rotmat(q), rng.normal(size=(n_links, 3)),
                  rng.normal(size=(n_links, 3)), rng.normal(size=(n_links, 3)) * 5, rng.normal(size=(n_links, 3)) * 5)
        for passive in {(), (0,), (n_links // 2,), (n_links - 1,)}:
            spec = model.solve(*motion, passive=passive, compiled=False)
            fast = model.solve(*motion, passive=passive, compiled=True)
            scale = max(1.0, float(np.abs(spec.rotor_wrench_w).max()))
            for name in ("force_ff_w_n", "torque_ff_w_nm", "joint_force_w_n", "joint_torque_w_nm", "rotor_wrench_w"):
                np.testing.assert_allclose(getattr(fast, name), getattr(spec, name), rtol=0, atol=1e-12 * scale,
                                           err_msg=f"{name}, passive {passive}")


def _ekf_like_covariances(rng, n: int) -> np.ndarray:
    """(n, 9, 9) random correlated covariances with an EKF's scales (position 0.1 m, velocity
    0.05 m/s, attitude 0.02 rad)."""
    sd = np.array([0.1] * 3 + [0.05] * 3 + [0.02] * 3)
    A = rng.normal(size=(n, 9, 9))
    corr = A @ np.swapaxes(A, 1, 2) + 9.0 * np.eye(9)
    inv_sd = 1.0 / np.sqrt(np.einsum("nii->ni", corr))
    return corr * inv_sd[:, :, None] * inv_sd[:, None, :] * sd[:, None] * sd[None, :]


@pytest.mark.parametrize("n_links", [1, 2, 3, 4, 7])
@pytest.mark.parametrize("omega_std", [0.0, 0.02])
def test_constraint_apply_kernel_matches_numpy(n_links, omega_std):
    """companion.kernels.sckf.constraint_apply_kernel (Alg. 1 on one chain, with the body-rate noise gain)
    against constraint_apply_dense's numpy specification on random chains: the same iteration
    count and every output to 1e-12 of its largest entry."""
    from companion.estimation.sckf import CAParams, constraint_apply_dense
    from companion.estimation.semi import BATCH_DENSE_MAX_LINKS, local_constraint_apply

    rng = np.random.default_rng(37 + n_links)
    params = CAParams(omega_std_rad_s=omega_std)
    iterations = []
    for _ in range(N_CASES // 2):
        spread = rng.choice([0.001, 0.05, 0.3])  # consistent to far off: one to many iterations
        p = np.cumsum(np.tile([1.0, 0.0, 0.0], (n_links, 1)), axis=0) + rng.normal(size=(n_links, 3)) * spread
        v = rng.normal(size=(n_links, 3)) * 0.3
        q = quat_normalize(np.array([1.0, 0.0, 0.0, 0.0]) + rng.normal(size=(n_links, 4)) * spread)
        w = rng.normal(size=(n_links, 3)) * 0.2
        d = np.tile([0.5, 0.0, 0.0], (n_links, 1))
        P = _ekf_like_covariances(rng, n_links)
        spec = constraint_apply_dense(p, v, q, w, d, P, params, compiled=False)
        fast = constraint_apply_dense(p, v, q, w, d, P, params, compiled=True)
        assert fast.iterations == spec.iterations and fast.converged == spec.converged
        iterations.append(spec.iterations)
        for name in ("p", "v", "q", "P", "P_full", "P_ends", "W_ends", "residual_history"):
            a, b = getattr(fast, name), getattr(spec, name)
            if b is None:
                assert a is None, name
                continue
            scale = max(float(np.abs(b).max()), 1e-300) if b.size else 1.0
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * scale, err_msg=name)
        if n_links <= BATCH_DENSE_MAX_LINKS:  # the semi-distributed step's batched groups take the same path
            (batched,) = local_constraint_apply(p, v, q, w, d, P, [list(range(n_links))], params)
            np.testing.assert_array_equal(batched.P_full, fast.P_full)
    if n_links > 1:
        assert max(iterations) > 1  # the loop itself is exercised, not only the first iteration


def _random_chain(rng, n_links: int, spread: float):
    """A chain of ``n_links`` 1 m links along x, off its joints by about ``spread``: p, v, q, w, d, P."""
    p = np.cumsum(np.tile([1.0, 0.0, 0.0], (n_links, 1)), axis=0) + rng.normal(size=(n_links, 3)) * spread
    v = rng.normal(size=(n_links, 3)) * 0.3
    q = quat_normalize(np.array([1.0, 0.0, 0.0, 0.0]) + rng.normal(size=(n_links, 4)) * spread)
    w = rng.normal(size=(n_links, 3)) * 0.2
    d = np.tile([0.5, 0.0, 0.0], (n_links, 1)) + rng.normal(size=(n_links, 3)) * 0.01
    return p, v, q, w, d, _ekf_like_covariances(rng, n_links)


@pytest.mark.parametrize("n_links", [1, 2, 3, 4, 7])
def test_joint_nis_kernel_matches_numpy(n_links):
    """companion.kernels.gate.joint_nis_kernel against joint_nis's numpy specification on random chains,
    from consistent to far off (NIS from about 1 to thousands): to 1e-12 of each value; a NaN
    state gives NaN at its joints both ways, so the gate cuts them."""
    from companion.estimation.gate import CHI2_6_1E6, GateParams, joint_nis

    rng = np.random.default_rng(71 + n_links)
    values = []
    for k in range(N_CASES):
        params = GateParams(gate_pos_m=rng.choice([0.01, 0.05]), gate_vel_m_s=rng.choice([0.1, 0.25]))
        p, v, q, w, d, P = _random_chain(rng, n_links, rng.choice([0.001, 0.05, 0.3, 1.0]))
        spec = joint_nis(p, v, q, w, d, P, params, compiled=False)
        fast = joint_nis(p, v, q, w, d, P, params, compiled=True)
        assert fast.shape == spec.shape == (n_links - 1,)
        np.testing.assert_allclose(fast, spec, rtol=1e-12, atol=0)
        values.extend(spec)
    if n_links > 1:
        assert min(values) < CHI2_6_1E6 < 10 * CHI2_6_1E6 < max(values)  # the inputs reach both sides of the gate
        p[n_links // 2, 1] = np.nan
        spec = joint_nis(p, v, q, w, d, P, compiled=False)
        fast = joint_nis(p, v, q, w, d, P, compiled=True)
        np.testing.assert_array_equal(np.isnan(fast), np.isnan(spec))
        assert np.isnan(spec).any()


@pytest.mark.parametrize("n_links", [1, 2, 3, 5])
@pytest.mark.parametrize("omega_std", [0.0, 0.02])
def test_local_boundary_kernel_matches_numpy(n_links, omega_std):
    """companion.kernels.semi.group_terms_kernel against local_boundary's specification (group_tip_terms
    and group_boundary) after a local step on random groups, with and without the body-rate
    noise (its end columns): tips, information, tip covariance and Cov(tau, x~_i) to 1e-12 of
    their largest entry."""
    from companion.estimation.sckf import CAParams, constraint_apply
    from companion.estimation.semi import local_boundary

    rng = np.random.default_rng(83 + n_links)
    params = CAParams(omega_std_rad_s=omega_std)
    with_rate_columns = 0
    for _ in range(N_CASES // 2):
        p, v, q, w, d, P = _random_chain(rng, n_links, rng.choice([0.001, 0.05, 0.3]))
        local = constraint_apply(p, v, q, w, d, P, params)
        with_rate_columns += local.W_ends is not None
        spec_b, spec_y = local_boundary(local.p, local.v, local.q, w, d, local, compiled=False)
        fast_b, fast_y = local_boundary(local.p, local.v, local.q, w, d, local, compiled=True)
        names = ("left_tip", "right_tip", "info_pv", "tip_cov")
        pairs = [(name, getattr(fast_b, name), getattr(spec_b, name)) for name in names]
        for name, a, b in pairs + [("Y", fast_y, spec_y)]:
            assert a.shape == b.shape, name
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * float(np.abs(b).max()), err_msg=name)
        assert np.array_equal(fast_b.info_pv, fast_b.info_pv.T) and np.array_equal(fast_b.tip_cov, fast_b.tip_cov.T)
    assert (with_rate_columns > 0) == (omega_std > 0 and n_links > 1)


def test_kernel_arrays_pass_through_or_copy_to_one_layout():
    """companion.kernels.jit.as_kernel_array: a C-contiguous writeable float64 array of the shape is
    passed as is; anything else (read-only, transposed, broadcast, integer) becomes one, so every
    kernel sees one array type (numba compiles again for a read-only array)."""
    from companion.kernels.jit import as_kernel_array

    x = np.zeros((2, 3))
    assert as_kernel_array(x, (2, 3)) is x
    ro = np.arange(6.0).reshape(2, 3)
    ro.setflags(write=False)
    for given, shape in ((ro, (2, 3)), (np.arange(6.0).reshape(3, 2).T, (2, 3)), ([0.5, 0, 0], (4, 3)),
                         (np.arange(6).reshape(2, 3), (2, 3))):
        out = as_kernel_array(given, shape)
        assert out.shape == shape and out.dtype == np.float64 and out.flags.c_contiguous and out.flags.writeable
        np.testing.assert_array_equal(out, np.broadcast_to(np.asarray(given, dtype=float), shape))
        assert not np.shares_memory(out, np.asarray(given))

"""Oracle test of the batch simulator's tick of all links (:class:`~link_firmware_sim.batch.LinkBatch`,
:func:`~link_firmware_sim.kernels.batch_tick.links_tick_kernel`) against each link's own fused tick
(``LinkFirmware.on_imu``): the same state, bit for bit, through runs of quiet ticks, ticks that
need their bookkeeping (the rotors at their limit, a wrench that is not finite, an attitude reference the gate rejects)
and ticks the batch hands back (a stale target), with measurements and corrections in between,
the attitude references fed to the firmware or given to the batch with their tick."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.estimation.so3 import quat_normalize
from companion.kernels.jit import ENABLED
from companion.messages import PoseTarget
from companion.skeleton.body import LinkInertia
from companion.skeleton.rotors import RotorGeometry

from .firmware_segments import flight_events

pytestmark = pytest.mark.skipif(not ENABLED, reason="numba not installed (or SKELETON_JIT=0)")

N_LINKS = 3


def _links(att_reset_rejections: int | None = None):
    """Three armed-ready firmwares (``att_reset_rejections``: their EKF's, else the default)."""
    from dataclasses import replace

    from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware

    cfg = FirmwareConfig()
    if att_reset_rejections is not None:
        cfg = replace(cfg, ekf=replace(cfg.ekf, att_reset_rejections=att_reset_rejections))
    inertia, geometry = LinkInertia(1.8, (0.01, 0.2, 0.2)), RotorGeometry.odar()
    return [LinkFirmware(i, cfg, inertia, geometry) for i in range(N_LINKS)]


def _same(a, b, tick: int) -> None:
    """Two firmwares in the same state, bit for bit."""
    msg = f"link {a.link} tick {tick}"
    for x, y in ((a.ekf.x, b.ekf.x), (a.ekf.P, b.ekf.P), (a.integrals.pos, b.integrals.pos),
                 (a.integrals.att, b.integrals.att), (a.allocator.xi_pre, b.allocator.xi_pre),
                 (a.wrench_guard.command, b.wrench_guard.command), (a.imu_health.gyro_sample, b.imu_health.gyro_sample),
                 (a.ekf.last_gyro_b_rad_s, b.ekf.last_gyro_b_rad_s)):
        np.testing.assert_array_equal(x, y, err_msg=msg)
    assert (a.time_s, a.airborne, a.thrust_total_n, a.allocator.scale, a.allocator.saturated) == (
        b.time_s, b.airborne, b.thrust_total_n, b.allocator.scale, b.allocator.saturated), msg
    assert a.thrust_limit.report() == b.thrust_limit.report(), msg
    assert a.wrench_guard.refused == b.wrench_guard.refused, msg
    assert (a.ekf.accepted, a.ekf.rejected, a.ekf.rejected_run) == (b.ekf.accepted, b.ekf.rejected, b.ekf.rejected_run), msg


def _attitudes_alone(events) -> np.ndarray | None:
    """Every link's attitude reference (n, 4) when each link's only event of the tick is one."""
    if all(len(evs) == 1 and evs[0][0] == "on_attitude" for evs in events):
        return np.array([evs[0][1][1] for evs in events])
    return None


#: link 3's attitude references from tick 400 to 499: a quarter turn off (the gate rejects them, and
#: a run of three rejections resets the attitude)
_WRONG = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])


@pytest.mark.parametrize("gps_every, attitude_every, att_in_batch", [(50, 10, False), (25, 5, False), (50, 10, True),
                                                                    (25, 5, True)])
def test_link_batch_ticks_as_each_links_own_fused_tick(gps_every, attitude_every, att_in_batch):
    """Three links, each with its own flight segment (seeded): link 1's targets stop (stale after
    1 s: the batch hands it back), link 2's target jumps 30 m away (the rotors at their limit: its
    ticks need their bookkeeping), link 3 flies on. The batch side syncs before every measurement,
    target or correction, as the batch simulator does, except (``att_in_batch``) attitude references
    alone, which go to the batch with their tick (link 3's are a quarter turn off for a while: the
    gate rejects them, and after three in a row the next one resets the attitude); the commands and every piece of state match the
    firmware's own ticks after every tick; then a wrench that is not finite is refused on both."""
    from link_firmware_sim.batch import LinkBatch

    reset = 3 if att_in_batch else None
    batched, own = _links(reset), _links(reset)
    batch = LinkBatch(batched)
    q0 = quat_normalize(np.array([1.0, 0.02, -0.01, 0.1]))
    p0 = np.array([0.3, -0.2, 1.5])
    for fw in batched + own:
        fw.initialize(0.0, p0 + fw.link, np.zeros(3), q0)
        fw.arm(0.0)
    rngs = [np.random.default_rng(40 + i) for i in range(N_LINKS)]
    imu_rng = np.random.default_rng(7)
    commands = np.zeros((N_LINKS, 8))
    plan = [dict(targets_until=200, far_at=10_000), dict(targets_until=300, far_at=301),
            dict(targets_until=900, far_at=10_000)]
    t = 0.0
    for k in range(1, 900):
        t = k * 0.002
        events = [flight_events(rngs[i], k, p0 + i, q0, gps_every=gps_every, attitude_every=attitude_every, **plan[i])
                  for i in range(N_LINKS)]
        if att_in_batch and 400 <= k < 500:
            events[2] = [(name, (t, _WRONG) if name == "on_attitude" else args) for name, args in events[2]]
        gyro = imu_rng.normal(size=(N_LINKS, 3)) * 0.05
        accel = np.array([0.0, 0.0, 9.81]) + imu_rng.normal(size=(N_LINKS, 3)) * 0.1
        att = _attitudes_alone(events) if att_in_batch else None
        if any(events) and att is None:
            batch.sync()
        for side in (batched, own) if att is None else (own,):
            for fw, evs in zip(side, events):
                for name, args in evs:
                    getattr(fw, name)(*args)
        expected = [fw.on_imu(t, gyro[i], accel[i]) for i, fw in enumerate(own)]
        for i in batch.tick(t, gyro, accel, commands, att=att):
            if att is not None:
                batched[i].on_attitude(t, att[i])
            commands[i] = batched[i].on_imu(t, gyro[i], accel[i])
        np.testing.assert_array_equal(commands, np.array(expected), err_msg=f"tick {k}")
        wrong = att_in_batch and 400 <= k < 500  # (no extra sync: several rejections in one run of the batch)
        if (k % 7 == 0 and not wrong) or k > 880:  # (a sync at other ticks than the events')
            batch.sync()
            for a, b in zip(batched, own):
                _same(a, b, k)
    batch.sync()
    counts = batch.counts
    assert counts["ticks"] > 300 and counts["ticked"] >= 2 and counts["not_taken"] >= 1, counts
    if att_in_batch:  # (the references the batch fused, and the run the gate rejected)
        assert own[0].ekf.accepted["att"] > 900 // attitude_every - 10 and own[2].ekf.rejected["att"] >= 5
    assert own[1].thrust_limit.report()["episodes"] == 1 and own[0].thrust_limit.report()["episodes"] == 0
    for side in (batched, own):  # a wrench that is not finite: the commands held, the refusal counted
        side[2].set_target(t, PoseTarget.hold(np.full(3, np.nan), q0))
    held = own[2].wrench_guard.command.copy()
    gyro, accel = np.zeros((N_LINKS, 3)), np.tile([0.0, 0.0, 9.81], (N_LINKS, 1))
    expected = [fw.on_imu(t + 0.002, gyro[i], accel[i]) for i, fw in enumerate(own)]
    for i in batch.tick(t + 0.002, gyro, accel, commands):
        commands[i] = batched[i].on_imu(t + 0.002, gyro[i], accel[i])
    batch.sync()
    np.testing.assert_array_equal(commands, np.array(expected))
    np.testing.assert_array_equal(commands[2], held)
    for a, b in zip(batched, own):
        _same(a, b, 900)
    assert batched[2].wrench_guard.refused == 1


def test_the_warm_up_loads_the_batch_kernel_for_the_batch_simulator():
    """After the firmware's warm-up, the batch of a flight's links compiles nothing new."""
    from link_firmware_sim.batch import LinkBatch
    from link_firmware_sim.kernels import batch_tick, warm

    warm.warm_up()
    before = list(batch_tick.links_tick_kernel.signatures)
    links = _links()
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for fw in links:
        fw.initialize(0.0, np.zeros(3), np.zeros(3), q)
        fw.arm(0.0)
        fw.set_target(0.0, PoseTarget.hold(np.zeros(3), q))
    batch = LinkBatch(links)
    gyro, accel = np.zeros((N_LINKS, 3)), np.tile([0.0, 0.0, 9.81], (N_LINKS, 1))
    batch.tick(0.002, gyro, accel, np.zeros((N_LINKS, 8)))
    assert batch.counts["ticks"] == 1
    assert list(batch_tick.links_tick_kernel.signatures) == before

"""Oracle test of the batch simulator's tick of all links (:class:`~link_firmware_sim.batch.LinkBatch`,
:func:`~link_firmware_sim.kernels.batch_tick.links_tick_kernel`) against each link's own fused tick
(``LinkFirmware.on_imu``): the same state, bit for bit, through runs of quiet ticks, ticks that
need their bookkeeping (the rotors at their limit, a wrench that is not finite) and ticks the batch
hands back (a stale target), with measurements and corrections in between."""

from __future__ import annotations

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


def _links():
    from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware

    inertia, geometry = LinkInertia(1.8, (0.01, 0.2, 0.2)), RotorGeometry.odar()
    return [LinkFirmware(i, FirmwareConfig(), inertia, geometry) for i in range(N_LINKS)]


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


@pytest.mark.parametrize("gps_every, attitude_every", [(50, 10), (25, 5)])
def test_link_batch_ticks_as_each_links_own_fused_tick(gps_every, attitude_every):
    """Three links, each with its own flight segment (seeded): link 1's targets stop (stale after
    1 s: the batch hands it back), link 2's target jumps 30 m away (the rotors at their limit: its
    ticks need their bookkeeping), link 3 flies on. The batch side syncs before every measurement,
    target or correction, as the batch simulator does; the commands and every piece of state match
    the firmware's own ticks after every tick; then a wrench that is not finite is refused on both."""
    from link_firmware_sim.batch import LinkBatch

    batched, own = _links(), _links()
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
        gyro = imu_rng.normal(size=(N_LINKS, 3)) * 0.05
        accel = np.array([0.0, 0.0, 9.81]) + imu_rng.normal(size=(N_LINKS, 3)) * 0.1
        if any(events):
            batch.sync()
        for side in (batched, own):
            for fw, evs in zip(side, events):
                for name, args in evs:
                    getattr(fw, name)(*args)
        expected = [fw.on_imu(t, gyro[i], accel[i]) for i, fw in enumerate(own)]
        for i in batch.tick(t, gyro, accel, commands):
            commands[i] = batched[i].on_imu(t, gyro[i], accel[i])
        np.testing.assert_array_equal(commands, np.array(expected), err_msg=f"tick {k}")
        if k % 7 == 0 or k > 880:  # (a sync at other ticks than the events')
            batch.sync()
            for a, b in zip(batched, own):
                _same(a, b, k)
    batch.sync()
    counts = batch.counts
    assert counts["ticks"] > 300 and counts["ticked"] >= 2 and counts["not_taken"] >= 1, counts
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

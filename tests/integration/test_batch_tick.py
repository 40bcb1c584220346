"""The batch simulator's tick of all links in one kernel call (:class:`~link_firmware_sim.batch.LinkBatch`)
against every link ticked by its own firmware: the same flight, bit for bit."""

from dataclasses import replace

import numpy as np
import pytest

from link_firmware_sim.batch import ENABLED, LinkBatch
from sitl.runner import BatchRunner
from sitl.scenario import InjectFault, LinkRebootFault, load_scenario
from sitl.scenarios.chain.flight import fly

from ..flights import seeded_metrics

pytestmark = pytest.mark.skipif(not ENABLED, reason="the batch tick is a compiled path (numba)")


def _reboot(sc):
    """Link 2 killed at 3 s, powered on again 0.5 s later; one companion per group ([1], [2, 3])."""
    return replace(sc, faults=replace(sc.faults, link=LinkRebootFault(kill=2, kill_at_s=3.0, restart_after_s=0.5)),
                   companion=replace(sc.companion, distributed=True, groups=((1,), (2, 3))))


def _gyro_garbage(sc):
    """Link 2's gyro reads garbage from 2 s to 3 s (the vehicle's failure filter)."""
    return replace(sc, faults=replace(sc.faults, inject=InjectFault(link=2, unit="gyro", type="garbage", at_s=2.0,
                                                                    duration_s=1.0)))


CASES = {
    # in the air at the start, one companion: quiet ticks almost throughout
    "three_link": ("configs/sitl/chain/three_link.toml", 7.5, None),
    # the neighbours of a dead link at their rotors' limit (ticks that need their bookkeeping),
    # a restarted firmware booting, the distributed companions' outputs at any tick
    "reboot": ("configs/sitl/chain/three_link.toml", 7.5, _reboot),
    # a link's IMU failing: the firmware's own path for it
    "gyro_garbage": ("configs/sitl/chain/three_link.toml", 7.5, _gyro_garbage),
    # seven links, three companions, barometer and magnetometer (the EKF's barometer offset state),
    # from the ground: take-off
    "seven_link_takeoff": ("configs/sitl/faults/link_reboot.toml", 7.5, None),
}


@pytest.mark.parametrize("case", CASES)
def test_batch_tick_flies_the_same_flight_as_each_links_own_tick(tmp_path, monkeypatch, case):
    """Every log series and every seeded metric equal, with the batch's kernel calls counted: it
    ran most ticks (each link ticked on its own only where the batch hands back)."""
    config, duration_s, change = CASES[case]
    sc = load_scenario(config, duration_s=duration_s)
    if change is not None:
        sc = change(sc)
    batches = []
    init = LinkBatch.__init__

    def recorded(self, firmware):
        init(self, firmware)
        batches.append(self)

    monkeypatch.setattr(LinkBatch, "__init__", recorded)
    runs = {}
    for on in (True, False):
        monkeypatch.setattr(BatchRunner, "batch_ticks", on)
        m = fly(sc, tmp_path / str(on), plots=False)
        runs[on] = m, np.load(tmp_path / str(on) / "log.npz")
    (m_on, log_on), (m_off, log_off) = runs[True], runs[False]
    assert len(batches) == 1
    counts = batches[0].counts
    fw_ticks = duration_s * sc.firmware.rate_hz
    assert counts["ticks"] > 0.8 * fw_ticks, counts  # (the other ticks feed a measurement or log a row)
    assert sorted(log_on.files) == sorted(log_off.files)
    for key in log_off.files:
        np.testing.assert_array_equal(log_on[key], log_off[key], err_msg=key)
    assert seeded_metrics(m_on) == seeded_metrics(m_off)
    if case == "reboot":
        assert counts["ticked"] > 0, counts  # (at the rotors' limit)

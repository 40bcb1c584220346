"""A wrench the controller returns that is not finite (link_firmware_sim.wrench_guard): refused on
every path (the step-by-step tick, the fused tick), the last finite commands held, the controller
reset, the refusal counted and reported; the link flies on."""

from __future__ import annotations

import numpy as np
import pytest

from companion.messages import PoseTarget
from link_firmware_sim.kernels.layouts import CTL_POS_INT
from link_firmware_sim.wrench_guard import REPORT_EVERY_S, WrenchGuard

from .test_gps_health import GRAVITY_UP, _hovering_firmware


def test_the_guard_holds_the_last_finite_commands_and_reports_once_a_second():
    g = WrenchGuard()
    g.passed(np.arange(8.0))
    held, events = g.refuse(1.0)
    assert np.array_equal(held, np.arange(8.0)) and g.holding and [e.kind for e in events] == ["fault"]
    held[:] = -1.0  # (a copy: the caller may change it)
    assert np.array_equal(g.command, np.arange(8.0))
    assert g.refuse(1.0 + 0.5 * REPORT_EVERY_S)[1] == []
    assert len(g.refuse(1.0 + REPORT_EVERY_S)[1]) == 1
    g.passed(np.ones(8))
    assert not g.holding and len(g.refuse(2.1)[1]) == 1  # a new episode: reported at once
    assert g.report() == {"refused": 4, "holding": True}


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "step_by_step"])
def test_a_corrupted_integral_is_refused_held_and_flown_through(fused):
    """An armed, hovering link whose controller integral becomes NaN at one tick (a numerical
    failure inside the firmware): that tick returns the previous tick's commands, a STATUSTEXT
    says so, the controller is reset and the next tick's wrench is finite again."""
    fw, q = _hovering_firmware()
    fw.fused_tick = fused
    assert fw.arm(0.0)
    fw.set_target(0.0, PoseTarget.hold(np.zeros(3), q))
    previous = None
    for k in range(1, 101):
        t = k / 500
        if k % 10 == 0:
            fw.on_attitude(t, q)
        if k == 60:
            fw.controller.state[CTL_POS_INT] = np.nan
            held = fw.on_imu(t, np.zeros(3), GRAVITY_UP)
            assert np.array_equal(held, previous) and fw.wrench_guard.holding
            assert [e.text for e in fw.events if e.kind == "fault"] == ["Wrench not finite: command held (1)"]
            assert np.isfinite(fw.controller.state).all()
            continue
        previous = fw.on_imu(t, np.zeros(3), GRAVITY_UP).copy()
        assert np.isfinite(previous).all() and np.abs(previous).sum() > 1.0
    assert fw.wrench_guard.refused == 1 and not fw.wrench_guard.holding

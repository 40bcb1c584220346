"""A motor failure seen in the ESCs' telemetry (link_firmware_sim/motor_failure.py) and the
firmware's answer: the rotor left out of the allocation (SKL_CA_FAIL), reported, restored at disarm."""

import numpy as np
import pytest

from companion.skeleton.body import SkeletonConfig, link_inertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware
from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.motor_failure import MAX_GAP_S, MIN_COMMAND_N, STOPPED_N, TIMEOUT_S, MotorFailureDetector
from link_firmware_sim.vehicle.params import ParamTable, StreamRates

DT = 0.002  # the firmware's 500 Hz tick
HOVER = np.array([3.25, -3.25] * 4)


def _feed(detector, seconds, reported_rotor=None, command=HOVER, t0=0.0, reported=0.0):
    """Ticks of ``seconds`` from ``t0``: ``command`` each, the ESCs reporting it but rotor
    ``reported_rotor`` at ``reported``; returns ``[(t, newly failed)]`` and the next tick's time."""
    found, k = [], 0
    while k * DT < seconds - 1e-12:
        t = t0 + k * DT
        rep = np.array(command, dtype=float)
        if reported_rotor is not None:
            rep[reported_rotor] = reported
        new = detector.update(t, command, rep)
        if new:
            found.append((t, new))
        k += 1
    return found, t0 + k * DT


def test_a_rotor_stopped_while_commanded_is_failed_after_the_timeout_once():
    det = MotorFailureDetector()
    found, t = _feed(det, 0.5, reported_rotor=5)
    assert found == [(pytest.approx(TIMEOUT_S, abs=1e-9), [5])]
    assert det.failed == [5]
    assert _feed(det, 0.2, reported_rotor=5, t0=t)[0] == []  # named once


@pytest.mark.parametrize("case", ["short", "slow_command", "turning", "gap"])
def test_what_is_not_a_failure(case):
    """Stopped for less than the timeout; commanded under MIN_COMMAND_N (an ESC may stop there);
    turning, if slowly; a stop whose ticks are broken by a telemetry gap starts its timer again."""
    det = MotorFailureDetector()
    if case == "short":
        found, t = _feed(det, TIMEOUT_S - 2 * DT, reported_rotor=2)
        found += _feed(det, 0.5, t0=t)[0]
    elif case == "slow_command":
        found = _feed(det, 0.5, reported_rotor=2, command=np.full(8, 0.9 * MIN_COMMAND_N))[0]
    elif case == "turning":
        found = _feed(det, 0.5, reported_rotor=2, reported=1.5 * STOPPED_N)[0]
    else:
        found, t = _feed(det, TIMEOUT_S - 2 * DT, reported_rotor=2)
        found += _feed(det, TIMEOUT_S - 2 * DT, reported_rotor=2, t0=t + MAX_GAP_S + DT)[0]
    assert found == [] and det.failed == []


def test_reset_forgets_the_failures():
    det = MotorFailureDetector()
    _feed(det, 0.2, reported_rotor=0)
    det.reset()
    assert det.failed == []
    assert _feed(det, TIMEOUT_S - 2 * DT, reported_rotor=0, t0=1.0)[0] == []


def _armed_firmware(**params):
    table = ParamTable(1, FirmwareConfig(), GeoOrigin(), StreamRates())
    for name, value in params.items():
        table.set(name, value)
    geometry = RotorGeometry.odar()
    fw = LinkFirmware(0, table.firmware_config(), link_inertia(SkeletonConfig(), geometry), geometry)
    fw.initialize(0.0, np.zeros(3), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    assert fw.arm(0.0)
    return fw, table


def _telemetry(fw, seconds, rotor, t0=0.0):
    t = t0
    while t < t0 + seconds:
        reported = HOVER.copy()
        reported[rotor] = 0.0
        fw.on_esc_telemetry(t, HOVER, reported)
        t += DT
    return t


@pytest.mark.parametrize("mode", [1, 0])
def test_the_firmware_leaves_a_failed_rotor_out_and_says_so(mode):
    """SKL_CA_FAIL = 1 (default): the rotor leaves the allocation, a critical STATUSTEXT says so;
    0: reported only. A second failure is not handled; a disarm restores every rotor."""
    fw, _ = _armed_firmware(SKL_CA_FAIL=mode)
    t = _telemetry(fw, 0.3, rotor=6)
    texts = [(e.kind, e.text) for e in fw.events]
    if mode:
        assert fw.allocator.removed_rotor == 6
        assert texts == [("reset", "Motor 7 failed: flying on the other seven")]
        assert fw.allocator.allocate(fw.allocator.mapping_matrix @ HOVER).command_n[6] == 0.0
        fw.events.clear()
        _telemetry(fw, 0.3, rotor=1, t0=t)
        assert fw.allocator.removed_rotor == 6
        assert [e.text for e in fw.events] == ["Motor 2 failed: not handled, 7 out"]
    else:
        assert fw.allocator.removed_rotor is None
        assert texts == [("reset", "Motor 7 failed: SKL_CA_FAIL off, still used")]
    fw.disarm()
    assert fw.allocator.removed_rotor is None and fw.motor_failure.failed == []
    fw.events.clear()
    _telemetry(fw, 0.3, rotor=6, t0=t + 1.0)  # disarmed: no telemetry judged
    assert fw.events == [] and fw.allocator.removed_rotor is None


def test_a_parameter_change_keeps_the_rotor_out():
    fw, table = _armed_firmware()
    _telemetry(fw, 0.3, rotor=4)
    table.set("SKL_SM_EPS1", 1.0)  # (a new allocator)
    fw.reconfigure(table.firmware_config())
    assert fw.allocator.removed_rotor == 4 and fw.allocator.params.eps1_n == 1.0

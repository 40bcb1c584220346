"""A motor failure seen in the ESCs' telemetry (link_firmware_sim/motor_failure.py) and the
firmware's answer: the rotor left out of the allocation (SKL_CA_FAIL), reported, restored at disarm."""

import numpy as np
import pytest

from companion.skeleton.body import SkeletonConfig, link_inertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware
from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.motor_failure import (MAX_GAP_S, MIN_COMMAND_N, RECOVER_S, STOPPED_N, TEST_THRUST_N, TIMEOUT_S,
                                             MotorFailureDetector)
from link_firmware_sim.vehicle.params import ParamTable, StreamRates

DT = 0.002  # the firmware's 500 Hz tick
HOVER = np.array([3.25, -3.25] * 4)


def _feed(detector, seconds, reported_rotor=None, command=HOVER, t0=0.0, reported=0.0, back=None):
    """Ticks of ``seconds`` from ``t0``: ``command`` each, the ESCs reporting it but rotor
    ``reported_rotor`` at ``reported``; returns ``[(t, newly failed)]`` (``back``, a list: gets
    ``(t, working again)``) and the next tick's time."""
    found, k = [], 0
    while k * DT < seconds - 1e-12:
        t = t0 + k * DT
        rep = np.array(command, dtype=float)
        if reported_rotor is not None:
            rep[reported_rotor] = reported
        new, again = detector.update(t, command, rep)
        if new:
            found.append((t, new))
        if again and back is not None:
            back.append((t, again))
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


def test_a_failed_rotor_that_turns_again_works_after_recover_s():
    """A failed rotor commanded its test thrust: found working once it has turned for RECOVER_S
    (not for less), and failed again if it stops again."""
    det = MotorFailureDetector()
    _, t = _feed(det, 0.2, reported_rotor=3)
    assert det.failed == [3]
    test = HOVER.copy()
    test[3] = TEST_THRUST_N
    back = []
    _, t = _feed(det, RECOVER_S - 2 * DT, command=test, t0=t, back=back)  # turning, not long enough
    _, t = _feed(det, 0.05, reported_rotor=3, command=test, t0=t, back=back)
    assert back == [] and det.failed == [3]
    _, t = _feed(det, 1.0, command=test, t0=t, back=back)
    assert back == [(pytest.approx(t - 1.0 + RECOVER_S, abs=1e-9), [3])] and det.failed == []
    assert _feed(det, 0.2, reported_rotor=3, t0=t)[0] == [(pytest.approx(t + TIMEOUT_S, abs=1e-9), [3])]


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


def _telemetry(fw, seconds, rotor, t0=0.0, turning=False):
    """``seconds`` of ticks: the link's allocation of its hover wrench commanded, rotor ``rotor``
    reported stopped (or, ``turning``, following its command)."""
    t = t0
    while t < t0 + seconds:
        command = fw.allocator.allocate(fw.allocator.mapping_matrix @ HOVER).command_n
        reported = command.copy()
        if not turning:
            reported[rotor] = 0.0
        fw.on_esc_telemetry(t, command, reported)
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
        assert fw.allocator.removed_rotor == 6 and fw.rotor_out
        assert texts == [("reset", "Motor 7 failed: flying on the other seven")]
        r = fw.allocator.allocate(fw.allocator.mapping_matrix @ HOVER)
        assert r.command_n[6] == TEST_THRUST_N  # (its telemetry tells whether it turns again)
        np.testing.assert_allclose(fw.allocator.mapping_matrix @ r.command_n, fw.allocator.mapping_matrix @ HOVER,
                                   atol=1e-9)
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


def test_a_rotor_that_turns_again_rejoins_the_allocation():
    fw, _ = _armed_firmware()
    t = _telemetry(fw, 0.3, rotor=2)
    assert fw.rotor_out
    fw.events.clear()
    _telemetry(fw, RECOVER_S + 0.1, rotor=2, t0=t, turning=True)
    assert not fw.rotor_out and [(e.kind, e.text) for e in fw.events] == [
        ("recovered", "Motor 3 turns again: flying on all eight")]
    assert fw.allocator.allocate(fw.allocator.mapping_matrix @ HOVER).command_n[2] == pytest.approx(HOVER[2])


def test_a_parameter_change_keeps_the_rotor_out():
    fw, table = _armed_firmware()
    _telemetry(fw, 0.3, rotor=4)
    table.set("SKL_SM_EPS1", 1.0)  # (a new allocator)
    fw.reconfigure(table.firmware_config())
    assert fw.allocator.removed_rotor == 4 and fw.allocator.params.eps1_n == 1.0
    assert fw.allocator.test_thrust_n == TEST_THRUST_N

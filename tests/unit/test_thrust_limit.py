"""The firmware's thrust-limit report (link_firmware_sim.thrust_limit) and its events."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from link_firmware_sim.events import StatusEvent
from link_firmware_sim.thrust_limit import ThrustLimit, ThrustLimitConfig

DT = 0.002


def _fly(monitor, pattern, scale=0.8, t0=0.0):
    """Ticks at 500 Hz: ``pattern`` a list of (seconds, at_limit); returns [(t, event)]."""
    out, t = [], t0
    for seconds, at in pattern:
        for _ in range(int(round(seconds / DT))):
            t += DT
            out += [(t, ev) for ev in monitor.on_tick(t, DT, at, scale if at else 1.0)]
    return out


def test_an_episode_is_reported_once_with_its_scale_and_ends_after_the_clear_time():
    m = ThrustLimit()
    events = _fly(m, [(1.0, False), (0.1, True), (0.3, False),  # a blip: counted, not reported
                      (1.2, True), (0.2, False), (0.4, True),  # a short break: the same episode
                      (0.6, False)])
    assert [e.kind for _, e in events] == ["fault", "recovered"]
    (t_fault, fault), (t_ok, ok) = events
    assert t_fault == pytest.approx(1.4 + DT + 0.25, abs=1.01 * DT)  # warn_after_s into the run
    assert fault.text == "Rotors at thrust limit, wrench 80%"
    assert t_ok == pytest.approx(3.2 + DT + 0.5, abs=1.01 * DT) and ok.text == "Rotors within limit after 1.8 s"
    r = m.report()
    assert r == {"at_limit_s": pytest.approx(0.1 + 1.2 + 0.4), "episodes": 1, "min_scale": 0.8, "at_limit_now": False}


def test_the_smallest_scale_of_the_run_before_the_report_is_the_one_reported():
    m = ThrustLimit()
    ev = m.on_tick(0.0, DT, True, 0.5) + m.on_tick(0.1, DT, True, 0.9) + m.on_tick(0.3, DT, True, 0.7)
    assert [e.text for e in ev] == ["Rotors at thrust limit, wrench 50%"] and m.active
    assert m.report()["min_scale"] == 0.5


@pytest.mark.parametrize("warn,clear", [(0.1, 0.2), (0.5, 1.0)])
def test_the_times_are_configurable(warn, clear):
    m = ThrustLimit(ThrustLimitConfig(warn_after_s=warn, clear_after_s=clear))
    events = _fly(m, [(2.0, True), (2.0, False)])
    assert [t for t, _ in events] == [pytest.approx(DT + warn, abs=1.01 * DT), pytest.approx(2.0 + DT + clear, abs=1.01 * DT)]


def test_the_times_are_parameters_and_a_change_applies_at_once():
    """SKL_TLIM_WARN / SKL_TLIM_CLR (the parameter protocol's table) set the firmware's thrust
    limit times; a PARAM_SET reaches the running monitor (LinkFirmware.reconfigure)."""
    from companion.skeleton.body import SkeletonConfig, link_inertia
    from companion.skeleton.rotors import RotorGeometry
    from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware
    from link_firmware_sim.geo import GeoOrigin
    from link_firmware_sim.vehicle.params import ParamTable, StreamRates

    table = ParamTable(1, FirmwareConfig(), GeoOrigin(), StreamRates())
    assert (table.values["SKL_TLIM_WARN"], table.values["SKL_TLIM_CLR"]) == (0.25, 0.5)
    geometry = RotorGeometry.odar()
    fw = LinkFirmware(0, table.firmware_config(), link_inertia(SkeletonConfig(), geometry), geometry)
    table.set("SKL_TLIM_WARN", 1.0)
    table.set("SKL_TLIM_CLR", 0.1)
    fw.reconfigure(table.firmware_config())
    assert fw.thrust_limit.config == ThrustLimitConfig(warn_after_s=1.0, clear_after_s=0.1)
    events = _fly(fw.thrust_limit, [(0.9, True), (0.2, False), (1.5, True), (0.2, False)])
    assert [e.kind for _, e in events] == ["fault", "recovered"]  # the 0.9 s run at the limit is not reported
    assert [t for t, _ in events] == [pytest.approx(1.1 + DT + 1.0, abs=1.01 * DT), pytest.approx(2.6 + DT + 0.1, abs=1.01 * DT)]
    for name, bad in (("SKL_TLIM_WARN", 0.0), ("SKL_TLIM_CLR", 11.0)):
        with pytest.raises(ValueError, match=name):
            table.set(name, bad)


def test_bad_input_is_refused():
    with pytest.raises(ValueError):
        ThrustLimitConfig(warn_after_s=0.0)
    with pytest.raises(ValueError, match="non-finite"):
        ThrustLimit().on_tick(math.nan, DT, True)
    with pytest.raises(ValueError, match="at most 50"):
        StatusEvent("fault", "x" * 51)
    with pytest.raises(ValueError, match="kind"):
        StatusEvent("alarm", "x")


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 400), st.booleans(), st.floats(0.0, 1.0)), min_size=1, max_size=12))
def test_time_counted_episodes_alternate_hypothesis(runs):
    """Every tick at the limit is counted; reports alternate fault / recovered, one fault per
    episode, each after warn_after_s at the limit without a break."""
    m, t, total, since, kinds = ThrustLimit(), 0.0, 0.0, None, []
    for n, at, scale in runs:
        for _ in range(n):
            t += DT
            total += DT if at else 0.0
            since = (since if since is not None else t) if at else None
            for ev in m.on_tick(t, DT, at, scale):
                kinds.append(ev.kind)
                if ev.kind == "fault":
                    assert since is not None and t - since >= m.config.warn_after_s - 1e-12
    assert m.at_limit_s == pytest.approx(total)
    assert kinds == ["fault", "recovered"] * (len(kinds) // 2) + (["fault"] if len(kinds) % 2 else [])
    assert m.episodes == kinds.count("fault") and m.active == (len(kinds) % 2 == 1)
    assert np.isfinite(m.min_scale) and 0.0 <= m.min_scale <= 1.0


def test_each_event_kind_is_sent_at_its_mavlink_severity():
    """The severities the vehicle sends and the run logs are the dialect's MAV_SEVERITY values."""
    from companion.mavlink.dialect import load_dialect
    from link_firmware_sim.events import EVENT_KINDS, SEVERITY

    D = load_dialect()
    assert set(SEVERITY) == set(EVENT_KINDS)
    assert SEVERITY == {"fault": D.MAV_SEVERITY_WARNING, "reset": D.MAV_SEVERITY_CRITICAL, "recovered": D.MAV_SEVERITY_INFO}

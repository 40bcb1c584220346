"""Zenoh layer over real sessions on loopback: the global step (eq. 6 equal to the in-process
result), failover, CPG targets and carried links bit for bit, malformed payloads, a rogue without
the fleet's credentials, Zenoh's runtime setting."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from companion.fleetnet import codec
from companion.fleetnet.bus import FleetBus
from companion.fleetnet.config import ZenohConfig
from companion.fleetnet.group import GroupLink
from companion.fleetnet.keys import boundary_key, home_key, passive_key, shift_key, target_key
from companion.fleetnet.leader import GlobalStepNode
from companion.messages import ChainHome, GlobalShift, GroupBoundaryReport, GroupPassiveLinks

from ..clocks import FakeClock
from ..fleetnet_cases import LAYOUTS, PERIOD_US, chain_boundaries, equal, targets
from ..ports import free_ports
from ..waits import wait_for
from ..zenoh_peers import peer_session

BLOCK = zenoh.CongestionControl.BLOCK  # test payloads queued, never dropped under congestion


def _buses(n_groups: int, prefix: str):
    cfg = ZenohConfig(endpoints=tuple(f"tcp/127.0.0.1:{p}" for p in free_ports(n_groups)))
    buses = [FleetBus(cfg, prefix, g, n_groups) for g in range(n_groups)]
    return cfg, buses


def _pump(links, until, timeout_s=3.0, clock=time.monotonic):
    """Pump every open :class:`GroupLink` (the daemon's shell) until ``until(resolved)``, at most
    ``timeout_s`` of wall time; ``clock``: the time the links' deadlines run on."""
    deadline = time.monotonic() + timeout_s
    resolved = {lk.group: [] for lk in links}
    while time.monotonic() < deadline:
        for lk in links:
            if not lk.bus.closed:
                resolved[lk.group] += lk.pump(clock())
        if until(resolved):
            return resolved
        time.sleep(0.001)
    return resolved


def _probe_key(bus) -> str:
    return f"{bus.prefix}/probe/{bus.group}"


def _subscribed(buses) -> bool:
    """Whether every other session knows every bus's subscriptions by now. A group is alive to the
    others (its liveliness token) a moment before its subscriptions reach them, and a boundary or
    shift published in that moment is lost; Zenoh's matching status only says that some remote
    session subscribes to a key, not which. So each bus holds a probe subscriber of its own,
    declared after its real ones (:func:`_wait_live`), and every other session's publisher to that
    probe's key must match it: a session's declarations travel in order on its links, so the
    earlier ones have arrived too. (And each bus's own shift and boundary keys have a remote
    subscriber.)"""
    for bus in buses:
        for key in (shift_key(bus.prefix), boundary_key(bus.prefix, bus.group)):
            probe = bus.session.declare_publisher(key, allowed_destination=zenoh.Locality.REMOTE)
            try:
                if not probe.matching_status.matching:
                    return False
            finally:
                probe.undeclare()
    for sub in buses:
        for pub in buses:
            if pub is sub:
                continue
            probe = pub.session.declare_publisher(_probe_key(sub), allowed_destination=zenoh.Locality.REMOTE)
            try:
                if not probe.matching_status.matching:
                    return False
            finally:
                probe.undeclare()
    return True


def _wait_live(links, n):
    """Pump until every open link sees ``n`` groups alive and their subscriptions are in place."""
    _pump(links, lambda r: all(len(lk.node.live) == n for lk in links if not lk.bus.closed))
    buses = [lk.bus for lk in links if not lk.bus.closed]
    probes = [bus.session.declare_subscriber(_probe_key(bus), lambda sample: None) for bus in buses]
    try:
        assert wait_for(lambda: _subscribed(buses), 5.0), "subscriptions missing"
    finally:
        for probe in probes:
            probe.undeclare()


def _two_live_links(cfg, buses) -> list[GroupLink]:
    """The group links of two Zenoh buses, once each sees the other alive and subscribed."""
    links = [GroupLink(GlobalStepNode(g, 2, cfg.order(2), PERIOD_US, startup_s=0.0), bus) for g, bus in enumerate(buses)]
    _wait_live(links, 2)
    return links


def test_cpg_targets_cross_zenoh_bit_for_bit_and_misplaced_ones_are_errors():
    """The leader's ChainTargets reach another group's companion unchanged; a target payload on
    the shift key (or a shift on the target key) is an error, never applied."""
    cfg, buses = _buses(2, "test_targets")
    try:
        links = _two_live_links(cfg, buses)
        rng = np.random.default_rng(5)
        sent = [targets(rng, tuple(range(7)), time_us=20_000 * k, seq=k) for k in range(50)]
        for msg in sent:
            links[1].publish_targets(msg)
        shift = GlobalShift(1, 0, (0,), np.zeros((1, 6)), hold_us=(0,))
        put = buses[1].session.put
        put(shift_key("test_targets"), codec.encode(sent[0]), congestion_control=BLOCK)  # on the shift key
        put(target_key("test_targets"), codec.encode(shift), congestion_control=BLOCK)  # on the target key
        got = []
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and len(got) < len(sent):
            links[0].pump(time.monotonic())
            got += links[0].take_targets()
            time.sleep(0.005)
        assert len(got) == len(sent)
        assert all(equal(a, b) for a, b in zip(got, sent))
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and sum(links[0].errors.values()) < 2:
            links[0].pump(time.monotonic())
            time.sleep(0.005)
        assert links[0].errors == {shift_key("test_targets"): 1, target_key("test_targets"): 1}
        assert links[0].take_targets() == []
    finally:
        for bus in buses:
            bus.close()


@pytest.mark.parametrize("kind", ["passive", "home"])
def test_a_groups_carried_links_and_home_cross_zenoh_and_one_on_another_groups_key_is_an_error(kind):
    """A group's GroupPassiveLinks (empty sets too) and ChainHome reach the other group's companion
    unchanged; one published on another group's key is an error, never taken."""
    prefix = f"test_{kind}"
    cfg, buses = _buses(2, prefix)
    try:
        links = _two_live_links(cfg, buses)
        if kind == "passive":
            sent = [GroupPassiveLinks(1, 20_000 * k, (2,) if k % 2 else ()) for k in range(20)]
            key_of, publish, take = passive_key, links[1].publish_passive, links[0].take_passive
        else:
            sent = [ChainHome(1, 1_000_000 * k, np.array([0.3, -0.2, 1.5 + k])) for k in range(5)]
            key_of, publish, take = home_key, links[1].publish_home, links[0].take_home
        for msg in sent:
            publish(msg)
        put = buses[1].session.put
        put(boundary_key(prefix, 1), codec.encode(sent[1]), congestion_control=BLOCK)  # on its boundary key
        put(key_of(prefix, 0), codec.encode(sent[1]), congestion_control=BLOCK)  # on group 1's key
        got = []
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and (len(got) < len(sent) or sum(links[0].errors.values()) < 2):
            links[0].pump(time.monotonic())
            got += take()
            time.sleep(0.005)
        assert len(got) == len(sent) and all(equal(a, b) for a, b in zip(got, sent))
        assert links[0].errors == {boundary_key(prefix, 1): 1, key_of(prefix, 0): 1}
        assert links[0].alive(1) and not take()
    finally:
        for bus in buses:
            bus.close()


def test_runtime_threads_give_a_zenoh_runtime_setting_zenoh_accepts():
    assert ZenohConfig(runtime_threads=0).runtime_env() is None
    env = ZenohConfig(runtime_threads=2).runtime_env()
    assert "rx: (worker_threads: 2)" in env and "tx: (worker_threads: 2)" in env
    with pytest.raises(ValueError, match="runtime_threads"):
        ZenohConfig(runtime_threads=99)
    code = ("import zenoh; c = zenoh.Config(); c.insert_json5('scouting/multicast/enabled', 'false'); "
            "c.insert_json5('listen/endpoints', '[]'); zenoh.open(c).close(); print('ok')")
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "ZENOH_RUNTIME": env},
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-500:]


@pytest.mark.parametrize("groups", LAYOUTS[:2])
def test_global_step_over_zenoh_equals_in_process_eq6(groups):
    """One cycle's global step over Zenoh gives every group eq. 6's shift. The nodes' deadlines run
    on a clock that stands still (:class:`tests.clocks.FakeClock`): however slow the host, no
    group gives up waiting; only the wall-time bound of the pumping ends the wait."""
    s = len(groups)
    ref, reports = chain_boundaries(11, groups)
    cfg, buses = _buses(s, f"test_eq6_{s}")
    links = [GroupLink(GlobalStepNode(g, s, cfg.order(s), PERIOD_US, startup_s=0.0, shift_deadline_s=2.0,
                                      leader_wait_s=1.5), bus) for g, bus in enumerate(buses)]
    try:
        _wait_live(links, s)
        clock = FakeClock(time.monotonic())
        early = {lk.group: lk.local_step(r.left_tip_pv_w, r.right_tip_pv_w, r.info_pv, PERIOD_US, clock())
                 for lk, r in zip(links, reports)}
        resolved = _pump(links, lambda r: all(r[g] or early[g] for g in range(s)), timeout_s=30.0, clock=clock)
        resolved = {g: early[g] + resolved[g] for g in range(s)}
        for g in range(s):
            (res,) = resolved[g]
            assert res.shift is not None, res.reason
            np.testing.assert_allclose(res.shift, ref.shifts[g], rtol=0, atol=1e-9)
            assert res.leader_group == cfg.order(s)[0]
    finally:
        for bus in buses:
            bus.close()


def test_leader_failover_over_zenoh_within_two_cycles(compiled_kernels):
    """Three groups on real deadlines (0.2 s): every cycle gets the leader's step before its
    computer goes away, at most two after. The compiled kernels are loaded first, as the daemon
    loads them before its first cycle: a first eq. 6 solve that loads them would miss the deadline.
    One cycle is flown first and not scored: under a loaded test run the first exchange on the new
    sessions (their first samples, the code paths' first calls) can take longer than a deadline."""
    groups = LAYOUTS[0]
    ref, reports = chain_boundaries(5, groups)
    cfg, buses = _buses(3, "test_failover")
    links = [GroupLink(GlobalStepNode(g, 3, cfg.order(3), PERIOD_US, startup_s=0.0, shift_deadline_s=0.2,
                                      leader_wait_s=0.15), bus) for g, bus in enumerate(buses)]
    try:
        _wait_live(links, 3)
        warm = {lk.group: lk.local_step(reports[lk.group].left_tip_pv_w, reports[lk.group].right_tip_pv_w,
                                        reports[lk.group].info_pv, 0, time.monotonic()) for lk in links}
        _pump(links, lambda r: all(any(x.cycle_us == 0 and x.leader_group is not None for x in r[g] + warm[g])
                                   for g in r))
        outcome = []  # per cycle: did every live group get the global step?
        for k in range(1, 13):
            if k == 6:
                links[1].close()  # the leader's computer goes away mid-run
            cycle = k * PERIOD_US
            alive = [lk for lk in links if not lk.bus.closed]
            now = time.monotonic()
            early = {lk.group: lk.local_step(reports[lk.group].left_tip_pv_w, reports[lk.group].right_tip_pv_w,
                                             reports[lk.group].info_pv, cycle, now) for lk in alive}
            resolved = _pump(alive, lambda r: all(any(x.cycle_us == cycle for x in r[g] + early[g]) for g in r))
            # did every live group get the leader's answer for this cycle?
            mine = {g: [x for x in resolved[g] + early[g] if x.cycle_us == cycle] for g in resolved}
            outcome.append(all(any(x.leader_group is not None for x in xs) for xs in mine.values()))
            if k >= 9:  # groups 1 and 3 are not neighbours: the leader's answer is no shift, not a zero one
                assert all(x.shift is None and "no neighbouring group" in x.reason
                           for xs in mine.values() for x in xs if x.leader_group is not None)
        assert all(outcome[:5])
        missed = [k for k, ok in enumerate(outcome[5:]) if not ok]
        assert len(missed) <= 2 and all(outcome[8:]), outcome
        for lk in (links[0], links[2]):  # group 1 is next in the order (2, 1, 3)
            assert lk.node.leader_log[-1][1] == 0
            (fo,) = lk.failovers
            assert fo["from"] == 2 and fo["to"] == 1 and fo["first_global_after_s"] < 1.0
    finally:
        for lk in links:
            lk.close()


def test_malformed_zenoh_payloads_are_counted_not_applied():
    cfg, buses = _buses(2, "test_garbage")
    raw = peer_session(connect=(cfg.endpoints[0],))
    try:
        _two_live_links(cfg, buses)  # (both see each other alive)
        good = codec.encode(GroupBoundaryReport(1, PERIOD_US, np.zeros(6), np.zeros(6), np.eye(6)))
        payloads = [b"", b"garbage", good[:-1], good[:4] + bytes([codec.VERSION + 1]) + good[5:],
                    struct.pack("<4sBB", b"ASKZ", codec.VERSION, 4) + b"\xff" * 10]
        for p in payloads:
            raw.put(boundary_key("test_garbage", 1), p, congestion_control=BLOCK)
            raw.put(shift_key("test_garbage"), p, congestion_control=BLOCK)
        raw.put(boundary_key("test_garbage", 0), good, congestion_control=BLOCK)  # valid, on the wrong group's key
        deadline = time.monotonic() + 3.0
        events = []
        while time.monotonic() < deadline and sum(e.kind == "error" for e in events) < 2 * len(payloads) + 1:
            events += buses[0].drain()
            time.sleep(0.01)
        errors = [e for e in events if e.kind == "error"]
        assert len(errors) == 2 * len(payloads) + 1
        assert any(f"version {codec.VERSION + 1}" in e.value for e in errors) and any("does not belong" in e.value for e in errors)
        assert not [e for e in events if e.kind in ("boundary", "shift")]
    finally:
        raw.close()
        for bus in buses:
            bus.close()


def test_a_session_without_the_fleet_credentials_cannot_join(tmp_path):
    """zenoh.users_file: the group companions authenticate to each other; a rogue session on this
    host (no credentials, a wrong password, an unknown user) opens no transport to them, so its
    well-formed shifts and boundaries never arrive, while the fleet's own do."""
    from companion.fleetnet.config import new_users_file, read_users_file

    users = tmp_path / "zenoh_users.txt"
    new_users_file(users, 2)
    assert set(read_users_file(str(users))) == {"companion-g1", "companion-g2"}
    cfg = ZenohConfig(endpoints=tuple(f"tcp/127.0.0.1:{p}" for p in free_ports(2)), users_file=str(users))
    buses = [FleetBus(cfg, "test_auth", g, 2) for g in range(2)]
    rogues = []
    try:
        for user, password in ((None, None), ("companion-g2", "x" * 20), ("rogue", "y" * 20)):
            auth = {"transport__auth__usrpwd__user": user, "transport__auth__usrpwd__password": password} if user else {}
            rogues.append(peer_session(connect=(cfg.endpoints[0],), **auth))
        _two_live_links(cfg, buses)  # (both see each other alive)
        fake = codec.encode(GlobalShift(1, PERIOD_US, (0, 1), np.ones((2, 6)), hold_us=(0, 0)))
        forged = codec.encode(GroupBoundaryReport(1, PERIOD_US, np.ones(6), np.ones(6), np.eye(6)))
        for r in rogues:
            for _ in range(5):
                r.put(shift_key("test_auth"), fake)
                r.put(boundary_key("test_auth", 1), forged)
        buses[1].publish_boundary(GroupBoundaryReport(1, 2 * PERIOD_US, np.zeros(6), np.zeros(6), np.eye(6)))
        deadline = time.monotonic() + 3.0
        events = []
        while time.monotonic() < deadline and not any(e.kind == "boundary" for e in events):
            events += buses[0].drain()
            time.sleep(0.01)
        time.sleep(0.3)
        events += buses[0].drain()
        got = [(e.kind, e.value.cycle_us) for e in events if e.kind in ("boundary", "shift")]
        assert got == [("boundary", 2 * PERIOD_US)]  # the fleet's own only
        assert not [e for e in events if e.kind == "error"]
    finally:
        for r in rogues:
            r.close()
        for bus in buses:
            bus.close()


def test_a_listen_address_not_up_yet_is_tried_again_then_named(caplog):
    """A group companion started before its computer's network is up (a Pi at boot): its listen
    address is tried again every second, saying so, instead of the companion exiting; with a
    limit, the error names zenoh.listen. Another error ends it at once."""
    from companion.configfile import ConfigError
    from companion.fleetnet.bus import ADDRESS_RETRY_S, open_group_session

    clock = FakeClock()
    sleeps = []

    def sleep(s):
        sleeps.append(s)
        clock.t += s

    port = free_ports(1)[0]
    cfg = ZenohConfig(endpoints=(f"tcp/10.255.255.1:{port}",))  # an address no interface holds
    with pytest.raises(ConfigError) as info:
        open_group_session(cfg, 0, 1, "fleet.toml", wait_s=12.0, clock=clock, sleep=sleep)
    assert info.value.key == "zenoh.listen" and "Cannot assign requested address" in info.value.reason
    assert sleeps == [ADDRESS_RETRY_S] * 12 and f"10.255.255.1:{port} is not up on this computer yet" in caplog.text
    sleeps.clear()
    import socket

    taken = socket.socket()
    try:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        busy = ZenohConfig(endpoints=(f"tcp/127.0.0.1:{taken.getsockname()[1]}",))
        with pytest.raises(ConfigError) as info:  # another process's port: no retry
            open_group_session(busy, 0, 1, "fleet.toml", wait_s=12.0, clock=clock, sleep=sleep)
    finally:
        taken.close()
    assert info.value.key == "zenoh" and sleeps == []

"""Inputs shared by the tests of the companion engine (tests/unit/test_engine*.py): a companion
setup, a straight chain's link states, feeding them to an engine, and a distributed setup's group
engines on one in-process bus, and flying them on it."""

from __future__ import annotations

import numpy as np

from companion.config import CompanionConfig, CompanionSetup, LinkEndpoint
from companion.engine import CompanionEngine, CorrectionOut
from companion.estimation.so3 import quat_from_euler_zyx
from companion.fleetnet.group import GroupLink
from companion.fleetnet.hub import LocalHub
from companion.fleetnet.leader import GlobalStepNode
from companion.messages import STATE_FLAG_EKF_OK, LinkState
from companion.skeleton.body import SkeletonConfig
from companion.trajectory import TrajectoryConfig


def setup_for(n=3, groups=(), **companion) -> CompanionSetup:
    """A companion config: ``n`` links of 1 m, the paper's bending flight as targets."""
    links = tuple(LinkEndpoint(i + 1, f"udpin://127.0.0.1:{15000 + i}") for i in range(n))
    return CompanionSetup(name="engine_test", skeleton=SkeletonConfig(n_links=n),
                          companion=CompanionConfig(links=links, groups=groups, **{"arm": True, **companion}),
                          trajectory=TrajectoryConfig(kind="bend", takeoff_altitude_m=2.5, bend_start_s=20.0))


def straight_state(i, n, t, dx=0.0, L=1.0):
    p = np.array([(i - (n - 1) / 2) * L + dx, 0.0, 2.0])
    return LinkState(i, t, p, np.zeros(3), quat_from_euler_zyx(0.0, 0.0, 0.0), np.zeros(3),
                     np.diag([0.04] * 6 + [1e-3] * 3))


def of(kind, outputs):
    return [o for o in outputs if isinstance(o, kind)]


def feed(engine, t, now, dx=None, flags=STATE_FLAG_EKF_OK, offsets=None):
    for lk in engine.links:
        off = offsets[lk.row] if offsets is not None else 0.0
        engine.on_state(lk.row, straight_state(lk.index, engine.n, t + off, 0.0 if dx is None else dx[lk.row]), flags,
                        now)
    return engine.poll(now)


def group_engines(setup: CompanionSetup, clock, **node) -> tuple[LocalHub, list[CompanionEngine]]:
    """One engine per group of a distributed ``setup``, joined by a :class:`LocalHub` (batch mode's
    bus) on ``clock``; ``node``: the global step's settings (default: a 35 ms shift deadline, the
    leader waiting 25 ms)."""
    n_groups = len(setup.companion.group_layout(setup.skeleton.n_links))
    hub = LocalHub(n_groups, clock)
    settings = {"shift_deadline_s": 0.035, "leader_wait_s": 0.025, **node}
    engines = [CompanionEngine(setup, group=g, start_center=(0.0, 0.0, 2.0),
                               net=GroupLink(GlobalStepNode(g, n_groups, setup.zenoh.order(n_groups), 50_000, **settings),
                                             hub.join(g), clock))
               for g in range(n_groups)]
    return hub, engines


def fly_group_engines(engines, clock, states_at, cycles: int = 16, heard=lambda k, i: True,
                      before=None) -> dict:
    """Distributed ``engines`` on their bus for ``cycles`` companion periods of 50 ms on ``clock``
    (a one-element list): each period ``before(k, t)`` first (when given), every link's state
    from ``states_at(t)`` (those ``heard(k, link index)``), then six polls of every engine; the
    corrections by ``(period, link index)``."""
    got = {}
    for k in range(cycles):
        t = clock[0] = 0.05 * k
        if before is not None:
            before(k, t)
        states = states_at(t)
        for e in engines:
            for lk in e.links:
                if heard(k, lk.index):
                    e.on_state(lk.row, states[lk.index], STATE_FLAG_EKF_OK, t)
        for _ in range(6):
            for e in engines:
                for out in of(CorrectionOut, e.poll(t)):
                    got[(k, e.links[out.row].index)] = out.correction
    return got

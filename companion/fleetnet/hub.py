"""Bus events, and an in-process bus for group companions that run in one process (pure).

:class:`BusEvent` is what a bus hands a :class:`~.group.GroupLink`: a decoded message, a
liveliness change or an error. :class:`LocalHub` connects the group engines of a batch-mode
flight the way Zenoh connects the daemons of a fleet: every message goes through the binary codec
(:mod:`.codec`), so the shifts and targets a group receives are the wire's, bit for bit; every
group sees the others come alive when it joins and leave when they close. Delivery is immediate
and in publication order, so a batch flight stays deterministic. A payload is decoded (and
validated) once and the receivers share the message: frozen, its arrays read-only.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from companion.messages import ChainHome, ChainTargets, GlobalShift, GroupBoundaryReport, GroupPassiveLinks

from . import codec

__all__ = ["BusEvent", "KINDS", "LocalHub", "LocalBus"]

#: the event kind of each message type (one table for both buses)
KINDS = {GroupBoundaryReport: "boundary", GlobalShift: "shift", ChainTargets: "targets", GroupPassiveLinks: "passive",
         ChainHome: "home"}


@dataclass(frozen=True)
class BusEvent:
    """One thing that arrived: ``kind`` is ``boundary``, ``shift``, ``targets``, ``passive``, ``home``, ``alive``,
    ``gone`` or ``error``;
    ``value`` the decoded message, the group (liveliness) or the error text; ``time_s`` the
    arrival time on the receiver's clock; ``key`` the key expression it came on."""

    kind: str
    value: Any
    time_s: float
    key: str


class LocalHub:
    """The in-process network of ``n_groups`` group companions; ``clock()`` stamps arrivals."""

    def __init__(self, n_groups: int, clock, prefix: str = "local"):
        self.clock = clock
        self.prefix = prefix
        self.buses: dict[int, LocalBus] = {}
        self.n_groups = n_groups

    def join(self, group: int) -> LocalBus:
        """The bus of 0-based ``group`` (it and the groups already there see each other come alive)."""
        if group in self.buses or not 0 <= group < self.n_groups:
            raise ValueError(f"group {group} cannot join (joined: {sorted(self.buses)}, groups 0..{self.n_groups - 1})")
        bus = LocalBus(self, group)
        now = self.clock()
        for other in self.buses.values():
            other.events.append(BusEvent("alive", group, now, f"{self.prefix}/group/{group + 1}/alive"))
            bus.events.append(BusEvent("alive", other.group, now, f"{self.prefix}/group/{other.group + 1}/alive"))
        self.buses[group] = bus
        return bus

    def pending(self) -> bool:
        """Whether any bus has undelivered events."""
        return any(bus.events for bus in self.buses.values())

    def _send(self, sender: int, message, key: str) -> None:
        receivers = [bus for group, bus in self.buses.items() if group != sender]
        payload = codec.encode(message)
        now = self.clock()
        if not receivers:
            return
        msg = _read_only(codec.decode(payload))  # one decode for all: the validation is most of its cost
        for bus in receivers:
            bus.events.append(BusEvent(KINDS[type(msg)], msg, now, key))

    def _leave(self, group: int) -> None:
        self.buses.pop(group, None)
        now = self.clock()
        for bus in self.buses.values():
            bus.events.append(BusEvent("gone", group, now, f"{self.prefix}/group/{group + 1}/alive"))


def _read_only(msg):
    """``msg`` (a frozen message) with its arrays made read-only, so that the groups sharing it
    cannot change it for one another."""
    for f in fields(msg):
        value = getattr(msg, f.name)
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
    return msg


class LocalBus:
    """One group's end of a :class:`LocalHub` (the interface of :class:`~.bus.FleetBus`)."""

    def __init__(self, hub: LocalHub, group: int):
        self.hub = hub
        self.group = group
        self.events: list[BusEvent] = []

    def pending(self) -> bool:
        """Whether events wait to be drained."""
        return bool(self.events)

    def drain(self) -> list[BusEvent]:
        out, self.events = self.events, []
        return out

    def publish_boundary(self, report: GroupBoundaryReport) -> None:
        self.hub._send(self.group, report, f"{self.hub.prefix}/group/{self.group + 1}/boundary")

    def publish_shift(self, shift: GlobalShift) -> None:
        self.hub._send(self.group, shift, f"{self.hub.prefix}/global/shift")

    def publish_targets(self, targets: ChainTargets) -> None:
        self.hub._send(self.group, targets, f"{self.hub.prefix}/cpg/target")

    def publish_passive(self, passive: GroupPassiveLinks) -> None:
        self.hub._send(self.group, passive, f"{self.hub.prefix}/group/{self.group + 1}/passive")

    def publish_home(self, home: ChainHome) -> None:
        self.hub._send(self.group, home, f"{self.hub.prefix}/group/{self.group + 1}/home")

    def close(self) -> None:
        self.hub._leave(self.group)

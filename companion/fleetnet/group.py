"""A group companion's global-step wiring: a :class:`~.leader.GlobalStepNode` on a bus.

:class:`GroupLink` is the thin shell around the pure node that the companion engine, the Zenoh
benchmark and batch mode run; the bus (:class:`~.bus.FleetBus` over Zenoh, or
:class:`~.hub.LocalBus` in one process) and the clock are passed in. It hands what arrives on the bus to the node, publishes what
the node decides, and returns the cycles that ended (:class:`~.leader.Resolution`) for the caller to turn
into corrections. It also keeps the operational record: malformed payloads per key, leader
failovers (from the moment the acting leader's token went to the first cycle with a global
step again, and the cycles without one in between) and the round trips reported while leading.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace


from companion.messages import ChainHome, ChainTargets, GroupPassiveLinks
from companion.quantiles import Quantiles

from .leader import GlobalStepNode
from .outcomes import Actions, PartBoundary, Resolution

__all__ = ["GroupLink", "percentiles"]

log = logging.getLogger(__name__)


def percentiles(values_ms: Quantiles) -> dict | None:
    """p50, p99, max and the count of a sketch's samples (``None`` without any)."""
    if not values_ms.count:
        return None
    return {"p50": values_ms.percentile(50), "p99": values_ms.percentile(99), "max": values_ms.max,
            "samples": values_ms.count}


class GroupLink:
    """See the module docstring."""

    def __init__(self, node: GlobalStepNode, bus, clock=time.monotonic):
        self.node = node
        self.bus = bus
        self.clock = clock
        self.errors: dict[str, int] = {}
        self.failovers: list[dict] = []
        self._failover: dict | None = None
        #: the round trips the groups reported while this one led [ms], in fixed memory
        self.round_trips_ms = Quantiles()
        self.network_round_trips_ms = Quantiles()
        self._targets_in: list[ChainTargets] = []
        self._passive_in: list[GroupPassiveLinks] = []
        self._home_in: list[ChainHome] = []

    @property
    def group(self) -> int:
        return self.node.group

    def fileno(self) -> int:
        return self.bus.fileno()

    def next_deadline_s(self, now_s: float) -> float | None:
        """When :meth:`pump` next has something to do without new input (:meth:`GlobalStepNode.next_deadline_s`)."""
        return self.node.next_deadline_s(now_s)

    def needs_pump(self, now_s: float) -> bool:
        """Whether :meth:`pump` at ``now_s`` has anything to do: an event waiting on the bus or a
        deadline of the node's reached (``False``: a pump would change nothing and return nothing)."""
        return self.bus.pending() or self.node.due(now_s)

    def leads(self, cycle_us: int, now_s: float) -> bool:
        """Whether this group leads ``cycle_us`` (and so generates the CPG targets)."""
        return self.node.leader_for(cycle_us, now_s) == self.group

    def publish_targets(self, targets: ChainTargets) -> None:
        self.bus.publish_targets(targets)

    def take_targets(self) -> list[ChainTargets]:
        """The CPG targets that arrived since the last call (oldest first)."""
        out, self._targets_in = self._targets_in, []
        return out

    def publish_passive(self, passive: GroupPassiveLinks) -> None:
        self.bus.publish_passive(passive)

    def take_passive(self) -> list[GroupPassiveLinks]:
        """The other groups' carried links that arrived since the last call (oldest first)."""
        out, self._passive_in = self._passive_in, []
        return out

    def publish_home(self, home: ChainHome) -> None:
        self.bus.publish_home(home)

    def take_home(self) -> list[ChainHome]:
        """The homes the other groups published since the last call (oldest first)."""
        out, self._home_in = self._home_in, []
        return out

    def alive(self, group: int) -> bool:
        """Whether 0-based ``group``'s companion is up (its liveliness token is there)."""
        return group in self.node.live

    def local_step(self, left_tip_pv_w, right_tip_pv_w, info_pv, cycle_us: int, now_s: float,
                   tip_cov_pv=None) -> list[Resolution]:
        """This group's boundary for ``cycle_us``: publish it (and solve, if leading)."""
        return self._carry_out(self.node.local_step(left_tip_pv_w, right_tip_pv_w, info_pv, cycle_us, now_s,
                                                    tip_cov_pv), now_s)

    def local_parts(self, parts: list[PartBoundary], cycle_us: int, now_s: float) -> list[Resolution]:
        """This group's boundaries for ``cycle_us``, one per part (a link down or left out split
        it): publish them (and solve, if leading)."""
        return self._carry_out(self.node.local_parts(parts, cycle_us, now_s), now_s)

    def pump(self, now_s: float) -> list[Resolution]:
        """Everything that arrived, then the deadlines; the cycles that ended."""
        resolved = []
        for ev in self.bus.drain():
            if ev.kind == "boundary":
                resolved += self._carry_out(self.node.on_boundary(ev.value, now_s, ev.time_s), now_s)
            elif ev.kind == "shift":
                resolved += self._carry_out(self.node.on_shift(ev.value, now_s, ev.time_s), now_s)
            elif ev.kind == "targets":
                self._targets_in.append(ev.value)
            elif ev.kind == "passive":
                self._passive_in.append(ev.value)
            elif ev.kind == "home":
                self._home_in.append(ev.value)
            elif ev.kind in ("alive", "gone"):
                alive = ev.kind == "alive"
                if ev.value != self.group:
                    log.info("group %d: group %d %s", self.group + 1, ev.value + 1, "is up" if alive else "left")
                # the leader whose shifts were last applied (the node may already have passed over
                # a silent leader, clearing ``acting``, before its token disappears)
                last = self.node.leader_log[-1][1] if self.node.leader_log else None
                if not alive and ev.value in (self.node.acting, last) and ev.value != self.group:
                    self._failover = {"from": ev.value + 1, "gone_at": ev.time_s, "cycles_without_global": 0}
                self.node.on_liveliness(ev.value, alive, ev.time_s)
            else:
                n = self.errors[ev.key] = self.errors.get(ev.key, 0) + 1
                if n <= 5 or n % 100 == 0:
                    log.warning("zenoh %s: dropped payload #%d: %s", ev.key, n, ev.value)
        return resolved + self._carry_out(self.node.tick(now_s), now_s)

    def _carry_out(self, actions: Actions, now_s: float) -> list[Resolution]:
        for boundary in actions.boundaries:
            self.bus.publish_boundary(boundary)
        for shift in actions.shifts:
            # the node measured its hold up to ``now_s``; the groups subtract it up to the put
            extra_us = int(round((self.clock() - now_s) * 1e6))
            self.bus.publish_shift(replace(shift, hold_us=tuple(h + extra_us for h in shift.hold_us)))
        for res in actions.resolved:
            fo = self._failover
            if fo is None:
                continue
            if res.leader_group is not None and res.leader_group + 1 != fo["from"]:
                # the new leader answered (with a shift, or with none: no neighbouring group left)
                fo.update(to=res.leader_group + 1, cycle_us=res.cycle_us,
                          first_global_after_s=round(now_s - fo["gone_at"], 4), global_step=res.shift is not None)
                self._failover = None
                self.failovers.append(fo)
                log.warning("leader failover: group %d -> group %d, %s %.0f ms after the leader left, "
                            "%d cycle(s) without it", fo["from"], fo["to"],
                            "global step back" if res.shift is not None else "the new leader answered (no neighbouring "
                            "group: local-only)", fo["first_global_after_s"] * 1e3, fo["cycles_without_global"])
            elif res.shift is None:
                fo["cycles_without_global"] += 1
        node = self.node
        for x in node.round_trips_us:
            self.round_trips_ms.add(x * 1e-3)
        for x in node.network_round_trips_us:
            self.network_round_trips_ms.add(x * 1e-3)
        node.round_trips_us, node.network_round_trips_us = [], []
        return actions.resolved

    def status_line(self) -> str:
        node = self.node
        leader = node.leader_log[-1][1] + 1 if node.leader_log else None
        text = (f"group {self.group + 1}: leader {leader if leader is not None else '-'}, cycles with global step "
                f"{node.counts['global']}, local-only {node.counts['local_only']}, malformed payloads "
                f"{sum(self.errors.values())}")
        net, e2e = percentiles(self.network_round_trips_ms), percentiles(self.round_trips_ms)
        if net and e2e:
            text += (f"; as leader: Zenoh global-step round trip (boundary published -> shift received, less the "
                     f"leader's wait for the other groups) p50 {net['p50']:.2f} ms, p99 {net['p99']:.2f} ms; end to "
                     f"end p50 {e2e['p50']:.2f} ms, p99 {e2e['p99']:.2f} ms ({e2e['samples']} boundaries)")
        return text

    def summary(self) -> dict:
        node = self.node
        e2e = percentiles(self.round_trips_ms)
        return {
            "group": self.group + 1,
            "global_step": {**node.counts, "rejected_shift_by_reason": dict(node.rejections),
                            "leaders": [[c * 1e-6, g + 1] for c, g in node.leader_log],
                            "duplicates": [{"cycle_s": c * 1e-6, "applied_from": a + 1, "second_from": b + 1,
                                            "second_live": live} for c, a, b, live in node.duplicates]},
            "round_trip_ms_as_leader": ({"network": percentiles(self.network_round_trips_ms), "end_to_end": e2e}
                                        if e2e else None),
            "failovers": self.failovers,
            "malformed_payloads": dict(self.errors),
        }

    def close(self) -> None:
        self.bus.close()

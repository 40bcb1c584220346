"""One companion's part in the networked global step: leader election and eq. 6 (pure).

:class:`GlobalStepNode` is a state machine with no clock, sockets or threads: the daemon feeds
it what arrives (boundaries, shifts, liveliness changes) and the monotonic time, and carries
out the :class:`Actions` it returns. Per cycle (one 20 Hz step, identified by its step time on
the flight-controller clock):

1. every group, after its local constraint application (Alg. 2), publishes its
   :class:`~companion.messages.GroupBoundaryReport` (:meth:`GlobalStepNode.local_step`), or one
   per part when a link down or left out splits it (:meth:`GlobalStepNode.local_parts`);
2. the leader solves eq. 6 (:func:`~companion.fleetnet.solve.solve_cycle`) once every part of
   every live group has reported, or ``leader_wait_s`` after the first report of the cycle with
   the parts it has (each run of joined parts is solved on its own: a missing group or a link
   down splits the chain, and each part of a split group is joined to the neighbouring group it
   touches), and publishes one :class:`~companion.messages.GlobalShift`;
3. each group applies its parts' shifts; if none has arrived ``shift_deadline_s`` after it
   published its boundaries, it sends its local-only corrections for that cycle (degrades,
   never stalls).

Leadership. Groups are ranked by a configured preference order; each companion holds a
liveliness token. The *acting* leader is the one whose shifts are being received. When the
acting leader's token disappears, the first live group in the order leads from the next cycle
(failover takes the token's disappearance plus at most one cycle). A companion that (re)joins
first listens for ``startup_s`` (and, with no acting leader, again for ``startup_s`` after
each group it sees come up, before it leads itself: its session may reach the others only
later): if shifts are flowing it follows the acting leader, even if it ranks higher; the acting leader then names it in its shifts as ``handover_group`` with a
``handover_cycle_us`` ``handover_cycles`` cycles ahead, and leads up to the cycle before.
Leadership thus only changes at a cycle both sides agreed on, so a returning leader never
makes two leaders in one cycle: asking who leads a later cycle changes nothing, the hand-over
is committed when a cycle from the agreed one on settles, and a cycle before it that is still
open in a lagging group stays the old leader's. Should two leaders still meet (a partition that heals), the
one ranked lower yields on seeing the other's shift, and every group applies only the first
shift of a cycle.

Trust (every payload is hostile until checked; a rogue session on the bus can publish
well-formed messages under any group's name). A shift is applied only if it answers the
cycle this group is waiting on (a shift for a cycle not reached yet never settles it, unless it
comes from the elected leader, leaves this group out, and checks out against the listed groups'
boundaries: the leader solved without it), comes from the leader this group elected for that
cycle, stays within ``max_shift_p_m`` / ``max_shift_v_m_s``, and is eq. 6 of the listed groups'
boundaries (each group receives every boundary; a shift that arrives before one of them waits
for it, at most :data:`_MAX_HELD` per cycle, until the deadline): anything else is counted
(``rejected_shift``, and ``rejections`` by reason: not_leader, not_pending, bounds, inconsistent,
unverifiable, conflicted, unknown_group) and dropped. Two different boundaries under one group's
name for one cycle are a conflict: that group is left out of the cycle. A leader whose shifts
stop arriving for ``leader_silence_cycles`` cycles (counted once it has been live longer than
its own start-up listening) is passed over in the election until a shift of its own is
accepted again; only a shift that checks out counts as hearing from it (or one that cannot be
checked because of a conflicting boundary), so forged shifts in a silent leader's name do not
hide its silence, and no message (a fake yield, a liveliness token without a companion behind
it) can wedge the election.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.messages import GlobalShift, GroupBoundaryReport

from .outcomes import Actions, PartBoundary, PartShift, Resolution
from .solve import runs, shift_covariance_terms, solve_cycle

log = logging.getLogger(__name__)

__all__ = ["PartBoundary", "PartShift", "Resolution", "Actions", "GlobalStepNode"]

#: Cycles of history kept for late boundaries and duplicate shifts.
_KEEP_CYCLES = 8
#: Shifts of the pending cycle held for a boundary still on its way (more are dropped, counted).
_MAX_HELD = 4
#: Duplicate shifts kept with their leaders for the summary (all are counted).
_MAX_DUPLICATES_KEPT = 16


def _same_report(a: GroupBoundaryReport, b: GroupBoundaryReport) -> bool:
    return (np.array_equal(a.left_tip_pv_w, b.left_tip_pv_w) and np.array_equal(a.right_tip_pv_w, b.right_tip_pv_w)
            and np.array_equal(a.info_pv, b.info_pv)
            and (a.tip_cov_pv is None) == (b.tip_cov_pv is None)
            and (a.tip_cov_pv is None or np.array_equal(a.tip_cov_pv, b.tip_cov_pv))
            and (a.parts, a.joins_left, a.joins_right) == (b.parts, b.joins_left, b.joins_right))


@dataclass
class _Pending:
    cycle_us: int
    published_s: float
    parts: int = 1


class GlobalStepNode:
    """See the module docstring. ``group`` and ``order`` are 0-based group indices."""

    def __init__(self, group: int, n_groups: int, order: Sequence[int], period_us: int, *,
                 shift_deadline_s: float = 0.02, leader_wait_s: float = 0.012, handover_cycles: int = 3,
                 startup_s: float = 0.5, max_shift_p_m: float = 2.0, max_shift_v_m_s: float = 1.0,
                 leader_silence_cycles: int = 3):
        if sorted(order) != list(range(n_groups)):
            raise ValueError(f"order {list(order)} must list each of the groups 0..{n_groups - 1} once")
        if not 0 <= group < n_groups:
            raise ValueError(f"group {group} is not one of 0..{n_groups - 1}")
        if period_us <= 0:
            raise ValueError(f"period_us must be positive, got {period_us}")
        self.group = group
        self.n_groups = n_groups
        self.order = tuple(order)
        self.rank = {g: k for k, g in enumerate(self.order)}
        self.period_us = int(period_us)
        self.shift_deadline_s = shift_deadline_s
        self.leader_wait_s = leader_wait_s
        self.handover_cycles = int(handover_cycles)
        self.startup_s = startup_s
        self.max_shift_p_m = max_shift_p_m
        self.max_shift_v_m_s = max_shift_v_m_s
        self.leader_silence_cycles = int(leader_silence_cycles)
        self.started_s: float | None = None
        self.muted: set[int] = set()  # leaders passed over: their shifts stopped arriving
        self._live_since: dict[int, float] = {}  # when each other group's token appeared
        self._silent_cycles = 0
        self._last_cycle_us = -1  # the newest cycle this group published a boundary for
        self._heard_cycle_us = -1  # the newest cycle the elected leader sent a shift for
        self._held: list[tuple[GlobalShift, float]] = []  # shifts of the pending cycle awaiting a boundary
        self.conflicted: dict[int, set[int]] = {}  # cycle -> groups with two different boundaries of a part
        self.live: set[int] = {group}
        self.reporting: set[int] = set()  # groups whose boundaries have arrived
        self.acting: int | None = None
        self.handover: tuple[int, int] | None = None  # (group, first cycle) agreed, not reached yet
        #: (the leader before the last hand-over, the hand-over's first cycle): a cycle before it that
        #: is still open here (this group lags) stays that leader's, never the new one's
        self._handed: tuple[int, int] | None = None
        self.pending: _Pending | None = None
        self.reports: dict[int, dict[tuple[int, int], GroupBoundaryReport]] = {}  # cycle -> (group, part) ->
        self.first_report_s: dict[int, float] = {}
        self.settled: dict[int, int] = {}  # cycle -> leader whose shift was applied / published
        self.last_round_trip_us = -1
        self.last_network_round_trip_us = -1
        self.received_s: dict[int, dict[tuple[int, int], float]] = {}  # cycle -> (group, part) -> its arrival
        #: round trips reported by the groups while this node led [us]: end to end (incl. the
        #: leader's wait for the other groups) and network only (less the leader's hold time)
        self.round_trips_us: list[int] = []
        self.network_round_trips_us: list[int] = []
        self.counts = {"global": 0, "local_only": 0, "led": 0, "late_shift": 0, "duplicate_shift": 0,
                       "yielded": 0, "partial": 0, "rejected_shift": 0, "conflicting_boundary": 0, "muted": 0}
        #: (cycle_us, leader whose shift settled it, leader of the second shift, that one live) per
        #: duplicate shift, the first :data:`_MAX_DUPLICATES_KEPT`
        self.duplicates: list[tuple[int, int, int, bool]] = []
        #: rejected shifts by reason (see the module docstring)
        self.rejections: dict[str, int] = {}
        #: (cycle_us, leader group) at every change of the leader whose shifts were applied
        self.leader_log: list[tuple[int, int]] = []

    # -- leadership ---------------------------------------------------------------------------------
    def start(self, now_s: float) -> None:
        if self.started_s is None:
            self.started_s = now_s

    def on_liveliness(self, group: int, alive: bool, now_s: float) -> None:
        self.start(now_s)
        if group == self.group or not 0 <= group < self.n_groups:
            return
        if alive:
            if group not in self.live:
                self._live_since[group] = now_s
            self.live.add(group)
            return
        self.live.discard(group)
        self.reporting.discard(group)
        if self.acting == group:
            self.acting = None
        if self.handover is not None and self.handover[0] == group:
            self.handover = None

    def leader_for(self, cycle_us: int, now_s: float) -> int | None:
        """The group that leads ``cycle_us`` as far as this node knows (``None``: nobody yet)."""
        self.start(now_s)
        # A question about a later cycle changes nothing: the hand-over is committed only when a
        # cycle from its first one on is settled (_commit_handover).
        if self.handover is not None:
            g, first = self.handover
            if cycle_us >= first and (g in self.live or g == self.group):
                return g
        elif self._handed is not None and cycle_us < self._handed[1]:
            g = self._handed[0]
            if g in self.live or g == self.group:
                return g
        if self.acting is not None and (self.acting in self.live or self.acting == self.group):
            return self.acting
        if now_s - self.started_s < self.startup_s:
            return None  # still listening for an acting leader
        elected = next((g for g in self.order if g in self.live and g not in self.muted), self.group)
        if elected == self.group and any(now_s - self._live_since.get(g, -np.inf) < self.startup_s
                                         for g in self.live if g != self.group):
            return None  # a group just came up (or this one just reached it): listen for its shifts first
        return elected

    def _leads(self, cycle_us: int, now_s: float) -> bool:
        return self.leader_for(cycle_us, now_s) == self.group

    # -- inputs -----------------------------------------------------------------------------------------
    def local_step(self, left_tip_pv_w, right_tip_pv_w, info_pv, cycle_us: int, now_s: float,
                   tip_cov_pv=None) -> Actions:
        """This group's boundary for ``cycle_us`` is ready (the whole group): publish it and wait
        for the shift."""
        return self.local_parts([PartBoundary(left_tip_pv_w, right_tip_pv_w, info_pv, tip_cov_pv)], cycle_us, now_s)

    def local_parts(self, parts: Sequence[PartBoundary], cycle_us: int, now_s: float) -> Actions:
        """This group's boundaries for ``cycle_us``, one per part in chain order (the first
        joining the previous group only if it starts with the group's first link, the last the
        next group only if it ends with its last): publish them and wait for the shift."""
        if not parts:
            raise ValueError("a group reports at least one part")
        out = Actions()
        if self.pending is not None:  # a new cycle overtook the old one: the old one ends local-only
            out.resolved.append(self._resolve(None, "overtaken by the next cycle"))
        reports = [GroupBoundaryReport(self.group, int(cycle_us), np.asarray(b.left_tip_pv_w, float),
                                       np.asarray(b.right_tip_pv_w, float), np.asarray(b.info_pv, float),
                                       self.last_round_trip_us, self.last_network_round_trip_us,
                                       None if b.tip_cov_pv is None else np.asarray(b.tip_cov_pv, float),
                                       k, len(parts), bool(b.joins_left and k == 0),
                                       bool(b.joins_right and k == len(parts) - 1))
                   for k, b in enumerate(parts)]
        out.boundaries = reports
        self.pending = _Pending(int(cycle_us), now_s, len(parts))
        self._held = []
        self._last_cycle_us = max(self._last_cycle_us, int(cycle_us))
        settled = self.settled.get(int(cycle_us))
        if settled is not None:  # the leader solved this cycle without us
            out.resolved.append(self._resolve(settled, "the leader solved this cycle without this group"))
            return out
        for report in reports:
            out.merge(self._add_report(report, now_s, now_s))
            if self.pending is None:  # solved (this group leads and every part is in)
                break
        return out

    def on_boundary(self, report: GroupBoundaryReport, now_s: float, arrived_s: float | None = None) -> Actions:
        """Another group's boundary (of one of its parts), handled at ``now_s``; ``arrived_s``: when
        it came off the wire (default ``now_s``), the start of the leader's hold time."""
        if report.group == self.group or not 0 <= report.group < self.n_groups:
            return Actions()
        self.reporting.add(report.group)
        return self._add_report(report, now_s, now_s if arrived_s is None else arrived_s)

    def on_shift(self, shift: GlobalShift, now_s: float, arrived_s: float | None = None) -> Actions:
        """A leader's shift, handled at ``now_s``; ``arrived_s``: when it came off the wire (the
        end of this group's round trip; default ``now_s``). Checked first (module docstring)."""
        out = Actions()
        arrived = now_s if arrived_s is None else arrived_s
        if shift.leader_group == self.group:
            return out  # our own, echoed (or someone using our name: never applied)
        if not 0 <= shift.leader_group < self.n_groups or any(not 0 <= g < self.n_groups for g in shift.groups):
            return self._reject("unknown_group", shift)
        cycle = shift.cycle_us
        settled = self.settled.get(cycle)
        if settled is not None:
            self.counts["duplicate_shift"] += 1
            live = shift.leader_group in self.live
            if len(self.duplicates) < _MAX_DUPLICATES_KEPT:
                self.duplicates.append((cycle, settled, shift.leader_group, live))
            log.warning("cycle %.3f s: a second shift, from group %d (%s), after group %d's", cycle * 1e-6,
                        shift.leader_group + 1, "live" if live else "its token gone", settled + 1)
            if (settled == self.group and self.rank[shift.leader_group] < self.rank[self.group]
                    and shift.leader_group in self.live and self._verify(shift) is not False):
                self.counts["yielded"] += 1  # two leaders met: the lower-ranked one yields
                self.acting = shift.leader_group
                self.muted.discard(shift.leader_group)
            return out
        pending = self.pending is not None and self.pending.cycle_us == cycle
        expected = self.leader_for(cycle, now_s)
        if expected is None:  # still listening: a live group's shift names the acting leader
            expected = shift.leader_group if shift.leader_group in self.live else -1
        if shift.leader_group != expected:
            return self._reject("not_leader", shift)
        # Only a checked shift is the leader's: only it counts as hearing from the leader (a forged
        # one in its name must not hide a silent leader) or settles a cycle.
        if not pending:
            if cycle <= self._last_cycle_us:
                self.counts["late_shift"] += 1  # a cycle this group already finished (or skipped)
                if self._verify(shift):
                    self._heard_cycle_us = max(self._heard_cycle_us, cycle)
                return out
            if self.group in shift.groups:  # the leader cannot have our boundary of a cycle we have not reached
                return self._reject("not_pending", shift)
            verdict = self._verify(shift)
            if verdict is None:  # the cycle's boundaries are not here: it cannot be the leader's yet
                return self._reject("unverifiable", shift)
            if not verdict:
                return self._reject("inconsistent", shift)
            self._heard_cycle_us = max(self._heard_cycle_us, cycle)
            # the leader's own (checked): it is the acting leader, as far as this group knows (a
            # group that has not stepped yet, just started, must not take the lead from it)
            self._settle(cycle, shift.leader_group)  # solved without us: local-only when we get there
            self.acting = shift.leader_group
            self.muted.discard(shift.leader_group)
            self._take_handover(shift)
            return out
        if self.conflicted.get(cycle, set()) & set(shift.groups):
            # a listed group's boundary came twice, differently: no shift of this cycle can be
            # checked. It may be the leader's: a forged boundary must not make it look silent.
            self._heard_cycle_us = max(self._heard_cycle_us, cycle)
            return self._reject("conflicted", shift)
        for own in (s for (g, _), s in zip(shift.keys, np.asarray(shift.shift_pv_w)) if g == self.group):
            if (not np.isfinite(own).all() or np.linalg.norm(own[:3]) > self.max_shift_p_m
                    or np.linalg.norm(own[3:]) > self.max_shift_v_m_s):
                return self._reject("bounds", shift)
        verdict = self._verify(shift)
        if verdict is None:  # a listed group's boundary has not reached us yet: check it when it does
            if len(self._held) >= _MAX_HELD:  # a flood of uncheckable shifts: keep the first few only
                return self._reject("unverifiable", shift)
            self._held.append((shift, arrived))
            return out
        if not verdict:
            return self._reject("inconsistent", shift)
        return self._apply(shift, arrived)

    def _apply(self, shift: GlobalShift, arrived: float) -> Actions:
        """Apply a checked shift to the pending cycle."""
        out = Actions()
        self._heard_cycle_us = max(self._heard_cycle_us, shift.cycle_us)
        self._settle(shift.cycle_us, shift.leader_group)
        self._held = []
        self._silent_cycles = 0
        self.acting = shift.leader_group
        self.muted.discard(shift.leader_group)
        self._take_handover(shift)
        rt = int(round((arrived - self.pending.published_s) * 1e6))
        hold = next((shift.hold_for(g, k) for g, k in shift.keys if g == self.group), None)
        self.last_round_trip_us = rt
        self.last_network_round_trip_us = rt - hold if hold is not None else -1
        out.resolved.append(self._resolve_shift(shift))
        return out

    def _recheck_held(self, cycle: int) -> Actions:
        """A boundary of ``cycle`` arrived: the shifts held for it may be checked now."""
        if not self._held or self.pending is None or self.pending.cycle_us != cycle:
            return Actions()
        held, self._held = self._held, []
        for k, (shift, arrived) in enumerate(held):
            verdict = self._verify(shift)
            if verdict is None:
                self._held.append((shift, arrived))
            elif not verdict:
                self._reject("inconsistent", shift)
            else:
                return self._apply(shift, arrived)
        return Actions()

    def _reject(self, reason: str, shift: GlobalShift) -> Actions:
        self.counts["rejected_shift"] += 1
        n = self.rejections[reason] = self.rejections.get(reason, 0) + 1
        if n <= 3 or n % 100 == 0:  # the first few of each kind, then every 100th (a flood stays quiet)
            log.warning("group %d: rejected a shift in group %d's name for cycle %.3f s (%s, #%d); live %s, acting %s, "
                        "handover %s, muted %s", self.group + 1, shift.leader_group + 1, shift.cycle_us * 1e-6, reason, n,
                        sorted(g + 1 for g in self.live), None if self.acting is None else self.acting + 1,
                        self.handover, sorted(g + 1 for g in self.muted))
        return Actions()

    def _verify(self, shift: GlobalShift) -> bool | None:
        """Is ``shift`` eq. 6 of the boundaries this group holds for its cycle? ``None``: some listed
        group's boundary is not here (yet); ``False`` also when a listed group's boundary came
        twice, differently (forged: the shift cannot be checked)."""
        reports = self.reports.get(shift.cycle_us, {})
        if self.conflicted.get(shift.cycle_us, set()) & set(shift.groups):
            return False
        keys = shift.keys
        if (len(keys) != len(set(keys)) or len(shift.parts) != len(shift.groups)
                or np.shape(shift.shift_pv_w) != (len(keys), 6) or not np.isfinite(shift.shift_pv_w).all()):
            return False
        if not all(key in reports for key in keys):
            return None
        solved, shifts = solve_cycle([reports[key] for key in keys])
        want = shifts[[solved.index(key) for key in keys]]
        return bool(np.all(np.abs(want - shift.shift_pv_w) <= 1e-9 + 1e-9 * np.abs(shift.shift_pv_w)))  # (allclose)

    def tick(self, now_s: float) -> Actions:
        """Deadlines: the leader solves cycles that waited ``leader_wait_s``; a group that waited
        ``shift_deadline_s`` for its shift sends local-only corrections."""
        out = Actions()
        for cycle, first in sorted(self.first_report_s.items()):
            if self._waited(cycle, first, now_s) and self._leads(cycle, now_s):
                out.merge(self._solve(cycle, now_s))
        if self._shift_overdue(now_s):
            leader = self.leader_for(self.pending.cycle_us, now_s)
            heard = self._heard_cycle_us >= self.pending.cycle_us
            if self._held:
                self.counts["rejected_shift"] += len(self._held)
                self.rejections["unverifiable"] = self.rejections.get("unverifiable", 0) + len(self._held)
                self._held = []
            out.resolved.append(self._resolve(None, "no shift before the deadline"))
            if heard:
                self._silent_cycles = 0
            elif (leader is not None and leader != self.group
                  and now_s - self._live_since.get(leader, -np.inf) > self.startup_s + self.shift_deadline_s):
                # (a group that just joined listens for startup_s before it leads: not silence)
                self._silent_cycles += 1
                if self._silent_cycles >= self.leader_silence_cycles:
                    # its shifts stopped (gone without its token leaving, or never there): pass it over
                    self.muted.add(leader)
                    self.counts["muted"] += 1
                    self._silent_cycles = 0
                    if self.acting == leader:
                        self.acting = None
                    if self.handover is not None and self.handover[0] == leader:
                        self.handover = None
        return out

    def next_deadline_s(self, now_s: float) -> float | None:
        """The earliest time after ``now_s`` (or at it) when :meth:`tick` may have something to do
        (``None``: nothing pending): a cycle reaching ``leader_wait_s``, once more when this group
        leads it; the shift's deadline. A cycle that has waited and another group leads gives no
        deadline (its shift, or that group leaving, comes as an input), except the end of a startup
        window, when the clock alone may make this group its leader: a caller that sleeps until the
        deadline never wakes in a loop while the leader computes."""
        times = []
        led_elsewhere = False
        for cycle, first in self.first_report_s.items():
            if cycle in self.settled:
                continue
            due = first + self.leader_wait_s
            if due > now_s or self._leads(cycle, now_s):
                times.append(due)
            else:
                led_elsewhere = True
        if led_elsewhere:
            ends = [since + self.startup_s for g, since in self._live_since.items() if g in self.live]
            if self.started_s is not None:
                ends.append(self.started_s + self.startup_s)
            times.extend(t for t in ends if t > now_s)
        if self.pending is not None:
            times.append(self.pending.published_s + self.shift_deadline_s)
        return min(times) if times else None

    def due(self, now_s: float) -> bool:
        """Whether :meth:`tick` at ``now_s`` may have something to do: a cycle this group leads has
        waited ``leader_wait_s``, or the shift is overdue (the same tests as :meth:`tick`'s;
        ``False``: a tick would change nothing)."""
        return self._shift_overdue(now_s) or any(
            self._waited(cycle, first, now_s) and self._leads(cycle, now_s)
            for cycle, first in self.first_report_s.items())

    def _waited(self, cycle: int, first_s: float, now_s: float) -> bool:
        """A cycle not settled whose first report came ``leader_wait_s`` ago or more."""
        return cycle not in self.settled and now_s - first_s >= self.leader_wait_s

    def _shift_overdue(self, now_s: float) -> bool:
        """This group's boundary has waited ``shift_deadline_s`` for its shift."""
        return self.pending is not None and now_s - self.pending.published_s >= self.shift_deadline_s

    # -- internals ----------------------------------------------------------------------------------------
    def _add_report(self, report: GroupBoundaryReport, now_s: float, arrived_s: float) -> Actions:
        cycle = report.cycle_us
        if cycle in self.settled:
            return Actions()
        held = self.reports.setdefault(cycle, {})
        if report.group in self.conflicted.get(cycle, ()):
            return Actions()
        old = held.get(report.key)
        siblings = [r for key, r in held.items() if key[0] == report.group and key != report.key]
        if (old is not None and not _same_report(old, report)) or any(r.parts != report.parts for r in siblings):
            # two different boundaries under one name (or parts that disagree on how many there
            # are): none of the group's can be trusted this cycle
            self.counts["conflicting_boundary"] += 1
            self.conflicted.setdefault(cycle, set()).add(report.group)
            for key in [key for key in held if key[0] == report.group]:
                del held[key]
            return Actions()
        held[report.key] = report
        self.received_s.setdefault(cycle, {})[report.key] = arrived_s
        self.first_report_s.setdefault(cycle, now_s)
        self._prune(cycle)
        if self._leads(cycle, now_s) and self._complete(cycle):
            return self._solve(cycle, now_s)
        return self._recheck_held(cycle)

    def _complete(self, cycle: int) -> bool:
        """Every part of every live group has reported ``cycle``."""
        held = self.reports.get(cycle, {})
        counts: dict[int, int] = {}
        declared: dict[int, int] = {}
        for (g, _), r in held.items():
            counts[g] = counts.get(g, 0) + 1
            declared[g] = r.parts
        return all(g in counts and counts[g] == declared[g] for g in self.live)

    def _solve(self, cycle: int, now_s: float) -> Actions:
        reports = list(self.reports.get(cycle, {}).values())
        out = Actions()
        if not reports:
            return out
        self._commit_handover(cycle, self.group)
        keys, shifts = solve_cycle(reports)
        groups = tuple(g for g, _ in keys)
        if len(set(groups)) < len(self.live):
            self.counts["partial"] += 1
        self.counts["led"] += 1
        if self.acting != self.group:
            log.info("group %d leads from cycle %.3f s (acting was %s; live %s, muted %s, handover %s)", self.group + 1,
                     cycle * 1e-6, None if self.acting is None else self.acting + 1, sorted(g + 1 for g in self.live),
                     sorted(g + 1 for g in self.muted), self.handover)
        self.acting = self.group
        others = [r for r in reports if r.group != self.group and r.part == 0]  # one round trip per group
        self.round_trips_us += [r.round_trip_us for r in others if r.round_trip_us >= 0]
        self.network_round_trips_us += [r.network_round_trip_us for r in others if r.network_round_trip_us >= 0]
        received = self.received_s.get(cycle, {})
        hold = tuple(int(round((now_s - received.get(key, now_s)) * 1e6)) for key in keys)
        if self.handover is None:
            preferred = next(g for g in self.order if g in self.live and g not in self.muted
                             and (g in self.reporting or g == self.group))
            if self.rank[preferred] < self.rank[self.group]:
                self.handover = (preferred, cycle + self.handover_cycles * self.period_us)
        hg, hc = self.handover if self.handover is not None else (-1, 0)
        msg = GlobalShift(self.group, cycle, groups, shifts, hg, hc, hold, tuple(k for _, k in keys))
        out.shifts.append(msg)
        self._settle(cycle, self.group)
        if self.pending is not None and self.pending.cycle_us == cycle:
            out.resolved.append(self._resolve_shift(msg))
        return out

    def _take_handover(self, shift: GlobalShift) -> None:
        """The acting leader's checked shift names the group it hands over to, and from which cycle."""
        if 0 <= shift.handover_group < self.n_groups and shift.cycle_us < shift.handover_cycle_us:  # still to come
            self.handover = (shift.handover_group, shift.handover_cycle_us)

    def _commit_handover(self, cycle: int, leader: int) -> None:
        """``leader`` settles ``cycle``: if that is the agreed hand-over, it is done (the leader of
        the cycles before it is kept for a lagging cycle of this group)."""
        if self.handover is not None and leader == self.handover[0] and cycle >= self.handover[1]:
            old = self.leader_log[-1][1] if self.leader_log else None
            self._handed = None if old is None or old == leader else (old, self.handover[1])
            self.handover = None

    def _settle(self, cycle: int, leader: int) -> None:
        self._commit_handover(cycle, leader)
        if not self.leader_log or self.leader_log[-1][1] != leader:
            self.leader_log.append((cycle, leader))
        self.settled[cycle] = leader
        # the cycle's boundaries stay (pruned with the history): a late shift of the leader is
        # checked against them before it counts as hearing from it
        self.received_s.pop(cycle, None)
        self.first_report_s.pop(cycle, None)
        self._prune(cycle)

    def _prune(self, cycle: int) -> None:
        horizon = cycle - _KEEP_CYCLES * self.period_us
        for table in (self.reports, self.received_s, self.first_report_s, self.settled, self.conflicted):
            for old in [c for c in table if c < horizon]:
                del table[old]

    def _resolve_shift(self, shift: GlobalShift) -> Resolution:
        """The pending cycle ends with ``shift``: per part, a global step only if it was solved
        together with a neighbour (a part alone in its run of the solution gets a zero shift: that
        is local-only, and counted so)."""
        reports = self.reports.get(shift.cycle_us, {})
        solved = [reports[key] for key in shift.keys if key in reports]
        run_of = {r.key: run for run in runs(solved) for r in run}
        parts = []
        for k in range(self.pending.parts):
            key = (self.group, k)
            if key not in shift.keys:
                parts.append(PartShift(None, "not in the leader's solution"))
            elif len(run_of.get(key, ())) < 2:
                parts.append(PartShift(None, "no neighbouring group in the leader's solution"))
            else:
                gain, cov = shift_covariance_terms(run_of[key], key) or (None, None)
                parts.append(PartShift(np.asarray(shift.shift_for(*key), float), "", gain, cov))
        return self._finish(shift.leader_group, tuple(parts))

    def _resolve(self, leader: int | None, reason: str) -> Resolution:
        """The pending cycle ends local-only for every part (``reason``)."""
        return self._finish(leader, tuple(PartShift(None, reason) for _ in range(self.pending.parts)))

    def _finish(self, leader: int | None, parts: tuple[PartShift, ...]) -> Resolution:
        pending, self.pending = self.pending, None
        res = Resolution(pending.cycle_us, leader, parts)
        self.counts["global" if res.global_applied else "local_only"] += 1
        return res

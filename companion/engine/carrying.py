"""Carrying: which links have their rotors off, so that their neighbours' feed-forward takes
their weight (the whole-chain feed-forward, ``trajectory.feedforward``).

A link is carried when it has flown and is now silent ``carry_silence_s`` (longer on a lossy wire
with ``carry_silence_max_s`` set: :mod:`.silence`), disarmed, or re-armed less than
``carry_spinup_s`` ago (:meth:`Carrying.own`). In distributed mode each group publishes its carried
links (:class:`~companion.messages.GroupPassiveLinks`, :meth:`Carrying.publish`) and
takes the other groups' (:meth:`Carrying.on_remote`, :meth:`Carrying.remote`): a dead link at a
group's end hangs on a link of the next group. Every carried stretch is logged and timed
(``carried_s`` and ``carried_by_other_groups_s`` in the engine's summary).

Silence is the companion's only sign of a power loss, and a link whose MAVLink link failed is
silent too while it flies on. Carried, it lifts itself and its neighbours push it up as well: the
chain rises. So a silent link (or another group's carried link) is no longer carried while its
neighbours this engine flies are on average :data:`RISE_M` above their targets (it is lifting
itself), and carried again if they sink as far below (:meth:`Carrying.lifting_itself`); each
release is logged and counted (``carry_released``).
"""

from __future__ import annotations

import logging
from statistics import median

import numpy as np

from ..messages import STATE_FLAG_ARMED, GroupPassiveLinks
from .links import CarryClock, LinkTrack
from .silence import silence_threshold_s

__all__ = ["DISARMED_STATES", "PASSIVE_REPEAT_US", "PASSIVE_STALE_US", "RISE_M", "Carrying"]

log = logging.getLogger(__name__)

#: Accepted states in a row reporting a link disarmed before the companion takes its rotors to
#: be off: 60 ms of the 50 Hz stream.
DISARMED_STATES = 3
#: Distributed mode: a group publishes its carried links when they change and at least this
#: often [us]; the others take a group's newest one within :data:`PASSIVE_STALE_US` of their own
#: cycle clock, also after its companion left (a dying group's carried link is still dead: its claim
#: holds until it goes stale).
PASSIVE_REPEAT_US = 1_000_000
PASSIVE_STALE_US = 2_500_000
#: A carried link whose neighbours (those this engine flies) are on average this far above their
#: targets [m] lifts itself: no longer carried until they are as far below.
RISE_M = 0.15


class Carrying:
    """The carried links of one engine's ``links`` under ``cfg`` (a
    :class:`~companion.config.CompanionConfig`); in distributed mode (``net`` a group link,
    ``group`` this engine's, ``groups`` every group's chain indices) also the other groups'.
    Every method takes the engine's cycle clock ``t_us`` (on the time base)."""

    def __init__(self, cfg, links: list[LinkTrack], group: int | None, groups, net):
        self.cfg = cfg
        self.links = links
        self.group = group
        self.groups = groups
        self.net = net
        # distributed mode: the other groups' carried links (newest message per group), what this
        # group last published, and how long each other group's link has been carried here
        self._remote: dict[int, GroupPassiveLinks] = {}
        self._sent: tuple[tuple[int, ...], int] | None = None
        self.counts = {"published": 0, "received": 0, "rejected": 0}
        self.remote_carried: dict[int, CarryClock] = {}  # another group's link -> its carrying here
        self._by_index = {lk.index: lk for lk in links}
        #: the newest target of each of this engine's links (:meth:`on_target`): its height [m]
        self._target_z: dict[int, float] = {}
        #: links taken to lift themselves (no longer carried while silent), and how often each was
        self.released: set[int] = set()
        self.release_count: dict[int, int] = {}

    def on_target(self, index: int, target) -> None:
        """The target just sent to this engine's link ``index`` (a :class:`~companion.messages.PoseTarget`)."""
        self._target_z[index] = float(target.p_w_m[2])

    def lifting_itself(self, index: int, t: float) -> bool:
        """Whether the carried link ``index`` is taken to lift itself: released once its neighbours
        that this engine flies are on average :data:`RISE_M` above their targets (their newest
        states against their newest targets: a dead link tilts the chain, one neighbour up and one
        down, and sinks it; a live one carried pushes both up), carried again once they are as far
        below; unchanged without such a neighbour."""
        released = index in self.released
        above = [float(lk.state.p_w_m[2]) - self._target_z[j] for j in (index - 1, index + 1)
                 if (lk := self._by_index.get(j)) is not None and lk.state is not None and j in self._target_z]
        if not above:
            return released
        mean = sum(above) / len(above)
        if mean > RISE_M and not released:
            self.released.add(index)
            self.release_count[index] = self.release_count.get(index, 0) + 1
            log.warning("link %d: carried, but its neighbours are %.2f m above their targets at %.2f s: it lifts "
                        "itself (alive, unheard); no longer carried", index + 1, mean, t)
            return True
        if mean < -RISE_M and released:
            self.released.discard(index)
            log.warning("link %d: its neighbours are %.2f m below their targets at %.2f s: carried again",
                        index + 1, -mean, t)
            return False
        return released

    def now(self, now_s: float, t_us: int) -> frozenset[int]:
        """The chain indices carried now: this engine's own (:meth:`own`) and, in distributed
        mode, the other groups' (after publishing this group's)."""
        passive = self.own(now_s, t_us)
        if self.net is not None:
            self.publish(passive, t_us)
            passive = passive | self.remote(t_us)
        return passive

    def own(self, now_s: float, t_us: int) -> frozenset[int]:
        """The chain indices of this engine's links whose rotors are taken to be off: a link that
        has flown and is now silent ``carry_silence_s`` (lengthened by the loss of its stream,
        :func:`~.silence.silence_threshold_s`; its newest state that far behind the
        median of the links' newest, the newest with fewer than three links; and nothing from it
        for that silence over ``clock_rate_max`` on the companion's own clock ``now_s``, so that a
        link whose states keep arriving is not taken as silent because another link's stamps were
        forged ahead, as they can be in a group of two), disarmed (its first
        report after a silence, else :data:`DISARMED_STATES` reports in a row; not believed while
        its stream has had replayed or future stamps within ``reboot_silence_s``), or
        heard armed again for less than ``carry_spinup_s`` (its
        ESCs restarting; after a silence of ``reboot_silence_s`` too, which may have been a reboot
        whose disarmed states were lost; a shorter dropout of an armed link costs no spin-up
        wait). All on the time base: what matters is how long the link
        has been falling or spinning up, and in SITL that is simulated time. Transitions are logged."""
        cfg, out = self.cfg, set()
        heard = [lk.state.time_s for lk in self.links if lk.state is not None]
        # the reference: the median of the links' newest stamps, which a link whose states are
        # forged ahead (within the stamp margin) does not move for the others; with fewer than
        # three links (a group's engine) the cycle clock, which such a link does not move either
        t = median(heard) if len(heard) >= 3 else t_us * 1e-6
        for lk in self.links:
            lag = np.inf if lk.state is None else t - lk.state.time_s
            loss = lk.loss.fraction if lk.loss is not None else 0.0
            silence_s = silence_threshold_s(loss, cfg.carry_silence_s, cfg.carry_silence_cap_s, cfg.state_rate_hz)
            silent = lag >= silence_s and lk.quiet(now_s, silence_s, cfg.clock_rate_max)
            # disarmed: the first report after a silence says, otherwise DISARMED_STATES reports in
            # a row (a lone forged one on an unsigned wire does not)
            # (not while its stream carries replayed or future stamps: then some of it is forged)
            if silent:
                lk.after_silence = True
            elif t - lk.stamp_rejected_s < cfg.reboot_silence_s:
                pass
            elif lk.after_silence:
                lk.after_silence = False
                lk.believed_armed = bool(lk.flags & STATE_FLAG_ARMED)
            elif lk.flags & STATE_FLAG_ARMED:
                lk.believed_armed = True
            elif lk.disarmed_states >= DISARMED_STATES:
                lk.believed_armed = False
            armed = lk.believed_armed
            # unheard that long: it may have rebooted (unless it was seen lifting itself meanwhile)
            if not armed or (lag >= cfg.reboot_silence_s and lk.index not in self.released):
                lk.armed_since_s = None
            elif lk.armed_since_s is None and not silent:
                lk.armed_since_s = t
            spinning = armed and not silent and t - lk.armed_since_s >= cfg.carry_spinup_s
            lk.flown = lk.flown or spinning
            passive = lk.flown and (silent or not spinning)
            if not silent:
                self.released.discard(lk.index)  # heard: what it says decides
            elif passive and self.lifting_itself(lk.index, t):
                passive = False  # unheard, but flying
            was = lk.carried.on
            ended = lk.carried.switch(passive, t)
            if passive and not was:
                why = (f"silent {silence_s:.2f} s ({100 * loss:.0f} % of its states lost)" if silent
                       else "disarmed in flight" if not armed else "re-armed, rotors starting")
                log.warning("link %d: %s at %.2f s: its neighbours carry it (whole-chain feed-forward)",
                            lk.index + 1, why, t)
            elif ended is not None:
                log.warning("link %d: flies itself again at %.2f s, after %.2f s carried", lk.index + 1, t, ended)
            if passive:
                out.add(lk.index)
        return frozenset(out)

    # -- across groups (distributed mode) ----------------------------------------------------------
    def publish(self, own: frozenset[int], t_us: int) -> None:
        """This group's carried links to the other groups: when the set changes, and each
        :data:`PASSIVE_REPEAT_US` (a group that starts later, or lost one, learns it)."""
        links = tuple(sorted(own))
        sent = self._sent
        if sent is not None and sent[0] == links and t_us - sent[1] < PASSIVE_REPEAT_US:
            return
        self._sent = (links, t_us)
        self.net.publish_passive(GroupPassiveLinks(self.group, t_us, links))
        self.counts["published"] += 1

    def on_remote(self, msg: GroupPassiveLinks, t_us: int) -> None:
        """Another group's carried links: kept (its newest) if they are that group's own links and,
        once this group has a cycle clock, its stamp is within :data:`PASSIVE_STALE_US` of it either
        way; otherwise counted and dropped (a group cannot make another group's links, or this
        group's, carried). Only a current claim is used (:meth:`remote`), and one that is not
        current gives way to any other (a stamp far ahead cannot pin a claim)."""
        g = msg.group
        why = None
        if g == self.group or not 0 <= g < len(self.groups):
            why = f"from group {g + 1}"
        elif not set(msg.links) <= set(self.groups[g]):
            why = f"links {[i + 1 for i in msg.links]} are not all group {g + 1}'s"
        elif t_us and not self._current(msg, t_us):
            why = f"stamp {msg.time_us * 1e-6:.3f} s, {(msg.time_us - t_us) * 1e-6:+.3f} s off the cycle clock"
        if why is not None:
            self.counts["rejected"] += 1
            n = self.counts["rejected"]
            if n <= 5 or n % 100 == 0:
                log.warning("carried links of group %d dropped (#%d): %s", g + 1, n, why)
            return
        self.counts["received"] += 1
        old = self._remote.get(g)
        if old is None or msg.time_us >= old.time_us or not self._current(old, t_us):
            self._remote[g] = msg

    @staticmethod
    def _current(msg: GroupPassiveLinks, t_us: int) -> bool:
        """Whether a group's claim is within :data:`PASSIVE_STALE_US` of the cycle clock ``t_us``."""
        return bool(t_us) and abs(msg.time_us - t_us) <= PASSIVE_STALE_US

    def remote(self, t_us: int) -> frozenset[int]:
        """The links the other groups' companions carry (their newest messages while not stale,
        whether or not the group's companion is still up); each carried stretch is logged and timed
        (``remote_carried``)."""
        out: set[int] = set()
        t = t_us * 1e-6
        for g, msg in self._remote.items():
            if self._current(msg, t_us):
                out.update(msg.links)
        for i in set(self.released) - set(self._by_index):  # another group's link no longer claimed
            if i not in out:
                self.released.discard(i)
        out = {i for i in out if not self.lifting_itself(i, t)}
        for i in out | {i for i, clock in self.remote_carried.items() if clock.on}:
            clock = self.remote_carried.setdefault(i, CarryClock())
            was = clock.on
            if clock.switch(i in out, t) is not None:
                log.warning("link %d (group %d) flies itself again at %.2f s", i + 1, self._group_of(i) + 1, t)
            elif clock.on and not was:
                log.warning("link %d (group %d) carried at %.2f s: its rotors are off (its group's companion says)",
                            i + 1, self._group_of(i) + 1, t)
        return frozenset(out)

    def _group_of(self, link: int) -> int:
        return next(g for g, members in enumerate(self.groups) if link in members)

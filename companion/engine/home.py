"""A distributed chain's home: one offset from the shared anchor that every group flies.

A centralised companion flies its trajectory from where the first step's estimate puts the
chain's middle (:mod:`companion.trajectory`, ``home = "estimate"``). Each group companion of a
distributed chain sees only its own links, and groups that shifted their targets by their own
estimates would disagree by their estimate errors and pull the chain apart. So one group
measures the home and the others take it (:class:`~companion.messages.ChainHome`):

* the group that holds link ``n // 2`` (0-based: the middle link, or the link whose left tip is
  the middle joint) measures it from its steps' estimate of that link: the chain's middle less
  the anchor. It does so only if none of its links was armed when this companion first heard
  them all (the chain rests where it was set down); a companion started in flight waits for the
  home the others hold. While the chain rests (trajectory time before ``refine_s``, the take-off's
  start less :data:`HOME_MARGIN_S`) it measures it again at every target, as the links'
  estimates settle after their start, and publishes each measurement;
* the other groups take each of its measurements until :data:`HOME_MARGIN_S` after ``refine_s``
  (time for the last to arrive), then keep the one they have; a group that has none by then takes
  the first home any group publishes (a companion started in flight);
* every group that holds a home no longer measured publishes it each :data:`HOME_REPEAT_US`, so
  that a companion that starts later flies from the same home;
* a group that has no home :data:`HOME_WAIT_S` after it first heard all its links (the measuring
  group's companion is not up, or its middle link is not heard) flies the anchor as given, and
  publishes that as its home;
* every input is checked: a home from this group's own index or outside the layout is dropped
  (``rejected``); on a fresh start, a home more than :data:`HOME_AGREE_M` from where this group's
  own first step puts its links against the trajectory's start is dropped too (an insider's
  forgery moves the chain no further than the receivers disagree), and one that arrives before
  that step waits for it; a measurement older than the one taken, and a home that differs from the
  one kept, are counted (``stale``, ``conflicts``) and not flown.
"""

from __future__ import annotations

import logging

import numpy as np

from ..estimation.so3 import quat_to_rotmat
from ..messages import STATE_FLAG_ARMED, ChainHome
from ..skeleton.kinematics import middle_of_link
from .links import LinkTrack

__all__ = ["NetHome", "HOME_AGREE_M", "HOME_MARGIN_S", "HOME_REPEAT_US", "HOME_WAIT_S"]

log = logging.getLogger(__name__)

#: How often a group publishes the home it holds [us].
HOME_REPEAT_US = 1_000_000
#: How long a group waits for a home before it flies the anchor as given [s].
HOME_WAIT_S = 5.0
#: The last measurement of the home comes this long before the take-off starts, and the groups
#: take measurements until this long after it [s] (trajectory time).
HOME_MARGIN_S = 0.2
#: Farthest a received home may be from this group's own evidence of it [m] (receivers' biases
#: are about a metre per axis; the middle link's and a group's mean differ by their biases).
HOME_AGREE_M = 5.0


class NetHome:
    """The home of group ``group`` (0-based) of an ``n_links`` chain in ``groups`` (each group's
    chain indices) whose shared anchor is ``anchor_w_m``, for the engine's ``links`` (``d``: their
    tip vectors) on the group link ``net``. See the module docstring."""

    def __init__(self, group: int, groups, net, links: list[LinkTrack], d: np.ndarray, n_links: int, anchor_w_m,
                 wait_s: float = HOME_WAIT_S):
        self.group = group
        self.n_groups = len(groups)
        #: the group that measures the home: the one holding link ``n // 2``
        self.measurer = next(g for g, members in enumerate(groups) if n_links // 2 in members)
        self.net = net
        self.n_links = n_links
        self.anchor_w_m = np.asarray(anchor_w_m, dtype=float)
        self.wait_s = wait_s
        self._d = d
        self._links = links
        #: this engine's row of link ``n // 2`` (``None``: another group measures the home)
        self.row = next((lk.row for lk in links if lk.index == n_links // 2), None)
        #: the home offset [m, world] once there is one (``None``: waiting)
        self.offset_w_m: np.ndarray | None = None
        #: where it came from: "measured", "group <g>" or "anchor" (none within the wait)
        self.source = ""
        self.counts = {"published": 0, "received": 0, "stale": 0, "conflicts": 0, "rejected": 0}
        self._first_s: float | None = None
        self._fresh = False  # no link of this group armed at first contact: the chain at its start
        self._own: np.ndarray | None = None  # this group's evidence of the home (fresh start)
        self._pending: list[ChainHome] = []  # homes received before that evidence
        self._taken_us = -1  # the stamp of the measurement taken last (from the measuring group)
        self._final = False  # no measurement taken any more: the home is kept
        self._changed = False  # a measurement to publish
        self._sent_us: int | None = None

    def on_remote(self, msg: ChainHome) -> None:
        """Another group's home (see the module docstring)."""
        if msg.group == self.group or not 0 <= msg.group < self.n_groups:
            self._reject(msg, "not another group of this chain")
            return
        if self._first_s is None or (self._fresh and self._own is None):
            self._pending.append(msg)  # (judged once this group's first step says where it stands)
            return
        self._judge(msg)

    def offset(self, now_s: float, estimate, planned_w_m: np.ndarray, t_traj_s: float,
               refine_s: float) -> np.ndarray | None:
        """The home offset, or ``None`` while waiting for it. ``estimate``: ``(p, q)`` of the
        engine's links in the newest step (``None`` before the first); ``planned_w_m``: (n, 3)
        every link's centre at the trajectory's start, unshifted; ``t_traj_s``: the trajectory's
        time; ``refine_s``: the trajectory time until which the home is measured again."""
        if self._first_s is None:  # every link heard for the first time: no ARM sent yet
            self._first_s = now_s
            self._fresh = not any(lk.flags & STATE_FLAG_ARMED for lk in self._links)
        if not self._final and t_traj_s >= refine_s + (0.0 if self.row is not None else HOME_MARGIN_S):
            self._final = True
            if self.offset_w_m is not None:
                log.info("group %d: home kept for the flight: %s m from the anchor (%s)", self.group + 1,
                         _fmt(self.offset_w_m), self.source)
        if estimate is not None and self._fresh and (self.offset_w_m is None or not self._final):
            p, q = (np.asarray(x, dtype=float) for x in estimate)
            usable = np.all(np.isfinite(p), axis=1)
            if self._own is None and usable.any():
                rows = np.flatnonzero(usable)
                self._own = np.mean(p[rows] - planned_w_m[[self._links[r].index for r in rows]], axis=0)
            if self.row is not None and usable[self.row] and np.all(np.isfinite(q[self.row])):
                middle = middle_of_link(p[self.row], quat_to_rotmat(q[self.row]), self._d[self.row], self.n_links)
                self._adopt(middle - self.anchor_w_m, "measured")
                return self.offset_w_m
        if not (self._fresh and self._own is None):  # (where this group stands is known, or not needed)
            pending, self._pending = self._pending, []
            for msg in pending:
                self._judge(msg)
        if self.offset_w_m is None and now_s - self._first_s >= self.wait_s:
            log.warning("group %d: no home within %.1f s (the measuring group's companion or its middle link not "
                        "heard): the anchor flown as given", self.group + 1, self.wait_s)
            self._final = True
            self._adopt(np.zeros(3), "anchor")
        return self.offset_w_m

    def publish(self, t_us: int) -> None:
        """The home held, to the other groups: each new measurement, then, once it is kept, each
        :data:`HOME_REPEAT_US`."""
        if self.offset_w_m is None:
            return
        if not self._final:
            if self.source != "measured" or not self._changed:  # (only the measuring group, while it measures)
                return
        elif self._sent_us is not None and t_us - self._sent_us < HOME_REPEAT_US:
            return
        self._changed = False
        self._sent_us = t_us
        self.net.publish_home(ChainHome(self.group, t_us, self.offset_w_m.copy()))
        self.counts["published"] += 1

    def summary(self) -> dict:
        return {"source": self.source, **self.counts}

    def _judge(self, msg: ChainHome) -> None:
        offset = np.asarray(msg.offset_w_m, dtype=float)
        if self._own is not None and np.linalg.norm(offset - self._own) > HOME_AGREE_M:
            self._reject(msg, f"{np.linalg.norm(offset - self._own):.1f} m from where this group's links put it")
            return
        self.counts["received"] += 1
        if not self._final and msg.group == self.measurer:  # (a measurement while the chain rests)
            if msg.time_us < self._taken_us:
                self.counts["stale"] += 1
                return
            self._taken_us = msg.time_us
            self._adopt(offset.copy(), f"group {msg.group + 1}")
        elif self.offset_w_m is None:
            self._adopt(offset.copy(), f"group {msg.group + 1}")
        elif not np.array_equal(offset, self.offset_w_m):
            self.counts["conflicts"] += 1
            n = self.counts["conflicts"]
            if n <= 5 or n % 100 == 0:
                log.warning("group %d: home from group %d (%s m) differs from the one flown (%s m, %s): not used (#%d)",
                            self.group + 1, msg.group + 1, _fmt(offset), _fmt(self.offset_w_m), self.source, n)

    def _reject(self, msg: ChainHome, why: str) -> None:
        self.counts["rejected"] += 1
        n = self.counts["rejected"]
        if n <= 5 or n % 100 == 0:
            log.warning("group %d: home from group %d dropped (#%d): %s", self.group + 1, msg.group + 1, n, why)

    def _adopt(self, offset_w_m: np.ndarray, source: str) -> None:
        first = self.offset_w_m is None
        self.offset_w_m, self.source, self._changed = offset_w_m, source, True
        if first:
            log.info("group %d: home %s m from the anchor (%s; %s)", self.group + 1, _fmt(offset_w_m), source,
                     "kept for the flight" if self._final
                     else "measured again while the chain rests, until the take-off")


def _fmt(x) -> str:
    return ", ".join(f"{float(v):.2f}" for v in x)

"""Pose targets: every link's target from the trajectory, every 1/``target_rate_hz``.

The trajectory (``[trajectory]``) is anchored at ``trajectory.anchor_w_m`` and, with ``home =
"estimate"``, flown from where the chain's estimate puts its middle at the start, as a flight
controller flies from its home (:mod:`companion.trajectory`): the targets wait for the first step
(in distributed mode, for the home the groups agree on: :mod:`.home`), its time starts with the
first targets (:meth:`Targets.send`), and while the chain rests before its take-off the home is
measured again at every target from the newest step (the estimate settles after its start);
with the whole-chain feed-forward, the carried links (:class:`~.carrying.Carrying`) are flown by
their neighbours. Targets are stamped on each link's own clock.

Distributed mode with ``trajectory.kind = "cpg"``: the leader publishes every link's targets
(:class:`~companion.messages.ChainTargets`) and the others forward their links' share
(:meth:`Targets.forward`); each engine also steps its own copy of the generator so that a new
leader continues the motion, and sends its own targets while no leader's arrive.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from ..messages import ChainTargets, PoseTarget
from ..quantiles import Quantiles
from ..skeleton.kinematics import chain_middle
from ..trajectory import make_trajectory
from .carrying import Carrying
from .home import HOME_MARGIN_S, NetHome
from .links import LinkTrack
from .outputs import TargetOut

__all__ = ["Targets"]

log = logging.getLogger(__name__)


class Targets:
    """The target source of one engine's ``links`` (``d``: their tip vectors) for ``setup`` (a
    :class:`~companion.config.CompanionSetup`).

    Args:
        group, net: distributed mode's group and group link (else ``None``).
        trajectory: a target source to use instead of the one built from the config at the first
            targets.
        start_center: the trajectory's anchor [m] (``None``: the chain's estimated middle from
            ``estimate`` at the first targets).
        estimate: ``(p, q)`` of ``links``, the newest step's estimate, or ``None`` before the
            first step: where a centralised companion's home is (``trajectory.home``).
        carrying: who is carried when targets are due.
        emit: takes each :class:`~.outputs.TargetOut`.
        timer: measures the targets' compute time only (``compute_ms``, never a decision).
    """

    def __init__(self, setup, links: list[LinkTrack], d: np.ndarray, group: int | None, net, trajectory,
                 start_center, carrying: Carrying, emit: Callable[[object], None], estimate: Callable[[], tuple | None],
                 timer=time.perf_counter):
        self.setup = setup
        self.links = links
        self.d = d
        self.n = setup.skeleton.n_links
        self.group = group
        self.net = net
        self.trajectory = trajectory
        self.carrying = carrying
        self._emit = emit
        self._estimate = estimate
        self._timer = timer
        #: the compute time [ms] of each :meth:`send` (the trajectory's targets with their feed-forward)
        self.compute_ms = Quantiles()
        self.period_us = int(round(1e6 / setup.companion.target_rate_hz))
        self._t0_us = 0
        self._started = False
        self._start_center = None if start_center is None else np.asarray(start_center, dtype=float)
        #: the targets wait for the first step's estimate: the anchor or the home is there
        chain = setup.trajectory.kind != "formation"  # (a formation flies its own start pose: no anchor)
        self._from_estimate = self._start_center is None or (setup.trajectory.home == "estimate" and net is None
                                                             and chain)
        #: the trajectory's shift to where the estimate puts the chain at the start [m, world]
        self.home_offset_w_m = np.zeros(3)
        #: distributed mode: the home the groups agree on (:mod:`.home`; ``None``: the anchor as given)
        self.home = (NetHome(group, setup.companion.group_layout(self.n), net, links, d, self.n, self._start_center)
                     if net is not None and setup.trajectory.home == "estimate" and chain
                     and self._start_center is not None else None)
        #: trajectory time until which the home is measured again at every target, the chain still at
        #: rest and its estimate settling (:data:`~.home.HOME_MARGIN_S` before the take-off starts)
        self.refine_s = (max(setup.trajectory.takeoff_start_s - HOME_MARGIN_S, 0.0)
                         if setup.trajectory.kind not in ("rest", "formation") else 0.0)
        self._planned: np.ndarray | None = None  # (n, 3) the trajectory's link centres at its start
        self._home_kept = False  # (a centralised companion's home no longer measured)
        #: CPG targets travel over the network from the leader (distributed mode)
        self.via_net = net is not None and setup.trajectory.kind == "cpg"
        self.counts = {"published": 0, "forwarded": 0, "own": 0, "received": 0, "stale": 0}
        self._leader_targets_s = -np.inf
        self._forwarded_time_us = -1

    def send(self, now_s: float, t_us: int, next_step_us: int) -> bool:
        """Every link's target for the cycle clock ``t_us`` (or, from a follower in distributed CPG
        mode, nothing while the leader's are being forwarded); ``next_step_us``: the cycle whose
        leader publishes them. ``False``: nothing is due yet (the home waits for the first step's
        estimate, or for the group that measures it)."""
        t_traj_s = (t_us - (self._t0_us if self._started else self._start_us(t_us))) * 1e-6
        if self.home is not None:
            if self.trajectory is None:  # (a group's trajectory is the shared anchor's, shifted by the home)
                self.trajectory = self._make_trajectory(self._start_center)
            if self._planned is None:
                self._planned = getattr(self.trajectory, "hover", self.trajectory).pose(0.0)[0]
            offset = self.home.offset(now_s, self._estimate(), self._planned, t_traj_s, self.refine_s)
            if offset is None:
                return False
            self.home_offset_w_m = offset
        elif self.trajectory is not None and self._from_estimate and self._start_center is not None \
                and not self._home_kept:
            if t_traj_s < self.refine_s:
                middle = self._estimated_middle()  # (the chain at rest: measured again, its estimate settling)
                if middle is not None:
                    self.home_offset_w_m = middle - self._start_center
            else:
                self._home_kept = True
                log.info("home kept for the flight: the trajectory flown %s m from its anchor",
                         ", ".join(f"{x:.2f}" for x in self.home_offset_w_m))
        if self.trajectory is None:
            center = self._start_center
            if self._from_estimate:
                middle = self._estimated_middle()
                if middle is None:
                    return False
                if center is None:
                    center = middle
                self.home_offset_w_m = middle - center
                if self._start_center is not None:
                    log.info("home: the trajectory flown from the estimated start (%s m), %.2f m from its anchor; "
                             "measured again while the chain rests, until the take-off",
                             ", ".join(f"{x:.2f}" for x in middle), float(np.linalg.norm(self.home_offset_w_m)))
            self.trajectory = self._make_trajectory(center)
        if self.home is not None:
            self.home.publish(t_us)
        if not self._started:
            self._started = True
            self._t0_us = self._start_us(t_us)
        # Trajectory time starts with the first targets, once every link has reported (and the
        # first step has run, for the home): on hardware the flight controllers have been up for a
        # while; in SITL this is within a step of t = 0.
        passive = self.carrying.now(now_s, t_us)
        t0 = self._timer()
        targets = self.trajectory.targets((t_us - self._t0_us) * 1e-6, passive=passive)
        if self.home_offset_w_m.any():  # (the targets this group sends or publishes)
            targets = list(targets)
            for i in range(len(targets)) if self.via_net else (lk.index for lk in self.links):
                targets[i] = _shifted(targets[i], self.home_offset_w_m)
        self.compute_ms.add((self._timer() - t0) * 1e3)
        if self.via_net:
            if self.net.leads(next_step_us, now_s):
                self.net.publish_targets(ChainTargets.of(self.group, t_us, self.counts["published"] & 0xFFFFFFFF,
                                                         range(self.n), targets))
                self.counts["published"] += 1
            elif now_s - self._leader_targets_s < 3e-6 * self.period_us:
                return True  # the leader's targets are being forwarded (:meth:`forward`)
            self.counts["own"] += 1
        for lk in self.links:
            self._out(lk, t_us, targets[lk.index])
        return True

    def _make_trajectory(self, center_w_m):
        """The configured trajectory anchored at ``center_w_m``."""
        return make_trajectory(self.setup.trajectory, self.setup.motion, self.setup.skeleton, center_w_m,
                               load=self.setup.load)

    def _estimated_middle(self) -> np.ndarray | None:
        """The chain's middle point in the newest step's estimate (``None``: no step yet, or a link
        without a finite estimate in it)."""
        estimate = self._estimate()
        if estimate is None:
            return None
        p, q = estimate
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            return None
        return chain_middle(np.asarray(p, dtype=float), np.asarray(q, dtype=float), self.d)

    def _start_us(self, t_us: int) -> int:
        """Where trajectory time starts on the time base: 0 for distributed companions on the links'
        shared clock (SITL: simulation time, the same in every group), else the first targets."""
        shared = self.net is not None and self.setup.companion.time_base == "flight_controller"
        return 0 if shared else t_us

    def forward(self, msg: ChainTargets, now_s: float) -> None:
        """Send this group's links their share of the leader's CPG targets."""
        self.counts["received"] += 1
        if msg.time_us <= self._forwarded_time_us:
            self.counts["stale"] += 1  # out of order, or a second leader during a hand-over
            return
        self._forwarded_time_us = msg.time_us
        self._leader_targets_s = now_s
        rows = {link: k for k, link in enumerate(msg.links)}
        for lk in self.links:
            k = rows.get(lk.index)
            if k is not None:
                self._out(lk, msg.time_us, msg.target(k))
        self.counts["forwarded"] += 1

    def _out(self, lk: LinkTrack, time_us: int, target: PoseTarget) -> None:
        self.carrying.on_target(lk.index, target)
        self._emit(TargetOut(lk.row, lk.system_id, lk.to_link_clock_us(time_us), target))


def _shifted(target: PoseTarget, offset_w_m: np.ndarray) -> PoseTarget:
    """``target`` moved by ``offset_w_m``: its fields and the attitude forms it has cached (``R_d``,
    ``R_tuple``: the same attitude), the position moved. (Built without the dataclass's ``__init__``,
    which a frozen target's fields need not pass again.)"""
    out = object.__new__(PoseTarget)
    fields = out.__dict__
    fields.update(target.__dict__)
    fields["p_w_m"] = target.p_w_m + offset_w_m
    return out

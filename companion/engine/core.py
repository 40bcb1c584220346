"""The companion engine: everything the companion decides, with no sockets, clocks or threads.

:class:`CompanionEngine` takes typed inputs, each with the time it happened on the caller's
monotonic clock (``now_s``), hands each concern to the part that owns it and returns the outputs
of :meth:`~CompanionEngine.poll`. The parts: :class:`~.admission.Admission` (time base,
plausibility, the cycle clock), :class:`~.selection.LinkSelection` (who takes part in a step),
:class:`~.step.ChainStep` (the 20 Hz step, the distributed halves, the step log),
:class:`~.targets.Targets` with :class:`~.carrying.Carrying` (targets, carried links) and
:class:`~.arming.Arming` (ARM and stream commands). This module keeps the schedule: what runs
when, on the links' flight-controller time.
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import replace

import numpy as np

from ..config import CompanionSetup
from ..estimation.neighbour import NeighbourMeasurement, NeighbourView, mount_covariance
from ..estimation.so3 import quat_to_rotmat
from ..messages import LinkState, NeighbourPose
from ..plausibility import StampGate
from ..quantiles import Quantiles
from ..trajectory import chain_model
from .admission import Admission
from .arming import RETRY_S, Arming
from .carrying import Carrying
from .links import LinkTrack, LinkWarnings, usec
from .outputs import Command, Heartbeat, HealthDue
from .selection import LAG_LIMIT_US, LinkSelection
from .silence import StreamLoss
from .step import ChainStep
from .targets import Targets

__all__ = ["CompanionEngine"]

log = logging.getLogger(__name__)


class CompanionEngine:
    """The companion's decisions for its links (see :mod:`companion.engine`).

    Args:
        setup: the companion's configuration (a SITL scenario is one too).
        group: 0-based group this engine serves (distributed mode), else ``None`` (every link).
        start_center: anchor of the trajectory [m] (default ``trajectory.anchor_w_m``, else the
            chain's middle in the first step's estimate: :mod:`.targets`).
        net: the distributed mode's :class:`~companion.fleetnet.group.GroupLink`.
        trajectory: a target source to use instead of the one built from the config at the first
            targets (batch mode shares one between its group engines: they would compute the same).
        timer: measures the step's and the targets' compute time only (never drives a decision).
    """

    def __init__(self, setup: CompanionSetup, *, group: int | None = None, start_center=None, net=None,
                 trajectory=None, timer=time.perf_counter):
        cfg = setup.companion
        self.setup = setup
        self.cfg = cfg
        n = setup.skeleton.n_links
        self.n = n
        self.groups = cfg.group_layout(n)
        if cfg.distributed and group is None:
            raise ValueError(f"companion.distributed: give the group this companion serves (--group 1..{len(self.groups)})")
        if group is not None and not cfg.distributed:
            raise ValueError("--group: only for distributed companions (companion.distributed = true)")
        if group is not None and not 0 <= group < len(self.groups):
            raise ValueError(f"--group {group + 1}: the config has groups 1..{len(self.groups)}")
        if (group is None) != (net is None):
            raise ValueError("a distributed engine needs its group's network (net), and only it")
        if start_center is None:
            start_center = setup.trajectory.anchor_w_m
        if group is not None and start_center is None and cfg.targets == "trajectory":
            raise ValueError("distributed companions must share the trajectory's anchor: set trajectory.anchor_w_m "
                             "or give --start-center")
        if setup.trajectory.feedforward and cfg.targets == "trajectory":
            chain_model(setup.skeleton)  # fail at start, not at the first target, without pinocchio
        self.group = group
        self.net = net
        members = self.groups[group] if group is not None else tuple(range(n))
        d = setup.skeleton.d_b_m[list(members)]
        endpoints = cfg.endpoints(n)
        self.links = [LinkTrack(i, row, endpoints[i].system_id, stamps=StampGate(cfg.stamp_window),
                                loss=StreamLoss.of_stream(cfg.state_rate_hz, cfg.carry_silence_cap_s))
                      for row, i in enumerate(members)]
        self._out: list = []
        warnings = LinkWarnings()
        self.admission = Admission(cfg, warnings, self.links)
        self.selection = LinkSelection(cfg, self.links, d, warnings)
        self.step = ChainStep(cfg, self.links, d, self.groups, self.selection, net, self._out.append, timer,
                              home=lambda: self.targets.home_offset_w_m)
        self.carrying = Carrying(cfg, self.links, group, self.groups, net)
        self.targets = Targets(setup, self.links, d, group, net, trajectory, start_center, self.carrying,
                               self._out.append, lambda: self.step.latest, timer)
        self.arming = Arming(cfg, self._out.append)
        self.period_us = int(round(1e6 / cfg.rate_hz))
        self.next_step_us: int | None = None
        self.next_target_us: int | None = None
        self._next_heartbeat_s = -np.inf
        self._next_health_s: float | None = None
        self._heard = True  # an input since the last poll (:meth:`needs_poll`)

    # -- figures the parts keep (read by callers and the reports) --------------------------------
    @property
    def fc_time_us(self) -> int:
        """The cycle clock: the newest plausible stamp received, on the time base [us]."""
        return self.admission.fc_time_us

    @property
    def trajectory(self):
        """The target source (``None`` before the first targets unless one was given)."""
        return self.targets.trajectory

    @property
    def log(self) -> dict[str, list]:
        """The step log, by :data:`~.step.STEP_LOG_KEYS`."""
        return self.step.log

    @property
    def withheld(self) -> int:
        """Steps in which no link could be corrected."""
        return self.selection.withheld

    @property
    def degraded(self) -> int:
        """Steps in which some link was left out."""
        return self.selection.degraded

    @property
    def passive_counts(self) -> dict[str, int]:
        """Distributed mode: the carried-links messages published, received and rejected."""
        return self.carrying.counts

    # -- inputs ----------------------------------------------------------------------------------
    def row_of(self, system_id: int) -> int | None:
        """This engine's row of the link with ``system_id`` (``None``: not one of its links)."""
        for lk in self.links:
            if lk.system_id == system_id:
                return lk.row
        return None

    def on_heartbeat(self, row: int, now_s: float) -> None:
        """A link's heartbeat: ask for its state stream until it acknowledges."""
        self._heard = True
        self.arming.on_heartbeat(self.links[row], now_s)

    def on_command_ack(self, row: int, command: Command, accepted: bool, result: int = 0) -> None:
        """A link's answer to an ARM or stream command (``result``: its MAV_RESULT)."""
        self._heard = True
        self.arming.on_command_ack(self.links[row], command, accepted, result)

    def on_system_time(self, row: int, time_unix_us: int, time_boot_ms: int) -> None:
        """``gps`` time base: the link's boot-to-GPS offset from SYSTEM_TIME."""
        self._heard = True
        self.admission.on_system_time(self.links[row], time_unix_us, time_boot_ms)

    def on_rejected(self, row: int, kind: str, reason: str) -> None:
        """A state message from the link that failed validation (counted and logged)."""
        self._heard = True
        lk = self.links[row]
        lk.rejected += 1
        log.warning("link %d: rejected %s: %s", lk.index + 1, kind, reason)

    def on_neighbour(self, t_capture_s: float, measurement: NeighbourMeasurement) -> None:
        """A camera measurement between two of this engine's links (``observer`` and ``observed``
        are rows), captured at ``t_capture_s`` on the observing link's clock: applied at the next
        step (a distributed group's local half) that holds both (:mod:`.neighbours`). With
        ``neighbour_cameras`` off, or for a row the engine does not have, it is counted as left
        out. Its covariance gets the mounts' share (``neighbour_mount_std_m`` / ``_deg``:
        :func:`~companion.estimation.neighbour.mount_covariance`)."""
        if not self.cfg.neighbour_cameras or max(measurement.observer, measurement.observed) >= len(self.links):
            self.step.neighbours.refuse()
            return
        offset_us = self.links[measurement.observer].offset_us or 0  # (the link's clock to the time base)
        mounts = mount_covariance(measurement.t_cm_m, self.cfg.neighbour_mount_std_m,
                                  np.radians(self.cfg.neighbour_mount_std_deg))
        self.step.neighbours.add((usec(t_capture_s) + offset_us) * 1e-6,
                                 replace(measurement, cov=measurement.cov + mounts))

    def on_neighbour_pose(self, pose: NeighbourPose) -> None:
        """A neighbour pose off the wire (chain indices, :class:`~companion.messages.NeighbourPose`):
        :meth:`on_neighbour` between the rows of its links, or counted as left out when this
        engine does not step both (another group's pair, a pair across two groups)."""
        row_of = {lk.index: lk.row for lk in self.links}
        if pose.observer not in row_of or pose.observed not in row_of:
            self.step.neighbours.refuse()
            return
        try:
            view = NeighbourView(pose.camera_pos_b_m, quat_to_rotmat(pose.q_bc_wxyz), pose.marker_pos_b_m,
                                 quat_to_rotmat(pose.q_bm_wxyz))
            m = NeighbourMeasurement(row_of[pose.observer], row_of[pose.observed], quat_to_rotmat(pose.q_cm_wxyz),
                                     pose.t_cm_m, pose.cov_c, view)
        except ValueError:  # shapes, a covariance not positive definite: a message not from the wire's decoder
            self.step.neighbours.refuse()
            return
        self.on_neighbour(pose.t_capture_s, m)

    def on_state(self, row: int, state: LinkState, flags: int, now_s: float, correction_seq: int = 0,
                 correction_latency_us: int = 0) -> bool:
        """A validated state of link ``row`` (``state.link`` its chain index, stamped on the link's
        clock), with the flags and the correction it reports. ``False``: not usable yet (no GPS
        time offset for this link, or its stamp was rejected: then nothing it carries is used,
        flags and reported latency included)."""
        self._heard = True
        return self.admission.on_state(self.links[row], state, flags, now_s, correction_seq, correction_latency_us)

    # -- the loop ----------------------------------------------------------------------------------
    def next_deadline_s(self, now_s: float) -> float | None:
        """When, from ``now_s`` on, :meth:`poll` next has something to do without new input (the network's deadlines)."""
        return self.net.next_deadline_s(now_s) if self.net is not None else None

    def needs_poll(self, now_s: float) -> bool:
        """Whether :meth:`poll` at ``now_s`` has anything to do: an input since the last poll (a
        link's message or acknowledgement), an output waiting, an event on the network, or a timer
        due (the heartbeat, the health table, an arm retry, the network's deadlines); the same tests
        as the poll's. ``False``: a poll would change nothing and return nothing, so a caller that
        polls on every tick of a simulation (the batch runner) may leave it out."""
        if self._heard or self._out or self._next_health_s is None:
            return True
        if now_s >= self._next_heartbeat_s or now_s >= self._next_health_s:
            return True
        if self.arming.any_due(self.links, now_s):
            return True
        return self.net is not None and self.net.needs_pump(now_s)

    def poll(self, now_s: float) -> list:
        """Run what is due at ``now_s``; returns the outputs, in order: corrections, targets,
        commands (arm, stream rate), the heartbeat and the health report when due
        (:mod:`companion.engine.outputs`)."""
        self._heard = False
        if self.net is not None:
            self.step.finish(self.net.pump(now_s))
            for msg in self.net.take_targets():
                if self.targets.via_net:
                    self.targets.forward(msg, now_s)
            for msg in self.net.take_passive():
                self.carrying.on_remote(msg, self.fc_time_us)
            for msg in self.net.take_home():
                if self.targets.home is not None:
                    self.targets.home.on_remote(msg)
        self._duties(now_s)
        if self._all_states():
            t = self.fc_time_us
            if self.next_step_us is None:
                # steps on the period grid of flight-controller time: the groups' cycles coincide
                self.next_step_us = -(-t // self.period_us) * self.period_us
                self.next_target_us = t
            waiting = self._send_targets(now_s, t) is False
            if t >= self.next_step_us:
                newest = [usec(lk.state.time_s) for lk in self.links]
                # Step once every link has reported for this step time (a coherent snapshot); a link
                # lagging more than LAG_LIMIT behind the others is not waited for (and left out of the
                # step, :meth:`LinkSelection.plan`), so one silent link degrades the step, never stalls it.
                spread = max(newest) - min(newest)
                if min(newest) >= self.next_step_us or spread > LAG_LIMIT_US:
                    self.step.run(now_s, t, self.next_step_us)
                    self.next_step_us += self.period_us * max(1, (t - self.next_step_us) // self.period_us + 1)
                    if waiting:  # the first targets wait for the first step's estimate (:mod:`.targets`)
                        self._send_targets(now_s, t)
            self.arming.run(self.links, now_s)
        out = self._out.copy()
        self._out.clear()
        return out

    def _send_targets(self, now_s: float, t: int) -> bool | None:
        """The targets if due at the cycle clock ``t`` (``None``: not due; ``False``: due, but
        waiting for the first step)."""
        if self.cfg.targets != "trajectory" or t < self.next_target_us:
            return None
        if not self.targets.send(now_s, t, self.next_step_us):
            return False
        period = self.targets.period_us
        self.next_target_us += period * max(1, (t - self.next_target_us) // period + 1)
        return True

    def _duties(self, now_s: float) -> None:
        """The heartbeat every :data:`~.arming.RETRY_S` and the health report every ``health_period_s``."""
        if now_s >= self._next_heartbeat_s:
            self._out.append(Heartbeat())
            self._next_heartbeat_s = now_s + RETRY_S
        if self._next_health_s is None:
            self._next_health_s = now_s + self.cfg.health_period_s
        elif now_s >= self._next_health_s:
            self._out.append(HealthDue(self.cfg.health_period_s))
            self._next_health_s = now_s + self.cfg.health_period_s

    def _all_states(self) -> bool:
        return all(lk.state is not None for lk in self.links)

    # -- reports ---------------------------------------------------------------------------------------
    def health_rows(self, period_s: float, now_s: float) -> list[dict]:
        """Per link, since the last call: state rate [Hz], age of the newest state [ms], states
        rejected (malformed, replayed, stamped too far ahead: totals), reboots, steps it was left
        out of in the period and why it is out now (``""``: in), correction latency p50 / p99 [ms]
        (``None`` without samples)."""
        rows = []
        for lk in self.links:
            lat = np.asarray(lk.latency_window_ms)
            excluded = sum(lk.excluded.values())
            rows.append({
                "link": lk.index + 1, "system_id": lk.system_id,
                "state_hz": (lk.states - lk.states_at_report) / period_s,
                "age_ms": (now_s - lk.last_state_s) * 1e3 if lk.last_state_s is not None else float("nan"),
                "rejected": lk.rejected + lk.replayed + lk.future,
                "replayed": lk.replayed, "future": lk.future, "reboots": lk.reboots,
                "excluded": excluded - lk.excluded_at_report,
                "status": lk.status or ("gps" if lk.row in self.selection.one_way else ""),
                "latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
                "latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
            })
            lk.states_at_report = lk.states
            lk.excluded_at_report = excluded
            lk.latency_window_ms = []
        return rows

    def summary(self) -> dict:
        """The run's totals: steps, withheld and degraded steps, step compute time, correction
        latency, the trajectory's shift to the estimated start (:mod:`.targets`), per link its
        counters, carried time and stretches, the times it was taken to lift itself while silent,
        the estimated loss of its state stream and its exclusions; in distributed mode the group
        link's figures, the CPG targets' counts and the other groups' carried links."""
        lat = functools.reduce(Quantiles.merge, [lk.latencies_ms for lk in self.links], Quantiles())
        steps = self.step.step_times_ms
        t_s = self.fc_time_us * 1e-6
        return {
            "steps": steps.count,
            "withheld_steps": self.selection.withheld,
            "degraded_steps": self.selection.degraded,
            "bridged_steps": self.step.bridged_steps,
            "common_mode_kept": self.selection.common_mode_kept,
            "neighbour_measurements": self.step.neighbours.counts(),
            "step_ms": {"p50": steps.percentile(50), "p99": steps.percentile(99)} if steps.count else None,
            "targets_ms": ({"p50": self.targets.compute_ms.percentile(50), "p99": self.targets.compute_ms.percentile(99)}
                           if self.targets.compute_ms.count else None),
            "home_offset_m": [round(float(x), 4) for x in self.targets.home_offset_w_m],
            "home": self.targets.home.summary() if self.targets.home is not None else None,
            "correction_latency_ms": {"p50": lat.percentile(50), "p99": lat.percentile(99),
                                      "samples": lat.count} if lat.count else None,
            "links": {str(lk.system_id): {"states": lk.states, "rejected": lk.rejected, "replayed": lk.replayed,
                                          "future": lk.future, "reboots": lk.reboots,
                                          "gps_fault_steps": lk.gps_fault_steps,
                                          "bridged_steps": lk.bridged_steps,
                                          "carried_s": round(lk.carried.seconds(t_s), 3),
                                          "carried_stretches": lk.carried.stretches,
                                          "carry_released": self.carrying.release_count.get(lk.index, 0),
                                          "state_loss": round(lk.loss.fraction, 4) if lk.loss is not None else None,
                                          "excluded_steps": dict(lk.excluded)} for lk in self.links},
            **(self.net.summary() if self.net is not None else {}),
            **({"cpg_targets": dict(self.targets.counts)} if self.targets.via_net else {}),
            **({"carried_by_other_groups_s": {
                str(self.cfg.endpoints(self.n)[i].system_id): round(clock.seconds(t_s), 3)
                for i, clock in sorted(self.carrying.remote_carried.items())},
                "carried_links_messages": dict(self.carrying.counts)} if self.net is not None else {}),
        }

    def log_arrays(self) -> dict[str, np.ndarray]:
        """The step log as arrays (keys with at least one row)."""
        return {k: np.asarray(v) for k, v in self.step.log.items() if v}

"""The companion daemon: the :class:`~companion.engine.CompanionEngine` behind MAVLink ports (and Zenoh).

The engine decides everything (steps, corrections, targets, arming, time base, the distributed
halves); this shell owns the I/O and the clocks (passed in; the system's by default). For every
link it holds a :class:`~companion.mavlink.port.MavlinkPort` (UDP in SITL, serial on hardware):

* frames in: with ``[signing]`` (``onboard`` link mode) every frame is signed and checked by
  the port first (unsigned, wrongly signed and replayed frames are counted per link: the
  health table's ``sig rej`` column); a message from another system id is counted as ignored; HEARTBEAT, COMMAND_ACK,
  SYSTEM_TIME and the state message (SKELETON_LINK_STATE, or ODOMETRY in ``standard`` mode,
  decoded by :mod:`companion.mavlink.codec` / :mod:`companion.mavlink.standard`) go to the
  engine with the arrival time; a state that fails validation (non-finite, non-unit quaternion,
  covariance not positive definite) is counted per link and dropped; STATUSTEXT is logged;
* the engine's outputs out: SKELETON_CORRECTION (or, in ``standard`` mode, the corrected pose as
  external-vision ODOMETRY, MAV_FRAME_LOCAL_NED, for PX4's EKF2), SET_POSITION_TARGET_LOCAL_NED +
  SET_ATTITUDE_TARGET (+ SKELETON_TARGET_FEEDFORWARD in dialect mode: angular acceleration and
  whole-chain feed-forward), COMMAND_LONG (ARM, SET_MESSAGE_INTERVAL), a 1 Hz HEARTBEAT
  (MAV_TYPE_ONBOARD_CONTROLLER), and every ``health_period_s`` the health table in the log.

Distributed mode (``companion.distributed``, one daemon per group, ``--group``): the engine's
:class:`~companion.fleetnet.group.GroupLink` runs on a Zenoh session
(:class:`~companion.fleetnet.bus.FleetBus`, imported only in this mode); malformed Zenoh payloads
are counted per key and logged.

The vision consumer's messages (:class:`~companion.fleetnet.inbox.MessageInbox`) arrive on the
fleet session (distributed) or on a session of the daemon's own (centralised, ``[zenoh]
vision_session``): with neighbour cameras (``companion.neighbour_cameras``) its
:class:`~companion.messages.NeighbourPose` messages go to the engine before its next poll; with a
slung load (``[load]``) its :class:`~companion.load.model.LoadObservation` messages go to the load
filter (:class:`~companion.load.tracker.LoadTracker`), which also takes a sample of every carrying
vehicle's state at ``load.vehicle_rate_hz`` of the links' time. The summary's
``neighbour_poses_wire`` and ``load_observations_wire`` count what arrived and what was dropped;
``load`` the filter's counters.

Bad input never stops the daemon: unparseable bytes and unknown ids are counted by the ports,
invalid states by the engine. The run folder gets ``companion_link<sysid>.tlog`` (one per link),
``companion.log`` (by the
CLI), ``companion_log.stream`` (the engine's step log, appended every second with the rows since
the last flush, which then leave memory: a companion killed in flight keeps all but its last
second; read it with :func:`companion.logstream.read_log_stream`), ``companion_log.npz`` (the
whole step log, read back from the stream at the end), ``companion.mcap`` (the step log, the health reports and the links' STATUSTEXTs for Foxglove
and Lichtblick, at the end, when the ``mcap`` package is installed:
:mod:`companion.recording.companion_mcap`), ``companion_summary.json`` and, with a slung load,
``load.npz`` (the load filter's log, :func:`companion.load.tracker.log_keys`).
"""

from __future__ import annotations

import json
import logging
import signal
import time
from collections import deque
from pathlib import Path

import numpy as np

from .kernels import warm as _kernels
from .config import CompanionSetup
from .logstream import LogStream
from .engine import (
    Command,
    CommandOut,
    CompanionEngine,
    CorrectionOut,
    HealthDue,
    Heartbeat,
    TargetOut,
)
from .mavlink.codec import decode_link_state, encode_correction, encode_target_feedforward, usec
from .mavlink.dialect import load_dialect
from .mavlink.port import MavlinkPort
from .mavlink.standard import decode_odometry, encode_attitude_target, encode_odometry, encode_position_target
from .mavlink.timesync import LinkTimesync
from .mavlink.tlog import TlogWriter
from .mavlink.transport import wait_readable
from .messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, MessageError

__all__ = ["CompanionDaemon", "COMPANION_SYSTEM_ID", "COMPANION_COMPONENT_ID", "format_health_table"]

log = logging.getLogger(__name__)
D = load_dialect()

COMPANION_SYSTEM_ID = 190
COMPANION_COMPONENT_ID = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
#: health reports and STATUSTEXTs kept for companion.mcap (the newest; a report a minute at the
#: default period keeps a day of flight)
MAX_RECORDED = 100_000
_ACCEPT = frozenset({"HEARTBEAT", "SKELETON_LINK_STATE", "ODOMETRY", "COMMAND_ACK", "STATUSTEXT", "SYSTEM_TIME",
                     "TIMESYNC"})
_ACK_COMMANDS = {D.MAV_CMD_COMPONENT_ARM_DISARM: Command.ARM, D.MAV_CMD_SET_MESSAGE_INTERVAL: Command.STREAM}
#: standard mode: a link not synchronised over TIMESYNC after this long [s] is warned of, once
TIMESYNC_WARN_S = 20.0


def format_health_table(rows: list[dict], ports: list[MavlinkPort]) -> str:
    """The health table: the engine's per-link rows beside each port's state and counters.

    ``lost``: gaps in the link's MAVLink sequence numbers (frames lost on the wire, totals);
    ``dropped``: unparseable frames; ``rejected``: states refused (malformed, replayed, stamped
    too far ahead); ``sig rej``: frames refused by MAVLink signing; ``out``: steps of the period
    the link was left out of, and why it is out now (:data:`~companion.engine.selection.EXCLUSION_REASONS`)."""
    lines = [f"{'link':>4} {'sysid':>5} {'port':>4} {'states/s':>8} {'age ms':>7} {'lost':>6} {'dropped':>7} "
             f"{'rejected':>8} {'sig rej':>7} {'out':>12} {'lat p50 ms':>10} {'lat p99 ms':>10}"]
    for row, port in zip(rows, ports):
        up = "up" if port.transport.connected else "down"
        p50, p99 = (f"{row[k]:10.1f}" if row[k] is not None else f"{'-':>10}" for k in ("latency_p50_ms", "latency_p99_ms"))
        out = f"{row['excluded']} {row['status']}".strip() if row["excluded"] or row["status"] else "0"
        lines.append(f"{row['link']:>4} {row['system_id']:>5} {up:>4} {row['state_hz']:8.1f} {row['age_ms']:7.0f} "
                     f"{port.stats.seq_lost:6d} {port.stats.dropped:7d} {row['rejected']:8d} "
                     f"{port.stats.rejected_signing:7d} {out:>12} {p50} {p99}")
    return "\n".join(lines)


def _warm_kernels(setup: CompanionSetup) -> float | None:
    """The seconds it took to load (or compile) the companion's compiled kernels for ``setup``;
    ``None`` without them (the numpy path)."""
    if not _kernels.ENABLED:
        return None
    with _kernels.compile_notice("the companion's compiled kernels", log, report_done=False):
        return _kernels.warm_up(cpg=setup.trajectory.kind == "cpg")


class CompanionDaemon:
    """See the module docstring. ``group`` (0-based) selects distributed mode's group; ``bus``
    replaces the Zenoh session it would open (tests); ``bus_wait_s``: how long that session waits
    for a listen address no interface holds yet (``None``: until it is up). ``clock`` (monotonic seconds) is the one
    time of the daemon: the engine's inputs and polls, the ports' and the group link's timing;
    ``wall_clock`` (UNIX seconds) stamps the tlogs and the MAVLink signatures."""

    def __init__(self, setup: CompanionSetup, out_dir: Path | None = None, start_center=None,
                 group: int | None = None, bus=None, config_file: str = "<config>", clock=time.monotonic,
                 wall_clock=time.time, bus_wait_s: float | None = None):
        cfg = setup.companion
        self.setup = setup
        self.cfg = cfg
        self.clock = clock
        self.out_dir = out_dir
        # every compiled kernel it runs loaded (or compiled) before its ports open, so that a launcher
        # that waits for them finds it ready to fly, and no load (or compile) in the first SCKF cycle or
        # target set holds up the chain's corrections (None: the numpy path)
        self.kernels_s = _warm_kernels(setup)
        n = setup.skeleton.n_links
        groups = cfg.group_layout(n)
        members = groups[group] if group is not None and 0 <= group < len(groups) else tuple(range(n))
        endpoints = cfg.endpoints(n)
        mode = setup.signing.link_mode("onboard")
        key = setup.signing.key() if mode != "off" else None  # ValueError: no or unreadable key file
        self.ports: list[MavlinkPort] = []
        net = None
        try:
            for i in members:
                sysid = endpoints[i].system_id
                tlog = (TlogWriter(out_dir / f"companion_link{sysid}.tlog", wall_clock=wall_clock,
                                   max_mb=self.cfg.tlog_max_mb or None, keep=self.cfg.tlog_keep)
                        if out_dir is not None else None)
                self.ports.append(MavlinkPort(endpoints[i].url, COMPANION_SYSTEM_ID, COMPANION_COMPONENT_ID, _ACCEPT,
                                              tlog, peer_system_id=endpoints[i].system_id, signing=mode, key=key,
                                              link_id=i, clock=clock, wall_clock=wall_clock))
            if group is not None and cfg.distributed and 0 <= group < len(groups):
                net = self._group_link(setup, group, bus, config_file, bus_wait_s)
            self.engine = CompanionEngine(setup, group=group, start_center=start_center, net=net)
        except Exception:
            self._close_ports()
            if net is not None:
                net.close()
            raise
        self.net = net
        #: standard mode: each link's clock over TIMESYNC, so that PX4 reads the corrections' stamps
        self.timesync = [LinkTimesync() for _ in self.ports] if cfg.mode == "standard" else None
        self._timesync_warned: set[int] = set()  # links warned of no synchronisation
        self._vision_session = None  # a centralised companion's own session for the vision consumer
        self.inboxes: dict = {}
        try:
            self._open_inboxes(setup, net, config_file)
        except Exception:
            self._close_inboxes()
            self._close_ports()
            if net is not None:
                net.close()
            raise
        self.load_tracker = None
        self._next_load_sample_s = -np.inf
        self.load_rejected = 0
        if setup.load is not None:
            from .load.tracker import LoadTracker

            self.load_tracker = LoadTracker(setup.load, fixed_lag_s=setup.load.fixed_lag_s)
        self._stop = False
        self._log_stream = LogStream(out_dir / "companion_log.stream") if out_dir is not None else None
        self._members = members
        #: for companion.mcap: the health reports (time base [s], rows) and the links' STATUSTEXTs
        #: (time base [s], link, severity, text), the newest MAX_RECORDED of each
        self.health_log: deque = deque(maxlen=MAX_RECORDED)
        self.statustext_log: deque = deque(maxlen=MAX_RECORDED)
        #: each link's armed state as its autopilot's HEARTBEAT says (standard mode: ODOMETRY has none)
        self._armed = [False] * len(self.engine.links)

    def _group_link(self, setup: CompanionSetup, group: int, bus, config_file: str, wait_s: float | None):
        from .fleetnet.group import GroupLink
        from .fleetnet.leader import GlobalStepNode

        cfg, zc = setup.companion, setup.zenoh
        n_groups = len(cfg.group_layout(setup.skeleton.n_links))
        node = GlobalStepNode(group, n_groups, zc.order(n_groups), int(round(1e6 / cfg.rate_hz)),
                              shift_deadline_s=zc.shift_deadline_ms * 1e-3, leader_wait_s=zc.leader_wait_ms * 1e-3,
                              handover_cycles=zc.handover_cycles)
        if bus is None:
            try:
                from .fleetnet.bus import FleetBus  # Zenoh: only distributed companions need it
            except ImportError as exc:
                raise ValueError(f"companion.distributed needs Eclipse Zenoh ({exc}): pip install "
                                 "'aerial-skeleton-stack[distributed]'") from None
            bus = FleetBus(zc, setup.zenoh_prefix, group, n_groups, config_file, clock=self.clock, wait_s=wait_s)
        return GroupLink(node, bus, self.clock)

    def _open_inboxes(self, setup: CompanionSetup, net, config_file: str) -> None:
        """Where the vision consumer's messages arrive (module docstring): the fleet session of a
        distributed companion; a session of its own for a centralised one with ``[zenoh]
        vision_session``; nowhere else."""
        kinds = (["neighbour pose"] if setup.companion.neighbour_cameras else []) + (
            ["load observation"] if setup.load is not None else [])
        if not kinds:
            return
        if net is None:
            if not setup.zenoh.vision_session:
                return
            try:
                from .fleetnet.inbox import open_vision_session  # Zenoh: the distributed extra
            except ImportError as exc:
                raise ValueError(f"zenoh.vision_session needs Eclipse Zenoh ({exc}): pip install "
                                 "'aerial-skeleton-stack[distributed]'") from None
            session = self._vision_session = open_vision_session(setup.zenoh, config_file)
        else:
            session = getattr(net.bus, "session", None)  # (an in-process bus has none)
            if session is None:
                return
        from .fleetnet.inbox import MessageInbox

        for kind in kinds:
            self.inboxes[kind] = MessageInbox(session, setup.zenoh_prefix, kind)

    def _close_inboxes(self) -> None:
        for inbox in self.inboxes.values():
            inbox.close()
        self.inboxes = {}
        if self._vision_session is not None:
            from .fleetnet.bus import close_session

            close_session(self._vision_session, "the vision consumer's session")
            self._vision_session = None

    def _drain_inboxes(self) -> None:
        """The vision consumer's messages that arrived: neighbour poses to the engine, load
        observations to the load filter."""
        inbox = self.inboxes.get("neighbour pose")
        if inbox is not None:
            for pose in inbox.drain():
                self.engine.on_neighbour_pose(pose)
        inbox = self.inboxes.get("load observation")
        if inbox is not None:
            for obs in inbox.drain():
                try:
                    self.load_tracker.push_observation(obs)
                except ValueError as exc:  # a vehicle the load has no cable to
                    self.load_rejected += 1
                    if self.load_rejected <= 5:
                        log.warning("load observation dropped: %s", exc)

    def _sample_load(self) -> None:
        """A sample of every carrying vehicle for the load filter, when one is due on the links' time."""
        from .load.tracker import vehicle_states

        veh = vehicle_states([lk.state for lk in self.engine.links])
        if veh is None or veh.stamp_s < self._next_load_sample_s:
            return
        period = 1.0 / self.setup.load.vehicle_rate_hz
        self._next_load_sample_s = max(self._next_load_sample_s + period, veh.stamp_s + 0.5 * period)
        self.load_tracker.push_vehicles(veh)

    # -- input ---------------------------------------------------------------------------------------
    def _on_message(self, row: int, msg, now_s: float) -> None:
        engine, port = self.engine, self.ports[row]
        kind = msg.get_type()
        if msg.get_srcSystem() != engine.links[row].system_id:
            port.stats.ignored += 1
            return
        if kind == "HEARTBEAT":
            if msg.autopilot != D.MAV_AUTOPILOT_INVALID:  # (the autopilot's, not a camera's or a gimbal's)
                self._armed[row] = bool(msg.base_mode & D.MAV_MODE_FLAG_SAFETY_ARMED)
            engine.on_heartbeat(row, now_s)
        elif kind == "COMMAND_ACK":
            command = _ACK_COMMANDS.get(msg.command)
            if command is not None:
                engine.on_command_ack(row, command, msg.result == D.MAV_RESULT_ACCEPTED, msg.result)
        elif kind == "STATUSTEXT":
            link = engine.links[row].index + 1
            log.info("link %d: %s", link, msg.text)
            self.statustext_log.append((engine.fc_time_us * 1e-6, link, int(msg.severity), str(msg.text)))
        elif kind == "SYSTEM_TIME":
            engine.on_system_time(row, msg.time_unix_usec, msg.time_boot_ms)
        elif kind == "TIMESYNC" and self.timesync is not None:
            self._on_timesync(row, msg, now_s)
        elif (kind, self.cfg.mode) in (("SKELETON_LINK_STATE", "dialect"), ("ODOMETRY", "standard")):
            self._on_state(row, msg, now_s)
        else:
            port.stats.ignored += 1

    def _on_timesync(self, row: int, msg, now_s: float) -> None:
        """The autopilot's TIMESYNC: its request answered on its own clock (once learnt), its
        answer to one of ours taken into that clock's estimate (:mod:`.mavlink.timesync`)."""
        sync, now_ns, link = self.timesync[row], int(now_s * 1e9), self.engine.links[row].index + 1
        was, restarts = sync.synchronised, sync.counts["restarts"]
        if msg.tc1 == 0:
            answer = sync.answer(msg.ts1, now_ns)
            if answer is not None:
                self.ports[row].send(D.MAVLink_timesync_message(*answer))
        else:
            sync.on_answer(msg.tc1, msg.ts1, now_ns)
        if sync.counts["restarts"] > restarts:
            log.warning("link %d: its clock restarted (a reboot): TIMESYNC learnt afresh; PX4 stamps the "
                        "corrections on arrival until it has converged again (about a minute)", link)
        elif sync.synchronised and not was:
            log.info("link %d: clock synchronised over TIMESYNC (offset %.3f s, round trip %.1f ms): PX4 takes "
                     "the corrections' stamps once it has converged too", link, sync.offset_ns * 1e-9,
                     sync.rtt_ns * 1e-6)
            self._timesync_warned.discard(row)

    def _request_timesync(self, now_s: float) -> None:
        now_ns = int(now_s * 1e9)
        for row, (port, sync) in enumerate(zip(self.ports, self.timesync)):
            ts1 = sync.request(now_ns)
            if ts1 is not None:
                port.send(D.MAVLink_timesync_message(0, ts1))
            if sync.waiting_s(now_ns) >= TIMESYNC_WARN_S and row not in self._timesync_warned:
                self._timesync_warned.add(row)
                log.warning("link %d: no TIMESYNC answer with a round trip under %.0f ms in %.0f s: PX4 stamps the "
                            "corrections on arrival (set EKF2_EV_DELAY to the correction latency, "
                            "docs/companion.md)", self.engine.links[row].index + 1,
                            sync.config.max_rtt_ns * 1e-6, TIMESYNC_WARN_S)

    def _on_state(self, row: int, msg, now_s: float) -> None:
        """The link's state message (SKELETON_LINK_STATE, or a stock autopilot's ODOMETRY), validated."""
        engine, index = self.engine, self.engine.links[row].index
        try:
            if msg.get_type() == "SKELETON_LINK_STATE":
                state = decode_link_state(msg, index)
                reported = (msg.flags, now_s, msg.correction_seq, msg.correction_latency_us)
            else:
                # a stock autopilot's EKF output, armed or not as its heartbeat says (a companion
                # that arms links stops at an armed one, as with the dialect's flags)
                flags = STATE_FLAG_EKF_OK | (STATE_FLAG_ARMED if self._armed[row] else 0)
                state, reported = decode_odometry(msg, index), (flags, now_s)
        except MessageError as exc:
            engine.on_rejected(row, msg.get_type(), str(exc))
            return
        if not engine.on_state(row, state, *reported):
            self.ports[row].stats.ignored += 1  # no GPS time from this link yet
        elif self.load_tracker is not None:
            self._sample_load()

    # -- output ------------------------------------------------------------------------------------
    def _carry_out(self, outputs, now_s: float) -> None:
        """The engine's outputs: the messages for each link leave together (one UDP datagram where
        they fit: one wake-up of the link's firmware for its target and correction, not four)."""
        outgoing: dict[int, list] = {}  # port row -> messages, in the engine's order

        def queue(row: int, *msgs) -> None:
            outgoing.setdefault(row, []).extend(msgs)

        for out in outputs:
            if isinstance(out, CorrectionOut):
                if self.cfg.mode == "dialect":
                    queue(out.row, encode_correction(out.correction, out.system_id, 1))
                else:
                    queue(out.row, encode_odometry(out.corrected, usec(out.corrected.time_s),
                                                   estimator_type=D.MAV_ESTIMATOR_TYPE_VISION, rates_known=False))
            elif isinstance(out, TargetOut):
                boot_ms = out.time_us // 1000
                if self.cfg.mode == "dialect":
                    queue(out.row, encode_target_feedforward(out.target, boot_ms, out.system_id),
                          encode_position_target(out.target, boot_ms, out.system_id),
                          encode_attitude_target(out.target, boot_ms, out.system_id))
                else:  # stock PX4: the position target and its heading (its SET_ATTITUDE_TARGET would
                    # be an attitude setpoint with its own thrust, and it knows no feed-forward)
                    queue(out.row, encode_position_target(out.target, boot_ms, out.system_id, yaw=True))
            elif isinstance(out, CommandOut):
                queue(out.row, self._command(out))
            elif isinstance(out, Heartbeat):
                for row in range(len(self.ports)):
                    queue(row, D.MAVLink_heartbeat_message(D.MAV_TYPE_ONBOARD_CONTROLLER, D.MAV_AUTOPILOT_INVALID,
                                                           0, 0, D.MAV_STATE_ACTIVE, 3))
                if self._log_stream is not None:  # once a second, like the heartbeat
                    self._log_stream.flush(self.engine.log, keep=0)
            elif isinstance(out, HealthDue):
                log.info("health (last %.0f s):\n%s", out.period_s, self.health_table(out.period_s, now_s))
                if self.net is not None:
                    log.info("%s", self.net.status_line())
        for row, msgs in outgoing.items():
            self.ports[row].send_many(msgs)

    def _command(self, out: CommandOut):
        if out.command is Command.ARM:
            return D.MAVLink_command_long_message(out.system_id, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                                  1, 0, 0, 0, 0, 0, 0)
        mid = D.MAVLINK_MSG_ID_SKELETON_LINK_STATE if self.cfg.mode == "dialect" else D.MAVLINK_MSG_ID_ODOMETRY
        return D.MAVLink_command_long_message(out.system_id, 1, D.MAV_CMD_SET_MESSAGE_INTERVAL, 0, mid,
                                              out.interval_us, 0, 0, 0, 0, 0)

    def health_table(self, period_s: float, now_s: float | None = None) -> str:
        now_s = self.clock() if now_s is None else now_s
        rows = self.engine.health_rows(period_s, now_s)
        self.health_log.append((self.engine.fc_time_us * 1e-6, rows))
        return format_health_table(rows, self.ports)

    # -- main loop ---------------------------------------------------------------------------------------
    def poll(self, timeout_s: float) -> None:
        if self.timesync is not None:  # (sent before the wait: its answer is read as it arrives)
            self._request_timesync(self.clock())
        waitables = list(self.ports)
        if self.net is not None:
            waitables.append(self.net)
            now = self.clock()
            due = self.engine.next_deadline_s(now)
            if due is not None:
                timeout_s = min(timeout_s, max(due - now, 0.0))
        ready = wait_readable(waitables, timeout_s)
        for row, port in enumerate(self.ports):
            if port in ready:
                for msg in port.read():
                    self._on_message(row, msg, self.clock())
        self._drain_inboxes()
        now = self.clock()
        self._carry_out(self.engine.poll(now), now)

    def stop(self, *_args) -> None:
        self._stop = True

    def run(self, duration_s: float | None = None) -> None:
        signal.signal(signal.SIGTERM, self.stop)
        signal.signal(signal.SIGINT, self.stop)
        end = None if duration_s is None else self.clock() + duration_s
        engine = self.engine
        if self.kernels_s is not None:
            log.info("compiled kernels ready in %.1f s", self.kernels_s)
        log.info("companion up: %d link(s) %s, mode %s, SCKF %.0f Hz, groups %s%s; %s", len(self.ports),
                 ", ".join(port.url for port in self.ports), self.cfg.mode, self.cfg.rate_hz, engine.groups,
                 f", serving group {engine.group + 1} (Zenoh prefix {self.setup.zenoh_prefix!r})" if self.net else "",
                 "compiled kernels" if _kernels.ENABLED else "numpy path (no compiled kernels)")
        try:
            while not self._stop and (end is None or self.clock() < end):
                self.poll(0.05)
        finally:
            self.close()

    def summary(self) -> dict:
        out = self.engine.summary()
        for row, (lk, port) in enumerate(zip(self.engine.links, self.ports)):
            out["links"][str(lk.system_id)].update(vars(port.stats))
            if self.timesync is not None:
                out["links"][str(lk.system_id)]["timesync"] = self.timesync[row].report()
        for kind, key in (("neighbour pose", "neighbour_poses_wire"), ("load observation", "load_observations_wire")):
            if kind in self.inboxes:
                out[key] = self.inboxes[kind].summary()
        if self.load_tracker is not None:
            out["load"] = {**self.load_tracker.stats(), "rejected_observations": self.load_rejected}
        return out

    def step_log(self) -> dict[str, np.ndarray]:
        """The whole step log so far: read back from ``companion_log.stream`` (which first gets the
        newest rows), or the engine's in memory without an output folder."""
        if self._log_stream is None:
            return self.engine.log_arrays()
        return self._log_stream.read_back(self.engine.log, keep=0)

    def write_log(self) -> None:
        """The whole step log (``companion_log.npz``; the stream gets its last rows)."""
        if self.out_dir is None:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        tmp = self.out_dir / "companion_log.tmp.npz"
        steps = self.step_log()
        np.savez(tmp, **steps)
        tmp.replace(self.out_dir / "companion_log.npz")
        self.write_mcap(steps)

    def write_mcap(self, steps: dict | None = None) -> Path | None:
        """``companion.mcap`` (:mod:`companion.recording.companion_mcap`): the step log (``steps``,
        :meth:`step_log` when not given), the health reports and the STATUSTEXTs for
        Foxglove and Lichtblick; one log line instead when the ``mcap`` package is missing or there
        is nothing to write."""
        if self.out_dir is None:
            return None
        try:
            from .recording.companion_mcap import COMPANION_MCAP, write_companion_mcap

            path = self.out_dir / COMPANION_MCAP
            steps = self.step_log() if steps is None else steps
            write_companion_mcap(path, steps, self.setup.skeleton.d_b_m[list(self._members)],
                                 first_link=self._members[0] + 1, health=self.health_log,
                                 statustext=self.statustext_log)
        except ImportError:
            log.info("companion.mcap not written: the mcap package is missing (pip install 'mcap>=1.1')")
            return None
        except Exception as exc:  # noqa: BLE001 (the step log and summary stand without it)
            log.warning("companion.mcap not written: %s", exc)
            return None
        return path

    def _close_ports(self) -> None:
        for port in self.ports:
            port.close()

    def close(self) -> None:
        self._drain_inboxes()  # what arrived since the last poll is counted (and used) too
        summary = self.summary()
        log.info("companion summary: %s", json.dumps({k: summary[k] for k in (
            "steps", "step_ms", "targets_ms", "correction_latency_ms", "global_step", "round_trip_ms_as_leader", "failovers")
            if k in summary}))
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            # the summary first: it is small, and what a launcher that runs out of patience reads
            (self.out_dir / "companion_summary.json").write_text(json.dumps(summary, indent=1, default=str))
            self.write_log()
            self._log_stream.close()
            if self.load_tracker is not None:
                np.savez_compressed(self.out_dir / "load.npz", **self.load_tracker.arrays())
        self._close_ports()
        self._close_inboxes()
        if self.net is not None:
            self.net.close()

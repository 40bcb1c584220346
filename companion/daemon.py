"""The companion daemon: collects link states over MAVLink, applies the constraints, sends corrections.

One daemon serves the links of its chain (or group): for each it holds a :class:`MavlinkPort`
(UDP in SITL, serial on hardware). Everything runs on flight-controller time, the newest EKF
stamp received:

* every 1/``rate_hz`` s: the newest state of every link is time-aligned
  (:func:`companion.corrections.align_states`), the semi-distributed constraint application runs,
  and each link gets its correction (SKELETON_CORRECTION; in ``standard`` mode an external-vision
  ODOMETRY with the corrected pose);
* every 1/``target_rate_hz`` s: pose targets (SET_POSITION_TARGET_LOCAL_NED + SET_ATTITUDE_TARGET)
  from the configured source;
* on each link's first heartbeat: SET_MESSAGE_INTERVAL for the state message it reads
  (SKELETON_LINK_STATE, or ODOMETRY in ``standard`` mode) at ``state_rate_hz``, retried each
  second until acknowledged;
* once every link reports a usable EKF: ARM (COMMAND_LONG, retried until acknowledged) if enabled;
* every ``health_period_s`` of wall time: a health table (per-link state rate, age, dropped
  frames, correction latency) in the log.

Bad input never stops the daemon: unparseable bytes and unknown ids are counted by the ports,
states that fail validation (non-finite, non-unit quaternion, covariance not positive definite)
are counted per link and dropped.

Time base (``companion.time_base``): ``flight_controller`` takes every link's EKF stamps as one
clock (SITL: every simulated Pixhawk keeps simulation time). ``gps`` is for real Pixhawks, whose
clocks count from their own boot: each link's SYSTEM_TIME (PX4 sends it at 1 Hz; ``time_unix_usec``
is GPS time once it has a fix) gives the offset from its boot clock to GPS time (the median of its
last 5 reports, so crystal drift is followed), every stamp is moved onto GPS time on arrival and
back onto the link's own clock in what is sent to it; a link is not used until its offset is known.
GPS time is also what lets the group companions of a distributed chain agree on their cycles.

Distributed mode (``companion.distributed``, one daemon per group, ``group`` given): the daemon
serves its group's links only. Its step is the local half (:func:`companion.corrections.local_step`
at the cycle time, a multiple of the step period on flight-controller time, so every group's
boundary describes the same instant); the boundary goes out over Zenoh
(:class:`companion.fleetnet.bus.FleetBus`), and the corrections go to the links when the
leader's shift arrives or its deadline passes (:class:`companion.fleetnet.leader.GlobalStepNode`
decides; this module only carries out its actions). Malformed Zenoh payloads are counted per
key and logged. In this mode the target trajectory runs on flight-controller time from 0 (SITL:
simulation time) around ``start_center`` (default ``[start] center_w_m``), identical in every group.

CPG motion (``trajectory.kind = "cpg"``, thesis ch. 4-5) in distributed mode: the leader generates
every link's target and publishes them over Zenoh (:class:`~companion.messages.ChainTargets`, at
the target rate); every other group forwards its links' share as they arrive. Each companion also
steps its own copy of the generator on the same grid (the schedule is in the config and the
generator is deterministic), so that a group that takes over the leadership continues the motion
where it was; while no targets arrive from a leader (start-up, a failover), a group sends its own.
"""

from __future__ import annotations

import json
import logging
import math
import signal
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .corrections import compute_corrections, finish_step, local_step
from .estimation.chain import CON_DIM, CON_POS, CON_VEL
from .estimation.constraints import constraint_residual
from .estimation.so3 import quat_to_rotmat
from .fleetnet.bus import FleetBus
from .fleetnet.group import GroupLink
from .fleetnet.leader import GlobalStepNode, Resolution
from .mavlink.codec import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, decode_link_state, encode_correction, usec
from .mavlink.dialect import load_dialect
from .mavlink.frames import enu_ned, error_cov_enu_ned, flu_frd, quat_enu_flu_to_ned_frd, quat_ned_frd_to_enu_flu
from .mavlink.port import MavlinkPort, TlogWriter, wait_readable
from .messages import ChainTargets, LinkState, MessageError, check_pd

# The target source and the configuration schema are shared with the SITL (pure modules, no simulator).
from link_firmware_sim.control import PoseTarget
from sitl.trajectory import make_trajectory

__all__ = ["CompanionDaemon", "COMPANION_SYSTEM_ID", "odometry_to_link_state"]

log = logging.getLogger(__name__)
D = load_dialect()

COMPANION_SYSTEM_ID = 190
COMPANION_COMPONENT_ID = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
#: A link whose newest state is this far behind the newest of the chain is not waited for.
LAG_LIMIT_US = 100_000
#: Beyond this spread of the links' newest stamps no step runs: the time alignment would
#: extrapolate a state over it (a link that stopped streaming, or flight-controller clocks that
#: do not share a time base, e.g. Pixhawks booted at different times).
SPREAD_LIMIT_US = 500_000
_ACCEPT = frozenset({"HEARTBEAT", "SKELETON_LINK_STATE", "ODOMETRY", "COMMAND_ACK", "STATUSTEXT", "SYSTEM_TIME"})
#: SYSTEM_TIME reports whose median is a link's boot-to-GPS clock offset.
CLOCK_SAMPLES = 5
_UPPER_6 = np.triu_indices(6)


def odometry_to_link_state(msg, link: int) -> LinkState:
    """Standard-messages mode: a stock autopilot's ODOMETRY as a :class:`LinkState`.

    The 9x9 covariance is assembled from ODOMETRY's pose covariance (position and attitude, the
    attitude block read as a world small-angle covariance) and its body-frame velocity
    covariance rotated to the local frame; the position-velocity cross terms are not carried by
    ODOMETRY and are zero.
    """
    if msg.frame_id != D.MAV_FRAME_LOCAL_NED:
        raise MessageError(f"ODOMETRY.frame_id: {msg.frame_id} (expected MAV_FRAME_LOCAL_NED)")
    values = [msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz, *msg.q, msg.rollspeed, msg.pitchspeed, msg.yawspeed]
    if not all(math.isfinite(v) for v in values):
        raise MessageError("ODOMETRY: non-finite value")
    q = np.asarray(msg.q, dtype=float)
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise MessageError("ODOMETRY.q: not a unit quaternion")
    pose = np.zeros((6, 6))
    vel = np.zeros((6, 6))
    pose[_UPPER_6] = msg.pose_covariance
    vel[_UPPER_6] = msg.velocity_covariance
    pose = pose + np.triu(pose, 1).T
    vel = vel + np.triu(vel, 1).T
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(vel))):
        raise MessageError("ODOMETRY: covariance unknown (NaN)")
    R = quat_to_rotmat(q)
    P = np.zeros((9, 9))
    idx = [0, 1, 2, 6, 7, 8]
    P[np.ix_(idx, idx)] = pose
    P[3:6, 3:6] = R @ vel[:3, :3] @ R.T
    P = check_pd("ODOMETRY covariance", error_cov_enu_ned(P))
    v_ned = R @ np.array([msg.vx, msg.vy, msg.vz])
    return LinkState(link, msg.time_usec * 1e-6, enu_ned([msg.x, msg.y, msg.z]), enu_ned(v_ned),
                     quat_ned_frd_to_enu_flu(q / np.linalg.norm(q)),
                     flu_frd([msg.rollspeed, msg.pitchspeed, msg.yawspeed]), P)


@dataclass
class _Link:
    index: int
    system_id: int
    port: MavlinkPort
    state: LinkState | None = None
    flags: int = 0
    rejected: int = 0
    states: int = 0
    states_at_report: int = 0
    last_state_wall: float = 0.0
    arm_sent_wall: float = -1e9
    armed_ack: bool = False
    stream_sent_wall: float = -1e9
    stream_acked: bool = False
    correction_seq: int = -1
    latencies_ms: list = field(default_factory=list)
    latency_window_ms: list = field(default_factory=list)
    clock_samples_us: list = field(default_factory=list)
    gps_wait_logged: bool = False
    #: the link's clock + offset = the daemon's time base (0 with ``time_base = "flight_controller"``)
    offset_us: int | None = None

    def to_link_clock_us(self, t_us: int) -> int:
        return t_us - (self.offset_us or 0)


class CompanionDaemon:
    """See the module docstring. ``scenario`` is a :class:`sitl.scenario.Scenario` (one schema
    for SITL and hardware); ``start_center`` anchors the trajectory (default: the chain's
    estimated middle when the links first report). ``group`` (0-based) selects distributed
    mode's group; ``bus`` replaces the Zenoh session it would open (tests)."""

    def __init__(self, scenario, out_dir: Path | None = None, start_center=None, group: int | None = None,
                 bus=None, config_file: str = "<config>"):
        self.sc = scenario
        cfg = scenario.companion
        self.cfg = cfg
        n = scenario.skeleton.n_links
        self.n = n
        self.groups = cfg.group_layout(n)
        if cfg.distributed and group is None:
            raise ValueError(f"companion.distributed: give the group this companion serves (--group 1..{len(self.groups)})")
        if group is not None and not cfg.distributed:
            raise ValueError("--group: only for distributed companions (companion.distributed = true)")
        if group is not None and not 0 <= group < len(self.groups):
            raise ValueError(f"--group {group + 1}: the config has groups 1..{len(self.groups)}")
        self.group = group
        members = self.groups[group] if group is not None else tuple(range(n))
        self.d = scenario.skeleton.d_b_m[list(members)]
        self.params = cfg.params
        self.out_dir = out_dir
        tlog = TlogWriter(out_dir / "companion.tlog") if out_dir is not None else None
        endpoints = cfg.endpoints(n)
        self.links = [
            _Link(i, endpoints[i].system_id, MavlinkPort(endpoints[i].url, COMPANION_SYSTEM_ID, COMPANION_COMPONENT_ID,
                                                         _ACCEPT, tlog, peer_system_id=endpoints[i].system_id))
            for i in members
        ]
        self.net: GroupLink | None = None
        self._local: dict[int, tuple] = {}  # cycle -> (states, LocalStep) awaiting the shift
        if group is not None:
            zc = scenario.zenoh
            node = GlobalStepNode(group, len(self.groups), zc.order(len(self.groups)), int(round(1e6 / cfg.rate_hz)),
                                  shift_deadline_s=zc.shift_deadline_ms * 1e-3, leader_wait_s=zc.leader_wait_ms * 1e-3,
                                  handover_cycles=zc.handover_cycles)
            try:
                bus = bus if bus is not None else FleetBus(zc, scenario.zenoh_prefix, group, len(self.groups), config_file)
            except Exception:
                for lk in self.links:
                    lk.port.close()
                raise
            self.net = GroupLink(node, bus)
            if start_center is None:
                start_center = scenario.start.center_w_m
        self._by_sysid = {lk.system_id: lk for lk in self.links}
        self.period_us = int(round(1e6 / cfg.rate_hz))
        self.target_period_us = int(round(1e6 / cfg.target_rate_hz))
        self.fc_time_us = 0
        self.next_step_us: int | None = None
        self.next_target_us: int | None = None
        self.seq = 0
        self.trajectory = None
        self._trajectory_t0_us = 0
        #: CPG targets travel over Zenoh from the leader (distributed mode)
        self._zenoh_targets = self.net is not None and scenario.trajectory.kind == "cpg"
        self.target_counts = {"published": 0, "forwarded": 0, "own": 0, "received": 0, "stale": 0}
        self._leader_targets_wall = -1e9
        self._forwarded_time_us = -1
        self._start_center = None if start_center is None else np.asarray(start_center, dtype=float)
        self._next_health_wall = time.monotonic() + cfg.health_period_s
        self._next_heartbeat_wall = 0.0
        self._rows: dict[str, list] = {k: [] for k in (
            "t_sckf", "con_pos_before", "con_vel_before", "con_pos_after", "con_vel_after", "p_ekf_sckf",
            "p_corr_sckf", "iterations", "cycle_us", "v_ekf_sckf", "q_ekf_sckf", "w_sckf", "p_local_sckf",
            "v_corr_sckf", "q_corr_sckf", "global_applied", "leader")}
        self.step_times_ms: list[float] = []
        self.withheld = 0
        self._withheld_logged_wall = -1e9
        self._stop = False

    # -- input ---------------------------------------------------------------------------------------
    def _on_message(self, link: _Link, msg) -> None:
        kind = msg.get_type()
        if msg.get_srcSystem() != link.system_id:
            link.port.stats.ignored += 1
            return
        if kind == "HEARTBEAT":
            self._request_stream(link)
            return
        if kind == "COMMAND_ACK":
            if msg.command == D.MAV_CMD_COMPONENT_ARM_DISARM and msg.result == D.MAV_RESULT_ACCEPTED:
                link.armed_ack = True
            elif msg.command == D.MAV_CMD_SET_MESSAGE_INTERVAL and not link.stream_acked:
                link.stream_acked = True
                if msg.result != D.MAV_RESULT_ACCEPTED:
                    log.warning("link %d refused the state stream rate (MAV_RESULT %d): using its own rate",
                                link.index + 1, msg.result)
            return
        if kind == "STATUSTEXT":
            log.info("link %d: %s", link.index + 1, msg.text)
            return
        if kind == "SYSTEM_TIME":
            self._on_system_time(link, msg)
            return
        try:
            if kind == "SKELETON_LINK_STATE" and self.cfg.mode == "dialect":
                state = decode_link_state(msg, link.index)
                link.flags = msg.flags
                if msg.correction_seq != link.correction_seq and msg.correction_seq > 0:
                    link.correction_seq = msg.correction_seq
                    link.latencies_ms.append(msg.correction_latency_us * 1e-3)
                    link.latency_window_ms.append(msg.correction_latency_us * 1e-3)
            elif kind == "ODOMETRY" and self.cfg.mode == "standard":
                state = odometry_to_link_state(msg, link.index)
                link.flags = STATE_FLAG_EKF_OK
            else:
                link.port.stats.ignored += 1
                return
        except MessageError as exc:
            link.rejected += 1
            log.warning("link %d: rejected %s: %s", link.index + 1, kind, exc)
            return
        if self.cfg.time_base == "gps":
            if link.offset_us is None:
                link.port.stats.ignored += 1  # no GPS time from this link yet
                return
            state = replace(state, time_s=(usec(state.time_s) + link.offset_us) * 1e-6)
        link.state = state
        link.states += 1
        link.last_state_wall = time.monotonic()
        self.fc_time_us = max(self.fc_time_us, usec(state.time_s))

    def _on_system_time(self, link: _Link, msg) -> None:
        """``gps`` time base: the link's boot-to-GPS offset from SYSTEM_TIME."""
        if self.cfg.time_base != "gps":
            return
        if msg.time_unix_usec <= 0:
            if link.offset_us is None and not link.gps_wait_logged:
                log.info("link %d: no GPS time yet (SYSTEM_TIME.time_unix_usec = 0): waiting", link.index + 1)
                link.gps_wait_logged = True
            return
        link.clock_samples_us = (link.clock_samples_us + [int(msg.time_unix_usec) - int(msg.time_boot_ms) * 1000])[
            -CLOCK_SAMPLES:]
        first = link.offset_us is None
        link.offset_us = int(np.median(link.clock_samples_us))
        if first:
            log.info("link %d: boot clock + %.3f s = GPS time", link.index + 1, link.offset_us * 1e-6)

    # -- the 20 Hz step ---------------------------------------------------------------------------------
    def _all_states(self) -> bool:
        return all(lk.state is not None for lk in self.links)

    def _step(self) -> None:
        if self.net is not None:
            self._local_half()
            return
        states = [lk.state for lk in self.links]
        t0 = time.perf_counter()
        try:
            result, corrections = compute_corrections(states, self.d, self.groups, self.params, self.seq)
        except (ValueError, np.linalg.LinAlgError) as exc:
            log.warning("constraint application failed at t = %.3f s: %s", self.fc_time_us * 1e-6, exc)
            return
        self.step_times_ms.append((time.perf_counter() - t0) * 1e3)
        self.seq = (self.seq + 1) & 0xFFFF or 1
        self._send_corrections(corrections, (result.p, result.v, result.q, result.P))
        self._record(states, result)

    def _withhold(self, newest: list[int]) -> None:
        """No step: the links' stamps are too far apart to be aligned (logged every 5 s)."""
        self.withheld += 1
        now = time.monotonic()
        if now - self._withheld_logged_wall >= 5.0:
            self._withheld_logged_wall = now
            lag = self.links[int(np.argmin(newest))]
            log.error("link %d's newest state is %.3f s behind the newest of the chain: it stopped streaming, or the "
                      "flight controllers' clocks do not share a time base; no corrections until they agree "
                      "(%d cycles so far)", lag.index + 1, (max(newest) - min(newest)) * 1e-6, self.withheld)

    def _local_half(self) -> None:
        """Distributed mode: local constraint application at the cycle time, boundary out."""
        states = [lk.state for lk in self.links]
        cycle = self.next_step_us
        t0 = time.perf_counter()
        try:
            step = local_step(states, self.d, self.params, t=cycle * 1e-6)
        except (ValueError, np.linalg.LinAlgError) as exc:
            log.warning("local constraint application failed at t = %.3f s: %s", cycle * 1e-6, exc)
            return
        self.step_times_ms.append((time.perf_counter() - t0) * 1e3)
        self._local[cycle] = (states, step)
        b = step.boundary
        self._finish(self.net.local_step(b.left_tip, b.right_tip, b.info_pv, cycle, time.monotonic()))

    def _finish(self, resolved: list[Resolution]) -> None:
        """Corrections for the cycles that ended (with the leader's shift, or local-only)."""
        for res in resolved:
            entry = self._local.pop(res.cycle_us, None)
            for old in [c for c in self._local if c < res.cycle_us]:
                del self._local[old]
            if entry is None:
                continue
            states, step = entry
            if res.shift is None and res.reason:
                log.debug("cycle t = %.3f s: local-only corrections (%s)", res.cycle_us * 1e-6, res.reason)
            p, v, q, corrections = finish_step(states, step, res.shift, self.seq)
            self.seq = (self.seq + 1) & 0xFFFF or 1
            self._send_corrections(corrections, (p, v, q, step.result.P))
            r = self._rows
            r["t_sckf"].append(res.cycle_us * 1e-6)
            r["cycle_us"].append(res.cycle_us)
            r["p_ekf_sckf"].append(step.p)
            r["v_ekf_sckf"].append(step.v)
            r["q_ekf_sckf"].append(step.q)
            r["w_sckf"].append(step.w)
            r["p_local_sckf"].append(step.result.p)
            r["p_corr_sckf"].append(p)
            r["v_corr_sckf"].append(v)
            r["q_corr_sckf"].append(q)
            r["global_applied"].append(res.shift is not None)
            r["leader"].append(-1 if res.leader_group is None else res.leader_group + 1)
            r["iterations"].append(int(step.result.iterations))

    def _send_corrections(self, corrections, result) -> None:
        """Each link its correction (dialect) or its corrected pose (standard mode), stamped on the
        link's own clock; ``result`` is ``(p, v, q, P)`` of the daemon's links, in their order."""
        for row, (lk, corr) in enumerate(zip(self.links, corrections)):
            if self.cfg.mode == "dialect":
                own = replace(corr, ekf_time_s=lk.to_link_clock_us(usec(corr.ekf_time_s)) * 1e-6)
                lk.port.send(encode_correction(own, lk.system_id, 1))
            else:
                lk.port.send(self._vision_odometry(lk, result, row))

    def _vision_odometry(self, lk: _Link, result, i: int):
        """Standard mode: the corrected pose as external vision (ODOMETRY, MAV_FRAME_LOCAL_FRD);
        ``result`` is ``(p, v, q, P)`` of the daemon's links, ``i`` the row of this link."""
        p_all, v_all, q_all, P_all = result
        q = quat_enu_flu_to_ned_frd(q_all[i])
        R = quat_to_rotmat(q)
        v_body = R.T @ enu_ned(v_all[i])
        P = P_all[i]
        cov = np.full(21, 0.0)
        idx = [0, 1, 2, 6, 7, 8]
        cov[:] = error_cov_enu_ned(P)[np.ix_(idx, idx)][_UPPER_6]
        vcov = np.zeros((6, 6))
        vcov[:3, :3] = R.T @ error_cov_enu_ned(P)[3:6, 3:6] @ R
        vcov[3:, 3:] = np.eye(3) * 1e-4
        return D.MAVLink_odometry_message(
            lk.to_link_clock_us(usec(lk.state.time_s)), D.MAV_FRAME_LOCAL_FRD, D.MAV_FRAME_BODY_FRD,
            *enu_ned(p_all[i]).tolist(),
            q.tolist(), *v_body.tolist(), math.nan, math.nan, math.nan, cov.tolist(), vcov[_UPPER_6].tolist(),
            0, D.MAV_ESTIMATOR_TYPE_VISION, 100,
        )

    def _record(self, states, result) -> None:
        p = np.stack([s.p_w_m for s in states])
        v = np.stack([s.v_w_m_s for s in states])
        q = np.stack([s.q_wxyz for s in states])
        w = np.stack([s.omega_b_rad_s for s in states])
        r = self._rows
        r["t_sckf"].append(self.fc_time_us * 1e-6)
        r["p_ekf_sckf"].append(p)
        r["p_corr_sckf"].append(result.p)
        r["iterations"].append(int(result.iterations.max()))
        if self.n > 1:
            for tag, (pp, vv, qq) in (("before", (p, v, q)), ("after", (result.p, result.v, result.q))):
                c = constraint_residual(pp, vv, qq, w, self.d).reshape(-1, CON_DIM)
                r[f"con_pos_{tag}"].append(np.linalg.norm(c[:, CON_POS], axis=1))
                r[f"con_vel_{tag}"].append(np.linalg.norm(c[:, CON_VEL], axis=1))

    # -- targets and arming --------------------------------------------------------------------------------
    def _send_targets(self) -> None:
        if self.trajectory is None:
            center = self._start_center
            if center is None:
                p = np.stack([lk.state.p_w_m for lk in self.links])
                mid = self.n // 2
                center = p[mid] if self.n % 2 else 0.5 * (p[mid - 1] + p[mid])
            self.trajectory = make_trajectory(self.sc.trajectory, self.sc.motion, self.n, self.sc.skeleton.link_length_m,
                                              center)
            # distributed in SITL: every group on the same clock from 0 (simulation time)
            shared = self.net is not None and self.cfg.time_base == "flight_controller"
            self._trajectory_t0_us = 0 if shared else self.fc_time_us
        # Trajectory time starts when every link has first reported (on hardware the flight
        # controllers have been up for a while; in SITL this is within a tick of t = 0).
        t_traj = (self.fc_time_us - self._trajectory_t0_us) * 1e-6
        targets = self.trajectory.targets(t_traj)
        if self._zenoh_targets:
            now = time.monotonic()
            if self.net.leads(self.next_step_us, now):
                self.net.publish_targets(ChainTargets(
                    self.group, self.fc_time_us, self.target_counts["published"] & 0xFFFFFFFF, tuple(range(self.n)),
                    np.stack([x.p_w_m for x in targets]), np.stack([x.q_wxyz for x in targets]),
                    np.stack([x.v_w_m_s for x in targets]), np.stack([x.a_w_m_s2 for x in targets]),
                    np.stack([x.omega_d_rad_s for x in targets]), np.stack([x.omega_dot_d_rad_s2 for x in targets])))
                self.target_counts["published"] += 1
            elif now - self._leader_targets_wall < 3e-6 * self.target_period_us:
                return  # the leader's targets are being forwarded (:meth:`_forward_targets`)
            self.target_counts["own"] += 1
        for lk in self.links:
            self._send_target(lk, self.fc_time_us, targets[lk.index])

    def _forward_targets(self, msg: ChainTargets) -> None:
        """Send this group's links their share of the leader's CPG targets."""
        self.target_counts["received"] += 1
        if msg.time_us <= self._forwarded_time_us:
            self.target_counts["stale"] += 1  # out of order, or a second leader during a hand-over
            return
        self._forwarded_time_us = msg.time_us
        self._leader_targets_wall = time.monotonic()
        rows = {link: k for k, link in enumerate(msg.links)}
        for lk in self.links:
            k = rows.get(lk.index)
            if k is not None:
                self._send_target(lk, msg.time_us, PoseTarget(msg.p_w_m[k], msg.q_wxyz[k], msg.v_w_m_s[k], msg.a_w_m_s2[k],
                                                              msg.omega_b_rad_s[k], msg.omega_dot_b_rad_s2[k]))
        self.target_counts["forwarded"] += 1

    def _send_target(self, lk: _Link, time_us: int, target: PoseTarget) -> None:
        """SET_POSITION_TARGET_LOCAL_NED + SET_ATTITUDE_TARGET (NED/FRD: converted here)."""
        boot_ms = (lk.to_link_clock_us(time_us) // 1000) & 0xFFFFFFFF
        p, v, a = enu_ned(target.p_w_m), enu_ned(target.v_w_m_s), enu_ned(target.a_w_m_s2)
        lk.port.send(D.MAVLink_set_position_target_local_ned_message(
            boot_ms, lk.system_id, 1, D.MAV_FRAME_LOCAL_NED, 0b0000_1100_0000_0000, *p.tolist(), *v.tolist(),
            *a.tolist(), 0.0, 0.0))
        rates = flu_frd(target.omega_d_rad_s).tolist()
        lk.port.send(D.MAVLink_set_attitude_target_message(
            time_boot_ms=boot_ms, target_system=lk.system_id, target_component=1, type_mask=0,
            q=quat_enu_flu_to_ned_frd(target.q_wxyz).tolist(), body_roll_rate=rates[0],
            body_pitch_rate=rates[1], body_yaw_rate=rates[2], thrust=0.0))

    def _request_stream(self, lk: _Link) -> None:
        now = time.monotonic()
        if lk.stream_acked or now - lk.stream_sent_wall < 1.0:
            return
        mid = D.MAVLINK_MSG_ID_SKELETON_LINK_STATE if self.cfg.mode == "dialect" else D.MAVLINK_MSG_ID_ODOMETRY
        lk.port.send(D.MAVLink_command_long_message(lk.system_id, 1, D.MAV_CMD_SET_MESSAGE_INTERVAL, 0, mid,
                                                    1e6 / self.cfg.state_rate_hz, 0, 0, 0, 0, 0))
        lk.stream_sent_wall = now

    def _arm(self) -> None:
        if not self.cfg.arm or not self._all_states():
            return
        now = time.monotonic()
        for lk in self.links:
            if lk.flags & STATE_FLAG_ARMED or not lk.flags & STATE_FLAG_EKF_OK or now - lk.arm_sent_wall < 1.0:
                continue
            lk.port.send(D.MAVLink_command_long_message(lk.system_id, 1, D.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                                        1, 0, 0, 0, 0, 0, 0))
            lk.arm_sent_wall = now

    # -- health -------------------------------------------------------------------------------------------
    def health_table(self, period_s: float) -> str:
        rows = [f"{'link':>4} {'sysid':>5} {'port':>4} {'state Hz':>8} {'age ms':>7} {'dropped':>7} {'rejected':>8} "
                f"{'lat p50 ms':>10} {'lat p99 ms':>10}"]
        now = time.monotonic()
        for lk in self.links:
            rate = (lk.states - lk.states_at_report) / period_s
            lk.states_at_report = lk.states
            age = (now - lk.last_state_wall) * 1e3 if lk.last_state_wall else float("nan")
            lat = np.asarray(lk.latency_window_ms)
            lk.latency_window_ms = []
            p50 = f"{np.percentile(lat, 50):10.1f}" if lat.size else f"{'-':>10}"
            p99 = f"{np.percentile(lat, 99):10.1f}" if lat.size else f"{'-':>10}"
            up = "up" if lk.port.transport.connected else "down"
            rows.append(f"{lk.index + 1:>4} {lk.system_id:>5} {up:>4} {rate:8.1f} {age:7.0f} {lk.port.stats.dropped:7d} "
                        f"{lk.rejected:8d} {p50} {p99}")
        return "\n".join(rows)

    # -- main loop ---------------------------------------------------------------------------------------
    def poll(self, timeout_s: float) -> None:
        waitables = [lk.port for lk in self.links]
        if self.net is not None:
            waitables.append(self.net)
            due = self.net.next_deadline_s()
            if due is not None:
                timeout_s = min(timeout_s, max(due - time.monotonic(), 0.0))
        ready = wait_readable(waitables, timeout_s)
        for lk in self.links:
            if lk.port in ready:
                for msg in lk.port.read():
                    self._on_message(lk, msg)
        if self.net is not None:
            self._finish(self.net.pump(time.monotonic()))
            for msg in self.net.take_targets():
                if self._zenoh_targets:
                    self._forward_targets(msg)
        self._wall_clock_duties()
        if not self._all_states():
            return
        t = self.fc_time_us
        if self.next_step_us is None:
            # steps on the period grid of flight-controller time: the groups' cycles coincide
            self.next_step_us = -(-t // self.period_us) * self.period_us
            self.next_target_us = t
        if self.cfg.targets == "trajectory" and t >= self.next_target_us:
            self._send_targets()
            self.next_target_us += self.target_period_us * max(1, (t - self.next_target_us) // self.target_period_us + 1)
        if self.sc.companion.enabled and t >= self.next_step_us:
            newest = [usec(lk.state.time_s) for lk in self.links]
            # Step once every link has reported for this step time (a coherent snapshot); a link
            # lagging more than LAG_LIMIT behind the others is not waited for (its state is
            # propagated by the time alignment), so one silent link degrades the step, never stalls it.
            spread = max(newest) - min(newest)
            if spread > SPREAD_LIMIT_US:
                self._withhold(newest)
                self.next_step_us += self.period_us * max(1, (t - self.next_step_us) // self.period_us + 1)
            elif min(newest) >= self.next_step_us or spread > LAG_LIMIT_US:
                self._step()
                self.next_step_us += self.period_us * max(1, (t - self.next_step_us) // self.period_us + 1)
        self._arm()

    def _wall_clock_duties(self) -> None:
        """1 Hz heartbeat on every link (a MAVLink component) and the periodic health table."""
        now = time.monotonic()
        if now >= self._next_heartbeat_wall:
            for lk in self.links:
                lk.port.send(D.MAVLink_heartbeat_message(D.MAV_TYPE_ONBOARD_CONTROLLER, D.MAV_AUTOPILOT_INVALID,
                                                         0, 0, D.MAV_STATE_ACTIVE, 3))
            self._next_heartbeat_wall = now + 1.0
        if now >= self._next_health_wall:
            log.info("health (last %.0f s):\n%s", self.cfg.health_period_s, self.health_table(self.cfg.health_period_s))
            if self.net is not None:
                log.info("%s", self.net.status_line())
            self.write_log()
            self._next_health_wall = now + self.cfg.health_period_s

    def stop(self, *_args) -> None:
        self._stop = True

    def run(self, duration_s: float | None = None) -> None:
        signal.signal(signal.SIGTERM, self.stop)
        signal.signal(signal.SIGINT, self.stop)
        end = None if duration_s is None else time.monotonic() + duration_s
        log.info("companion up: %d link(s) %s, mode %s, SCKF %.0f Hz, groups %s%s", len(self.links),
                 ", ".join(lk.port.url for lk in self.links), self.cfg.mode, self.cfg.rate_hz, self.groups,
                 f", serving group {self.group + 1} (Zenoh prefix {self.sc.zenoh_prefix!r})" if self.net else "")
        try:
            while not self._stop and (end is None or time.monotonic() < end):
                self.poll(0.05)
        finally:
            self.close()

    def summary(self) -> dict:
        lat = np.concatenate([np.asarray(lk.latencies_ms) for lk in self.links]) if self.links else np.zeros(0)
        steps = np.asarray(self.step_times_ms)
        return {
            "steps": int(steps.size),
            "withheld_steps": self.withheld,
            "step_ms": {"p50": float(np.percentile(steps, 50)), "p99": float(np.percentile(steps, 99))} if steps.size else None,
            "correction_latency_ms": {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)),
                                      "samples": int(lat.size)} if lat.size else None,
            "links": {str(lk.system_id): {"states": lk.states, "rejected": lk.rejected, **vars(lk.port.stats)}
                      for lk in self.links},
            **(self.net.summary() if self.net is not None else {}),
            **({"cpg_targets": dict(self.target_counts)} if self._zenoh_targets else {}),
        }

    def write_log(self) -> None:
        """The step log so far (``companion_log.npz``, rewritten whole: it survives a crash up to
        the last checkpoint)."""
        if self.out_dir is None:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        tmp = self.out_dir / "companion_log.tmp.npz"
        np.savez(tmp, **{k: np.asarray(v) for k, v in self._rows.items() if v})
        tmp.replace(self.out_dir / "companion_log.npz")

    def close(self) -> None:
        summary = self.summary()
        log.info("companion summary: %s", json.dumps({k: summary[k] for k in (
            "steps", "step_ms", "correction_latency_ms", "global_step", "round_trip_ms_as_leader", "failovers")
            if k in summary}))
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self.write_log()
            (self.out_dir / "companion_summary.json").write_text(json.dumps(summary, indent=1, default=str))
        for lk in self.links:
            lk.port.close()
        if self.net is not None:
            self.net.close()

"""The companion engine: everything the companion decides, with no sockets, clocks or threads.

:class:`CompanionEngine` is what the daemon (:mod:`companion.daemon`) and the SITL batch runner
both run. Typed inputs go in, each with the time it happened on the caller's monotonic clock
(``now_s``: wall time in the daemon, simulation time in batch mode):

* :meth:`~CompanionEngine.on_state`: a link's :class:`~companion.messages.LinkState` (decoded by the
  caller from SKELETON_LINK_STATE, or ODOMETRY in ``standard`` mode) with its flags and the
  correction it reports applied;
* :meth:`~CompanionEngine.on_heartbeat`, :meth:`~CompanionEngine.on_command_ack`,
  :meth:`~CompanionEngine.on_system_time`, :meth:`~CompanionEngine.on_rejected`;
* :meth:`~CompanionEngine.poll` runs what is due and returns the outputs, in order:
  :class:`CorrectionOut`, :class:`TargetOut`, :class:`CommandOut` (arm, stream rate),
  :class:`Heartbeat` and :class:`HealthDue`, each for the caller to carry out (encode and send, or
  hand to an in-process firmware).

What it decides, on the links' flight-controller time (the newest plausible EKF stamp received):

* plausibility before use: a state whose stamp is not newer than the link's last (a replay) or
  further ahead than the link's clock can have run (:mod:`companion.plausibility`) is rejected
  and counted, and never moves the cycle clock; a link silent for a while that comes back on a
  new clock has rebooted; a link back from a silence (or a reboot) is re-admitted after
  :data:`READMIT_CYCLES` usable cycles;
* every 1/``rate_hz``: once every link has reported for the step time (or a link lags more
  than :data:`LAG_LIMIT_US`), the links that may be used (newest state within
  :data:`LAG_LIMIT_US` of the step time, EKF usable, not being re-admitted) are time-aligned
  (:func:`companion.corrections.align_states`) and checked against each other by the joint
  chi-square gate (:mod:`companion.estimation.gate`), which cuts inconsistent joints and leaves
  an outlier link out. The chain splits where links are left out or joints cut; every segment
  of two or more links gets its constraint application (Alg. 1, or Alg. 2 + eq. 6 with several
  groups) and its links their corrections; a link left out gets none that cycle and flies on
  its own EKF. Why each link is out is counted (:data:`EXCLUSION_REASONS`, the health table,
  :meth:`CompanionEngine.summary`) and logged per step (``corrected_sckf``). A link that flags
  a GPS fault (``STATE_FLAG_GPS_FAULT``: its EKF rejects its fixes, or they stopped) and that
  the gate finds at odds with its neighbours is not left out but takes part one way: its
  position variance is raised by :data:`GPS_FAULT_POS_VAR_M2`, so the step puts it where its
  neighbours say it is and leaves them unmoved (``gps_fault_steps``; while it agrees with them
  it takes part as usual, its dead-reckoned position still informative). With
  ``enabled = false`` the step only logs the links' EKF states;
* every 1/``target_rate_hz``: every link's pose target from the trajectory (``[trajectory]``),
  anchored at ``trajectory.anchor_w_m`` or where the chain is when every link first reports;
  with the whole-chain feed-forward (``trajectory.feedforward``), a link whose rotors are taken
  to be off (it has flown, and is now silent ``carry_silence_s``, disarmed, or re-armed less than
  ``carry_spinup_s`` ago) is carried: its neighbours' feed-forward takes its weight
  (:meth:`_passive_links`; ``carried_s`` in the summary); in distributed mode with the other
  groups' carried links too, which each group publishes (:class:`~.messages.GroupPassiveLinks`,
  :meth:`_publish_passive`): a dead link at a group's end hangs on a link of the next group;
* arming (``arm = true``) once every link reports a usable EKF, until it reports armed: retried
  every :data:`ARM_RETRY_S` for the first :data:`ARM_FAST_TRIES` commands, then each second (a
  link rebooted in flight has its rotors off until armed: one lost command must not cost a
  second; a link that keeps refusing is not flooded);
* the state stream (SET_MESSAGE_INTERVAL) on a link's heartbeat, retried each second until
  acknowledged; a 1 Hz heartbeat; the health report every ``health_period_s``.

Time base ``gps`` (real Pixhawks count from their own boot): each link's SYSTEM_TIME gives the
offset of its boot clock to GPS time (median of its last :data:`CLOCK_SAMPLES` reports, which
follows crystal drift); stamps are moved onto GPS time on arrival and back onto the link's clock
in what is sent to it; a link is not used before its offset is known.

Distributed mode (one engine per group, ``group`` given, ``net`` a
:class:`~companion.fleetnet.group.GroupLink` on whatever bus the caller passes: Zenoh in the
daemon, an in-process hub in batch mode): the step is the group's local half at the cycle time
(a multiple of the step period, the same instant in every group); the boundary goes to the
leader and the corrections go out when the leader's shift arrives or its deadline passes. With
``trajectory.kind = "cpg"`` the leader publishes every link's targets and the others forward
their links' share; each engine also steps its own copy of the generator so that a new leader
continues the motion, and sends its own targets while no leader's arrive.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from enum import Enum
from statistics import median

import numpy as np

from .config import CompanionSetup
from .corrections import align_states, compute_corrections, finish_step, local_step
from .estimation.chain import ERR_P
from .estimation.gate import gate_chain, segments
from .messages import (STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, STATE_FLAG_GPS_FAULT, ChainTargets, Correction,
                       GroupPassiveLinks, LinkState, PoseTarget)
from .plausibility import StampGate, StampVerdict
from .skeleton.kinematics import chain_middle
from .trajectory import chain_model, make_trajectory

__all__ = [
    "LAG_LIMIT_US",
    "EXCLUSION_REASONS",
    "READMIT_CYCLES",
    "CLOCK_SAMPLES",
    "Command",
    "CorrectionOut",
    "TargetOut",
    "CommandOut",
    "Heartbeat",
    "HealthDue",
    "LinkTrack",
    "CompanionEngine",
    "STEP_LOG_KEYS",
]

log = logging.getLogger(__name__)

#: A link whose newest state is this far behind the newest of the chain is not waited for.
LAG_LIMIT_US = 100_000
#: Why a link took no part in a step: its newest state is more than LAG_LIMIT_US from the step
#: time (silent, or a clock that does not share the time base); its EKF is not usable; it is
#: back after a silence or a reboot and waits READMIT_CYCLES usable cycles; the joint gate found
#: it inconsistent with its neighbours (:mod:`companion.estimation.gate`); or it is usable but
#: alone in its segment.
EXCLUSION_REASONS = ("stale", "ekf", "returning", "gate", "alone")
#: Usable cycles a link back from a silence of ``reboot_silence_s`` or more (or a reboot) waits
#: before it is constrained again (its EKF may still be settling).
READMIT_CYCLES = 10
#: Position variance added to the state of a link that flags a GPS fault [m^2] ((10 m)^2): the
#: constraint application then moves that link onto its neighbours and leaves them where they
#: are (their corrections change by about their variance over this, under 1e-5), so a glitching
#: GPS is corrected by the chain instead of pulling it.
GPS_FAULT_POS_VAR_M2 = 100.0
#: SYSTEM_TIME reports whose median is a link's boot-to-GPS clock offset.
CLOCK_SAMPLES = 5
#: Retry period of unacknowledged commands, the heartbeat period [s].
RETRY_S = 1.0
#: Retry period of the first ARM commands to a disarmed link with a usable EKF [s], and how many
#: are sent that fast before :data:`RETRY_S` (MAVSDK retransmits a command after 0.5 s).
ARM_RETRY_S = 0.2
ARM_FAST_TRIES = 5
#: Accepted states in a row reporting a link disarmed before the companion takes its rotors to
#: be off (carrying, :meth:`CompanionEngine._passive_links`): 60 ms of the 50 Hz stream.
DISARMED_STATES = 3
#: Distributed mode: a group publishes its carried links (:class:`~.messages.GroupPassiveLinks`)
#: when they change and at least this often [us]; the others take a group's newest one within
#: :data:`PASSIVE_STALE_US` of their own cycle clock (and while its companion is up).
PASSIVE_REPEAT_US = 1_000_000
PASSIVE_STALE_US = 2_500_000
#: The step log, one row per step (per cycle in distributed mode), every array on the time base.
STEP_LOG_KEYS = ("t_sckf", "cycle_us", "p_ekf_sckf", "v_ekf_sckf", "q_ekf_sckf", "w_sckf", "p_local_sckf",
                 "p_corr_sckf", "v_corr_sckf", "q_corr_sckf", "iterations", "global_applied", "leader",
                 "corrected_sckf", "nis_max_sckf", "P_ekf_sckf", "P_corr_sckf")


class Command(Enum):
    """What a :class:`CommandOut` asks a link: arm, or stream its state at a rate."""

    ARM = "arm"
    STREAM = "stream"


@dataclass(frozen=True)
class CorrectionOut:
    """Send link ``row`` its correction (dialect mode) or its corrected estimate (standard mode:
    external vision). Both are stamped on the link's own clock."""

    row: int
    system_id: int
    correction: Correction
    corrected: LinkState


@dataclass(frozen=True)
class TargetOut:
    """Send link ``row`` its pose target for ``time_us`` on the link's own clock."""

    row: int
    system_id: int
    time_us: int
    target: PoseTarget


@dataclass(frozen=True)
class CommandOut:
    """Send link ``row`` a command: arm, or stream its state message every ``interval_us``."""

    row: int
    system_id: int
    command: Command
    interval_us: float = 0.0


@dataclass(frozen=True)
class Heartbeat:
    """The companion's 1 Hz heartbeat is due (on every link)."""


@dataclass(frozen=True)
class HealthDue:
    """The periodic health report is due (:meth:`CompanionEngine.health_rows` over ``period_s``)."""

    period_s: float


@dataclass
class CarryClock:
    """How long a link has been carried (its rotors taken to be off), on the time base: the
    stretches so far and the one going on."""

    total_s: float = 0.0
    since_s: float | None = None

    @property
    def on(self) -> bool:
        return self.since_s is not None

    def switch(self, on: bool, t: float) -> float | None:
        """Start or end a stretch at ``t``; the length of the one that ended (``None``: none)."""
        if on and self.since_s is None:
            self.since_s = t
        elif not on and self.since_s is not None:
            ended, self.since_s = t - self.since_s, None
            self.total_s += ended
            return ended
        return None

    def seconds(self, t: float) -> float:
        """Carried so far, a stretch still going on included (to ``t``)."""
        return self.total_s + (t - self.since_s if self.since_s is not None else 0.0)


@dataclass
class LinkTrack:
    """What the engine knows of one link (``index`` in the chain, ``row`` in this engine)."""

    index: int
    row: int
    system_id: int
    state: LinkState | None = None
    flags: int = 0
    rejected: int = 0
    states: int = 0
    states_at_report: int = 0
    last_state_s: float | None = None
    arm_sent_s: float = -np.inf
    arm_tries: int = 0  # ARM commands since the link last reported armed
    armed_ack: bool = False
    stream_sent_s: float = -np.inf
    stream_acked: bool = False
    correction_seq: int = -1
    latencies_ms: list = field(default_factory=list)
    latency_window_ms: list = field(default_factory=list)
    clock_samples_us: list = field(default_factory=list)
    gps_wait_logged: bool = False
    #: the link's clock + offset = the engine's time base (0 with ``time_base = "flight_controller"``)
    offset_us: int | None = None
    stamps: StampGate | None = None
    #: states rejected for their stamp: not newer than the last (replays), too far ahead
    replayed: int = 0
    future: int = 0
    reboots: int = 0
    gps_fault_steps: int = 0  # steps it took part in one way (its GPS flagged faulty)
    #: cycles this link took no part in, by reason (see :data:`EXCLUSION_REASONS`)
    excluded: dict = field(default_factory=dict)
    excluded_at_report: int = 0
    #: why it was left out of the last step ("" = used)
    status: str = ""
    readmit_cycles: int = 0
    #: it has been armed for ``carry_spinup_s`` (it has flown); since when it reports armed;
    #: carried: its rotors taken to be off (``carry_silence_s``, ``carry_spinup_s``)
    flown: bool = False
    armed_since_s: float | None = None
    disarmed_states: int = 0  # accepted states in a row that report it disarmed
    believed_armed: bool = False
    after_silence: bool = False
    stamp_rejected_s: float = -np.inf  # the last replayed or future state, on the time base
    carried: CarryClock = field(default_factory=CarryClock)

    def to_link_clock_us(self, t_us: int) -> int:
        return t_us - (self.offset_us or 0)


def _usec(t_s: float) -> int:
    return int(round(t_s * 1e6))


def _blocks(P: np.ndarray) -> np.ndarray:
    """(n, 3, 3, 3): the position, velocity and attitude blocks of (n, 9, 9) covariances (what
    the step log keeps of them: enough for the NEES of each, a third of the size)."""
    return np.stack([P[:, 3 * b:3 * b + 3, 3 * b:3 * b + 3] for b in range(3)], axis=1)


def _stacked(states: list[LinkState]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(p, v, q, w)`` of ``states``, stacked (n, 3 or 4)."""
    return (np.array([s.p_w_m for s in states]), np.array([s.v_w_m_s for s in states]),
            np.array([s.q_wxyz for s in states]), np.array([s.omega_b_rad_s for s in states]))


class CompanionEngine:
    """See the module docstring.

    Args:
        setup: the companion's configuration (a SITL scenario is one too).
        group: 0-based group this engine serves (distributed mode), else ``None`` (every link).
        start_center: anchor of the trajectory [m] (default ``trajectory.anchor_w_m``, else the
            chain's estimated middle when every link first reports).
        net: the distributed mode's :class:`~companion.fleetnet.group.GroupLink`.
        trajectory: a target source to use instead of the one built from the config at the first
            targets (batch mode shares one between its group engines: they would compute the same).
        timer: measures the step's compute time only (never drives a decision).
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
        self.d = setup.skeleton.d_b_m[list(members)]
        self.params = cfg.params
        c = cfg.gnss_common_pos_var_m2
        #: the GNSS error common to every link (CompanionConfig.gnss_common_pos_var_m2), or None
        self._common = np.diag([c[0], c[0], c[1]]) if c is not None and any(c) else None
        self.common_mode_kept = 0  # link-steps whose position covariance was not larger than it
        endpoints = cfg.endpoints(n)
        self.links = [LinkTrack(i, row, endpoints[i].system_id, stamps=StampGate(cfg.stamp_window))
                      for row, i in enumerate(members)]
        self._cycle_clock = StampGate(cfg.stamp_window)  # what moves fc_time_us
        self.gate_params = cfg.gate
        self.period_us = int(round(1e6 / cfg.rate_hz))
        self.target_period_us = int(round(1e6 / cfg.target_rate_hz))
        self.fc_time_us = 0
        self.next_step_us: int | None = None
        self.next_target_us: int | None = None
        self.seq = 0
        self.trajectory = trajectory
        self._trajectory_t0_us = 0
        self._trajectory_started = False
        self._start_center = None if start_center is None else np.asarray(start_center, dtype=float)
        #: CPG targets travel over the network from the leader (distributed mode)
        self._net_targets = net is not None and setup.trajectory.kind == "cpg"
        self.target_counts = {"published": 0, "forwarded": 0, "own": 0, "received": 0, "stale": 0}
        # distributed mode: the other groups' carried links (newest message per group), what this
        # group last published, and how long each other group's link has been carried here
        self._remote_passive: dict[int, GroupPassiveLinks] = {}
        self._passive_sent: tuple[tuple[int, ...], int] | None = None
        self.passive_counts = {"published": 0, "received": 0, "rejected": 0}
        self._remote_carried: dict[int, CarryClock] = {}  # another group's link -> its carrying here
        self._leader_targets_s = -np.inf
        self._forwarded_time_us = -1
        self._local: dict[int, tuple] = {}  # cycle -> (states, LocalStep, NIS, reported P) awaiting the shift
        self._next_heartbeat_s = -np.inf
        self._next_health_s: float | None = None
        self.log: dict[str, list] = {k: [] for k in STEP_LOG_KEYS}
        self.step_times_ms: list[float] = []
        self.withheld = 0  # steps in which no link could be corrected
        self.degraded = 0  # steps in which some link was left out
        self._one_way: set[int] = set()  # rows taking part one way this step (GPS fault; _plan)
        self._reject_logged_s: dict[tuple[int, str], float] = {}
        self._timer = timer
        self._out: list = []
        self._heard = True  # an input since the last poll (:meth:`needs_poll`)

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
        lk = self.links[row]
        if lk.stream_acked or now_s - lk.stream_sent_s < RETRY_S:
            return
        self._out.append(CommandOut(row, lk.system_id, Command.STREAM, 1e6 / self.cfg.state_rate_hz))
        lk.stream_sent_s = now_s

    def on_command_ack(self, row: int, command: Command, accepted: bool, result: int = 0) -> None:
        self._heard = True
        lk = self.links[row]
        if command is Command.ARM and accepted:
            lk.armed_ack = True
        elif command is Command.STREAM and not lk.stream_acked:
            lk.stream_acked = True
            if not accepted:
                log.warning("link %d refused the state stream rate (MAV_RESULT %d): using its own rate", lk.index + 1,
                            result)

    def on_system_time(self, row: int, time_unix_us: int, time_boot_ms: int) -> None:
        """``gps`` time base: the link's boot-to-GPS offset from SYSTEM_TIME."""
        self._heard = True
        if self.cfg.time_base != "gps":
            return
        lk = self.links[row]
        if time_unix_us <= 0:
            if lk.offset_us is None and not lk.gps_wait_logged:
                log.info("link %d: no GPS time yet (SYSTEM_TIME.time_unix_usec = 0): waiting", lk.index + 1)
                lk.gps_wait_logged = True
            return
        sample = int(time_unix_us) - int(time_boot_ms) * 1000
        if lk.offset_us is not None and abs(sample - lk.offset_us) > 1_000_000:
            # the boot clock jumped (a reboot): the old samples describe another clock
            log.warning("link %d: its boot clock moved %.3f s against GPS time (a reboot): offset re-learnt",
                        lk.index + 1, (lk.offset_us - sample) * 1e-6)
            lk.clock_samples_us = []
        lk.clock_samples_us = (lk.clock_samples_us + [sample])[-CLOCK_SAMPLES:]
        first = lk.offset_us is None
        lk.offset_us = int(np.median(lk.clock_samples_us))
        if first:
            log.info("link %d: boot clock + %.3f s = GPS time", lk.index + 1, lk.offset_us * 1e-6)

    def on_rejected(self, row: int, kind: str, reason: str) -> None:
        """A state message from the link that failed validation (counted and logged)."""
        self._heard = True
        self.links[row].rejected += 1
        log.warning("link %d: rejected %s: %s", self.links[row].index + 1, kind, reason)

    def on_state(self, row: int, state: LinkState, flags: int, now_s: float, correction_seq: int = 0,
                 correction_latency_us: int = 0) -> bool:
        """A validated state of link ``row`` (``state.link`` its chain index, stamped on the link's
        clock), with the flags and the correction it reports. ``False``: not usable yet (no GPS
        time offset for this link, or its stamp was rejected: then nothing it carries is used,
        flags and reported latency included)."""
        self._heard = True
        lk = self.links[row]
        if self.cfg.time_base == "gps":
            if lk.offset_us is None:
                return False
            state = replace(state, time_s=(_usec(state.time_s) + lk.offset_us) * 1e-6)
        stamp_us = _usec(state.time_s)
        verdict = lk.stamps.check(stamp_us, now_s)
        if verdict in (StampVerdict.REPLAY, StampVerdict.FUTURE):
            lk.stamp_rejected_s = self.fc_time_us * 1e-6  # its flags are not believed for a while
        if verdict is StampVerdict.REPLAY:
            lk.replayed += 1
            self._log_rejection(lk, "replay", now_s, "state stamped %.3f s, not newer than its last (%.3f s): a "
                                "replay or a reordered frame", stamp_us * 1e-6, lk.stamps.last_us * 1e-6)
            return False
        if verdict is StampVerdict.FUTURE:
            lk.future += 1
            self._log_rejection(lk, "future", now_s, "state stamped %.3f s, %.3f s after its last: further than its "
                                "clock can have run", stamp_us * 1e-6, (stamp_us - lk.stamps.last_us) * 1e-6)
            return False
        if verdict is StampVerdict.REBASED:
            lk.reboots += 1
            lk.readmit_cycles = READMIT_CYCLES
            log.warning("link %d: silent, then back on a new clock (%.3f s): rebooted; re-admitted after %d usable "
                        "cycles", lk.index + 1, stamp_us * 1e-6, READMIT_CYCLES)
        elif lk.last_state_s is not None and now_s - lk.last_state_s >= self.cfg.reboot_silence_s:
            lk.readmit_cycles = READMIT_CYCLES
            log.warning("link %d: back after %.1f s of silence; re-admitted after %d usable cycles", lk.index + 1,
                        now_s - lk.last_state_s, READMIT_CYCLES)
        if correction_seq != lk.correction_seq and correction_seq > 0:
            lk.correction_seq = correction_seq
            lk.latencies_ms.append(correction_latency_us * 1e-3)
            lk.latency_window_ms.append(correction_latency_us * 1e-3)
        lk.flags = flags
        lk.disarmed_states = 0 if flags & STATE_FLAG_ARMED else lk.disarmed_states + 1
        lk.state = state
        lk.states += 1
        lk.last_state_s = now_s
        if self._cycle_clock.check(stamp_us, now_s) in (StampVerdict.ACCEPTED, StampVerdict.REBASED):
            self.fc_time_us = stamp_us
        return True

    def _log_rejection(self, lk: LinkTrack, kind: str, now_s: float, fmt: str, *args) -> None:
        """The first rejection of a kind per link, then at most one every 5 s."""
        key = (lk.row, kind)
        if now_s - self._reject_logged_s.get(key, -np.inf) >= 5.0:
            self._reject_logged_s[key] = now_s
            log.warning("link %d: " + fmt, lk.index + 1, *args)

    # -- the loop ----------------------------------------------------------------------------------
    def next_deadline_s(self) -> float | None:
        """When :meth:`poll` next has something to do without new input (the network's deadlines)."""
        return self.net.next_deadline_s() if self.net is not None else None

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
        if self.cfg.arm and any(self._arm_due(lk, now_s) for lk in self.links):
            return True
        return self.net is not None and self.net.needs_pump(now_s)

    def poll(self, now_s: float) -> list:
        """Run what is due at ``now_s``; returns the outputs (see the module docstring)."""
        self._heard = False
        if self.net is not None:
            self._finish(self.net.pump(now_s))
            for msg in self.net.take_targets():
                if self._net_targets:
                    self._forward_targets(msg, now_s)
            for msg in self.net.take_passive():
                self._on_remote_passive(msg)
        self._duties(now_s)
        if self._all_states():
            t = self.fc_time_us
            if self.next_step_us is None:
                # steps on the period grid of flight-controller time: the groups' cycles coincide
                self.next_step_us = -(-t // self.period_us) * self.period_us
                self.next_target_us = t
            if self.cfg.targets == "trajectory" and t >= self.next_target_us:
                self._send_targets(now_s)
                self.next_target_us += self.target_period_us * max(1, (t - self.next_target_us) // self.target_period_us + 1)
            if t >= self.next_step_us:
                newest = [_usec(lk.state.time_s) for lk in self.links]
                # Step once every link has reported for this step time (a coherent snapshot); a link
                # lagging more than LAG_LIMIT behind the others is not waited for (and left out of the
                # step, :meth:`_plan`), so one silent link degrades the step, never stalls it.
                spread = max(newest) - min(newest)
                if min(newest) >= self.next_step_us or spread > LAG_LIMIT_US:
                    self._step(now_s)
                    self.next_step_us += self.period_us * max(1, (t - self.next_step_us) // self.period_us + 1)
            self._arm(now_s)
        out, self._out = self._out, []
        return out

    def _duties(self, now_s: float) -> None:
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

    # -- the 20 Hz step --------------------------------------------------------------------------------
    def _plan(self, t_us: int, now_s: float) -> tuple[list[tuple[int, ...]], bool, float]:
        """Which of this engine's links the step at ``t_us`` uses (plausibility before use).

        A link is left out when its newest state is more than :data:`LAG_LIMIT_US` from ``t_us``,
        its EKF is not usable, it is back from a silence or a reboot, or the joint gate
        (:func:`~companion.estimation.gate.gate_chain`) finds it inconsistent with its neighbours;
        the chain splits there. Returns the segments (rows, at least two consecutive links each),
        whether every link is usable with no joint cut (``whole``), and the largest joint NIS.
        Each link's :attr:`LinkTrack.status` says why it is out ("" if it is in)."""
        usable = []
        for lk in self.links:
            off_us = _usec(lk.state.time_s) - t_us
            if abs(off_us) > LAG_LIMIT_US:
                why = "stale"
                self._log_rejection(lk, "stale", now_s, "newest state %.3f s from the step time: it stopped streaming, or "
                                    "its clock does not share the chain's time base; left out, the others go on",
                                    off_us * 1e-6)
            elif not lk.flags & STATE_FLAG_EKF_OK:
                why = "ekf"
            elif lk.readmit_cycles > 0:
                why = "returning"
                lk.readmit_cycles -= 1
            else:
                why = ""
            lk.status = why
            usable.append(not why)
        cut = [False] * (len(self.links) - 1)
        nis_max = float("nan")
        self._one_way = set()
        for run in segments(usable):
            rows = list(run)
            _, p, v, q = align_states([self.links[r].state for r in rows], t_us * 1e-6)
            w = np.array([self.links[r].state.omega_b_rad_s for r in rows])
            P = np.array([self._step_state(self.links[r]).P for r in rows])
            res = gate_chain(p, v, q, w, self.d[rows], P, self.gate_params)
            # A link that flags a GPS fault and disagrees with its neighbours is not left out: its
            # state is the suspect (its own firmware says so), so it takes part one way.
            suspects = {k for k, r in enumerate(rows) if self.links[r].flags & STATE_FLAG_GPS_FAULT
                        and (k in res.excluded or (k > 0 and res.cut[k - 1]) or (k < len(rows) - 1 and res.cut[k]))}
            if suspects:
                self._one_way.update(rows[k] for k in suspects)
                P = np.array([self._step_state(self.links[r]).P for r in rows])
                res = gate_chain(p, v, q, w, self.d[rows], P, self.gate_params)
            for j, c in enumerate(res.cut):
                cut[run[0] + j] = bool(c)
            for k in res.excluded:
                self.links[run[k]].status = "gate"
                usable[run[k]] = False
            if res.nis.size:
                nis_max = float(np.nanmax(np.append(res.nis, nis_max)))
        for r in self._one_way:
            self.links[r].gps_fault_steps += 1
        whole = all(usable) and not any(cut)
        segs = segments(usable, cut)
        in_segment = {r for seg in segs for r in seg}
        for lk in self.links:
            if not lk.status and lk.row not in in_segment and not whole:
                lk.status = "alone"
            if lk.status:
                lk.excluded[lk.status] = lk.excluded.get(lk.status, 0) + 1
        if not whole:
            self.degraded += 1
            if not segs:
                self.withheld += 1
        return segs, whole, nis_max

    def _common_removable(self, P: np.ndarray) -> bool:
        """Whether the configured common GNSS error can come out of ``P`` (its position block is larger)."""
        return self._common is not None and np.linalg.eigvalsh(P[ERR_P, ERR_P] - self._common).min() > 0.0

    def _step_state(self, lk: LinkTrack) -> LinkState:
        """``lk``'s state as the step uses it: without the GNSS error common to all links
        (``gnss_common_pos_var_m2``: no constraint sees it; :meth:`_restore_common` puts it back),
        and one way (position variance raised by :data:`GPS_FAULT_POS_VAR_M2`) when :meth:`_plan`
        found its flagged GPS fault at odds with its neighbours, so the step moves it onto them and
        leaves them unmoved."""
        common = self._common_removable(lk.state.P)
        if lk.row not in self._one_way and not common:
            return lk.state
        P = lk.state.P.copy()
        if common:
            P[ERR_P, ERR_P] -= self._common
        if lk.row in self._one_way:
            P[ERR_P, ERR_P] += GPS_FAULT_POS_VAR_M2 * np.eye(3)
        return replace(lk.state, P=P)

    def _restore_common(self, P_reported: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The corrected covariances ``P`` with the common GNSS error that :meth:`_step_state`
        took out of the links' reported ones, ``P_reported`` (same order), put back."""
        if self._common is None:
            return P
        P = np.array(P, dtype=float)
        for j, Pr in enumerate(P_reported):
            if self._common_removable(Pr):
                P[j][ERR_P, ERR_P] += self._common
            else:
                self.common_mode_kept += 1
                if self.common_mode_kept == 1:
                    log.warning("a link's position covariance is not larger than gnss_common_pos_var_m2: it keeps "
                                "its covariance as reported (its EKF does not report the receiver's bias?)")
        return P

    def _segment_groups(self, seg: tuple[int, ...]) -> list[tuple[int, ...]]:
        """This engine's groups cut to segment ``seg`` (rows), numbered from its first link."""
        members = set(seg)
        out = [tuple(r - seg[0] for r in g if r in members) for g in self.groups]
        return [g for g in out if g]

    def _step(self, now_s: float) -> None:
        if not self.cfg.enabled:
            self._observe()
            return
        if self.net is not None:
            self._local_half(now_s)
            return
        segs, _, nis_max = self._plan(self.fc_time_us, now_s)
        ekf, p, v, q, p_local, iterations, corrected, P = self._correct_segments(segs, None, split_groups=True)
        self._record(self.fc_time_us, -1, ekf, p, v, q, p_local, iterations, bool(corrected.any()), -1, corrected,
                     nis_max, P)

    def _correct_segments(self, segs, t_s: float | None, split_groups: bool):
        """Constraint application on every segment on its own, aligned to ``t_s`` (default: each
        segment's newest stamp), and its links' corrections out. ``split_groups``: a segment keeps
        its part of the configured groups (Alg. 2 + eq. 6 inside it); else it is one group (Alg. 1,
        a group companion's local-only step). Returns the step log's ``(ekf, p, v, q, p_local,
        iterations, corrected, (P_ekf, P_corr))`` over this engine's links (a link not corrected keeps
        its EKF state; a silent one, whose newest state is too old to say where it is, is NaN; P_ekf
        is what the links reported, P_corr the constraint application's covariance)."""
        states = [self._step_state(lk) for lk in self.links]
        ekf = _stacked(states)
        for lk in self.links:
            if lk.status == "stale":
                for a in ekf:
                    a[lk.row] = np.nan
        p, v, q = (a.copy() for a in ekf[:3])
        P_ekf = np.array([lk.state.P for lk in self.links])
        P_corr = P_ekf.copy()
        p_local = p.copy()
        corrected = np.zeros(len(self.links), dtype=bool)
        iterations = 0
        t0 = self._timer()
        done = []
        for seg in segs:
            rows = list(seg)
            groups = self._segment_groups(seg) if split_groups else [tuple(range(len(rows)))]
            try:
                result, corrections = compute_corrections([states[r] for r in rows], self.d[rows], groups,
                                                          self.params, self.seq, t_s)
            except (ValueError, np.linalg.LinAlgError) as exc:
                log.warning("constraint application failed at t = %.3f s (links %s): %s",
                            self.fc_time_us * 1e-6 if t_s is None else t_s, [self.links[r].index + 1 for r in rows], exc)
                continue
            p[rows], v[rows], q[rows] = result.p, result.v, result.q
            P_seg = self._restore_common(P_ekf[rows], result.P)
            P_corr[rows] = P_seg
            p_local[rows] = np.concatenate([r.p for r in result.local])
            corrected[rows] = True
            iterations = max(iterations, int(result.iterations.max()))
            done.append((seg, corrections, (result.p, result.v, result.q, P_seg)))
        self.step_times_ms.append((self._timer() - t0) * 1e3)
        for seg, corrections, result in done:
            self._send_corrections(seg, corrections, result)
        if done:
            self.seq = (self.seq + 1) & 0xFFFF or 1
        return ekf, p, v, q, p_local, iterations, corrected, (P_ekf, P_corr)

    def _observe(self) -> None:
        """``enabled = false``: log the links' EKF states at the step time, correct nothing."""
        ekf = _stacked([lk.state for lk in self.links])
        cycle = self.next_step_us if self.net is not None else -1
        p, v, q, _ = ekf
        P = np.array([lk.state.P for lk in self.links])
        self._record(self.fc_time_us if cycle < 0 else cycle, cycle, ekf, p, v, q, p, 0, False, -1,
                     np.zeros(len(self.links), dtype=bool), float("nan"), (P, P))

    def _local_half(self, now_s: float) -> None:
        """Distributed mode: local constraint application at the cycle time, boundary out. A group
        with a link left out publishes no boundary that cycle (its chain is cut anyway): each of
        its segments gets its local-only corrections at once."""
        cycle = self.next_step_us
        segs, whole, nis_max = self._plan(cycle, now_s)
        if not whole:
            ekf, p, v, q, _, iterations, corrected, P = self._correct_segments(segs, cycle * 1e-6, split_groups=False)
            self._record(cycle, cycle, ekf, p, v, q, p, iterations, False, -1, corrected, nis_max, P)
            return
        states = [self._step_state(lk) for lk in self.links]
        t0 = self._timer()
        try:
            step = local_step(states, self.d, self.params, t=cycle * 1e-6)
        except (ValueError, np.linalg.LinAlgError) as exc:
            log.warning("local constraint application failed at t = %.3f s: %s", cycle * 1e-6, exc)
            return
        self.step_times_ms.append((self._timer() - t0) * 1e3)
        # (the links' reported covariances, for the log and the common GNSS error to put back)
        self._local[cycle] = (states, step, nis_max, np.array([lk.state.P for lk in self.links]))
        b = step.boundary
        # stamped when it goes out, after the computation (the shift deadline runs from there)
        self._finish(self.net.local_step(b.left_tip, b.right_tip, b.info_pv, cycle, self.net.clock(), b.tip_cov))

    def _finish(self, resolved) -> None:
        """Corrections for the cycles that ended (with the leader's shift, or local-only)."""
        for res in resolved:
            entry = self._local.pop(res.cycle_us, None)
            for old in [c for c in self._local if c < res.cycle_us]:
                del self._local[old]
            if entry is None:
                continue
            states, step, nis_max, P_reported = entry
            if res.shift is None and res.reason:
                log.debug("cycle t = %.3f s: local-only corrections (%s)", res.cycle_us * 1e-6, res.reason)
            p, v, q, P, corrections = finish_step(states, step, res.shift, self.seq, res.shift_gain, res.shift_cov)
            P = self._restore_common(P_reported, P)
            self.seq = (self.seq + 1) & 0xFFFF or 1
            self._send_corrections(tuple(range(len(self.links))), corrections, (p, v, q, P))
            self._record(res.cycle_us, res.cycle_us, (step.p, step.v, step.q, step.w), p, v, q, step.result.p,
                         int(step.result.iterations),
                         res.shift is not None, -1 if res.leader_group is None else res.leader_group + 1,
                         np.ones(len(self.links), dtype=bool), nis_max, (P_reported, P))

    def _record(self, t_us: int, cycle_us: int, ekf, p, v, q, p_local, iterations: int, global_applied: bool,
                leader: int, corrected: np.ndarray, nis_max: float, P) -> None:
        """One step log row; ``ekf`` is ``(p, v, q, w)`` of the links' states the step started from
        (aligned to the cycle in distributed mode), ``p, v, q`` the corrected estimate (a link's
        EKF state where ``corrected`` is false), ``nis_max`` the largest joint NIS of the gate,
        ``P`` the ``(n, 9, 9)`` covariances ``(reported by the links, after the constraint
        application)`` (carried through the global step of eq. 6 when there was one:
        :func:`~companion.estimation.semi.shifted_covariance`), logged as their 3x3 position,
        velocity and attitude blocks."""
        pe, ve, qe, we = ekf
        row = {"t_sckf": t_us * 1e-6, "cycle_us": cycle_us, "p_ekf_sckf": pe, "v_ekf_sckf": ve, "q_ekf_sckf": qe,
               "w_sckf": we, "p_local_sckf": p_local, "p_corr_sckf": p, "v_corr_sckf": v, "q_corr_sckf": q,
               "iterations": iterations, "global_applied": global_applied, "leader": leader,
               "corrected_sckf": corrected, "nis_max_sckf": nis_max,
               "P_ekf_sckf": _blocks(P[0]), "P_corr_sckf": _blocks(P[1])}
        for key, value in row.items():
            self.log[key].append(value)

    def _send_corrections(self, rows: tuple[int, ...], corrections, result) -> None:
        """Links ``rows`` their corrections and corrected estimates, stamped on each link's own
        clock; ``result`` is ``(p, v, q, P)`` of those links, in their order."""
        p, v, q, P = result
        for j, (r, corr) in enumerate(zip(rows, corrections)):
            lk = self.links[r]
            t_link = lk.to_link_clock_us(_usec(corr.ekf_time_s)) * 1e-6
            self._out.append(CorrectionOut(lk.row, lk.system_id, replace(corr, ekf_time_s=t_link),
                                           LinkState(lk.index, t_link, p[j], v[j], q[j], lk.state.omega_b_rad_s, P[j])))

    # -- targets and arming ----------------------------------------------------------------------------
    def _send_targets(self, now_s: float) -> None:
        if not self._trajectory_started:
            self._trajectory_started = True
            self._trajectory_t0_us = self._trajectory_start_us()
        if self.trajectory is None:
            center = self._start_center
            if center is None:
                center = chain_middle(np.array([lk.state.p_w_m for lk in self.links]),
                                      np.array([lk.state.q_wxyz for lk in self.links]), self.d)
            self.trajectory = make_trajectory(self.setup.trajectory, self.setup.motion, self.setup.skeleton, center)
        # Trajectory time starts when every link has first reported (on hardware the flight
        # controllers have been up for a while; in SITL this is within a tick of t = 0).
        passive = self._passive_links(now_s)
        if self.net is not None:
            self._publish_passive(passive)
            passive = passive | self._remote_passive_links()
        targets = self.trajectory.targets((self.fc_time_us - self._trajectory_t0_us) * 1e-6, passive=passive)
        if self._net_targets:
            if self.net.leads(self.next_step_us, now_s):
                self.net.publish_targets(ChainTargets.of(self.group, self.fc_time_us,
                                                         self.target_counts["published"] & 0xFFFFFFFF, range(self.n),
                                                         targets))
                self.target_counts["published"] += 1
            elif now_s - self._leader_targets_s < 3e-6 * self.target_period_us:
                return  # the leader's targets are being forwarded (:meth:`_forward_targets`)
            self.target_counts["own"] += 1
        for lk in self.links:
            self._target_out(lk, self.fc_time_us, targets[lk.index])

    def _passive_links(self, now_s: float) -> frozenset[int]:
        """The chain indices of this engine's links whose rotors are taken to be off: a link that
        has flown and is now silent ``carry_silence_s`` (its newest state that far behind the
        median of the links' newest, the newest with fewer than three links; and nothing from it
        for ``carry_silence_s / clock_rate_max`` on the companion's own clock ``now_s``, so that a
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
        # three links (a group's engine) the cycle clock, the newest stamp
        t = median(heard) if len(heard) >= 3 else self.fc_time_us * 1e-6
        quiet_s = cfg.carry_silence_s / cfg.clock_rate_max  # the same silence, on the companion's clock
        for lk in self.links:
            lag = np.inf if lk.state is None else t - lk.state.time_s
            silent = lag >= cfg.carry_silence_s and (lk.last_state_s is None or now_s - lk.last_state_s >= quiet_s)
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
            if not armed or lag >= cfg.reboot_silence_s:  # unheard that long: it may have rebooted
                lk.armed_since_s = None
            elif lk.armed_since_s is None and not silent:
                lk.armed_since_s = t
            spinning = armed and not silent and t - lk.armed_since_s >= cfg.carry_spinup_s
            lk.flown = lk.flown or spinning
            passive = lk.flown and (silent or not spinning)
            was = lk.carried.on
            ended = lk.carried.switch(passive, t)
            if passive and not was:
                why = "silent" if silent else "disarmed in flight" if not armed else "re-armed, rotors starting"
                log.warning("link %d: %s at %.2f s: its neighbours carry it (whole-chain feed-forward)",
                            lk.index + 1, why, t)
            elif ended is not None:
                log.warning("link %d: flies itself again at %.2f s, after %.2f s carried", lk.index + 1, t, ended)
            if passive:
                out.add(lk.index)
        return frozenset(out)

    # -- carrying across groups (distributed mode) -------------------------------------------------
    def _publish_passive(self, own: frozenset[int]) -> None:
        """This group's carried links to the other groups: when the set changes, and each
        :data:`PASSIVE_REPEAT_US` (a group that starts later, or lost one, learns it)."""
        links, t = tuple(sorted(own)), self.fc_time_us
        sent = self._passive_sent
        if sent is not None and sent[0] == links and t - sent[1] < PASSIVE_REPEAT_US:
            return
        self._passive_sent = (links, t)
        self.net.publish_passive(GroupPassiveLinks(self.group, t, links))
        self.passive_counts["published"] += 1

    def _on_remote_passive(self, msg: GroupPassiveLinks) -> None:
        """Another group's carried links: kept (its newest) if they are that group's own links and,
        once this group has a cycle clock, its stamp is within :data:`PASSIVE_STALE_US` of it either
        way; otherwise counted and dropped (a group cannot make another group's links, or this
        group's, carried). Only a current claim is used (:meth:`_remote_passive_links`), and one
        that is not current gives way to any other (a stamp far ahead cannot pin a claim)."""
        g = msg.group
        why = None
        if g == self.group or not 0 <= g < len(self.groups):
            why = f"from group {g + 1}"
        elif not set(msg.links) <= set(self.groups[g]):
            why = f"links {[i + 1 for i in msg.links]} are not all group {g + 1}'s"
        elif self.fc_time_us and not self._passive_current(msg):
            why = f"stamp {msg.time_us * 1e-6:.3f} s, {(msg.time_us - self.fc_time_us) * 1e-6:+.3f} s off the cycle clock"
        if why is not None:
            self.passive_counts["rejected"] += 1
            n = self.passive_counts["rejected"]
            if n <= 5 or n % 100 == 0:
                log.warning("carried links of group %d dropped (#%d): %s", g + 1, n, why)
            return
        self.passive_counts["received"] += 1
        old = self._remote_passive.get(g)
        if old is None or msg.time_us >= old.time_us or not self._passive_current(old):
            self._remote_passive[g] = msg

    def _passive_current(self, msg: GroupPassiveLinks) -> bool:
        """Whether a group's claim is within :data:`PASSIVE_STALE_US` of this group's cycle clock."""
        return bool(self.fc_time_us) and abs(msg.time_us - self.fc_time_us) <= PASSIVE_STALE_US

    def _remote_passive_links(self) -> frozenset[int]:
        """The links the other groups' companions carry (their newest messages, not stale, while
        they are up); each carried stretch is logged and timed (``carried_by_other_groups_s``)."""
        t_us = self.fc_time_us
        out: set[int] = set()
        for g, msg in self._remote_passive.items():
            if self.net.alive(g) and self._passive_current(msg):
                out.update(msg.links)
        t = t_us * 1e-6
        for i in out | {i for i, clock in self._remote_carried.items() if clock.on}:
            clock = self._remote_carried.setdefault(i, CarryClock())
            was = clock.on
            if clock.switch(i in out, t) is not None:
                log.warning("link %d (group %d) flies itself again at %.2f s", i + 1, self._group_of(i) + 1, t)
            elif clock.on and not was:
                log.warning("link %d (group %d) carried at %.2f s: its rotors are off (its group's companion says)",
                            i + 1, self._group_of(i) + 1, t)
        return frozenset(out)

    def _group_of(self, link: int) -> int:
        return next(g for g, members in enumerate(self.groups) if link in members)

    def _trajectory_start_us(self) -> int:
        """Where trajectory time starts on the time base: 0 for distributed companions on the links'
        shared clock (SITL: simulation time, the same in every group), else the first targets."""
        shared = self.net is not None and self.cfg.time_base == "flight_controller"
        return 0 if shared else self.fc_time_us

    def _forward_targets(self, msg: ChainTargets, now_s: float) -> None:
        """Send this group's links their share of the leader's CPG targets."""
        self.target_counts["received"] += 1
        if msg.time_us <= self._forwarded_time_us:
            self.target_counts["stale"] += 1  # out of order, or a second leader during a hand-over
            return
        self._forwarded_time_us = msg.time_us
        self._leader_targets_s = now_s
        rows = {link: k for k, link in enumerate(msg.links)}
        for lk in self.links:
            k = rows.get(lk.index)
            if k is not None:
                self._target_out(lk, msg.time_us, msg.target(k))
        self.target_counts["forwarded"] += 1

    def _target_out(self, lk: LinkTrack, time_us: int, target: PoseTarget) -> None:
        self._out.append(TargetOut(lk.row, lk.system_id, lk.to_link_clock_us(time_us), target))

    def _arm(self, now_s: float) -> None:
        if not self.cfg.arm:
            return
        for lk in self.links:
            if lk.flags & STATE_FLAG_ARMED:
                lk.arm_tries = 0
                continue
            if not self._arm_due(lk, now_s):
                continue
            self._out.append(CommandOut(lk.row, lk.system_id, Command.ARM))
            lk.arm_sent_s = now_s
            lk.arm_tries += 1

    @staticmethod
    def _arm_due(lk: LinkTrack, now_s: float) -> bool:
        """A disarmed link with a healthy EKF whose last ARM was sent its retry interval ago."""
        if lk.flags & STATE_FLAG_ARMED or not lk.flags & STATE_FLAG_EKF_OK:
            return False
        return now_s - lk.arm_sent_s >= (ARM_RETRY_S if lk.arm_tries < ARM_FAST_TRIES else RETRY_S)

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
                "status": lk.status or ("gps" if lk.row in self._one_way else ""),
                "latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
                "latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
            })
            lk.states_at_report = lk.states
            lk.excluded_at_report = excluded
            lk.latency_window_ms = []
        return rows

    def summary(self) -> dict:
        lat = np.concatenate([np.asarray(lk.latencies_ms) for lk in self.links]) if self.links else np.zeros(0)
        steps = np.asarray(self.step_times_ms)
        return {
            "steps": int(steps.size),
            "withheld_steps": self.withheld,
            "degraded_steps": self.degraded,
            "common_mode_kept": self.common_mode_kept,
            "step_ms": {"p50": float(np.percentile(steps, 50)), "p99": float(np.percentile(steps, 99))} if steps.size else None,
            "correction_latency_ms": {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)),
                                      "samples": int(lat.size)} if lat.size else None,
            "links": {str(lk.system_id): {"states": lk.states, "rejected": lk.rejected, "replayed": lk.replayed,
                                          "future": lk.future, "reboots": lk.reboots,
                                          "gps_fault_steps": lk.gps_fault_steps,
                                          "carried_s": round(lk.carried.seconds(self.fc_time_us * 1e-6), 3),
                                          "excluded_steps": dict(lk.excluded)} for lk in self.links},
            **(self.net.summary() if self.net is not None else {}),
            **({"cpg_targets": dict(self.target_counts)} if self._net_targets else {}),
            **({"carried_by_other_groups_s": {
                str(self.cfg.endpoints(self.n)[i].system_id): round(clock.seconds(self.fc_time_us * 1e-6), 3)
                for i, clock in sorted(self._remote_carried.items())},
                "carried_links_messages": dict(self.passive_counts)} if self.net is not None else {}),
        }

    def log_arrays(self) -> dict[str, np.ndarray]:
        """The step log as arrays (keys with at least one row)."""
        return {k: np.asarray(v) for k, v in self.log.items() if v}

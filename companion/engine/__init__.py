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

What it decides, on the links' flight-controller time (the newest plausible EKF stamp received),
one module per concern:

* :mod:`.admission`: the time base (``gps``: each link's boot clock mapped to GPS time through
  SYSTEM_TIME) and plausibility before use (replayed or future stamps rejected, reboots and
  silences re-admitted after :data:`READMIT_CYCLES` usable cycles);
* :mod:`.selection`: which links a step uses (stale, EKF not usable, returning, the joint
  chi-square gate; a link flagging a GPS fault at odds with its neighbours takes part one way)
  and why each is out (:data:`EXCLUSION_REASONS`);
* :mod:`.step`: every 1/``rate_hz``, once every link has reported for the step time (or a link
  lags more than :data:`LAG_LIMIT_US`), the constraint application on every segment and the
  links' corrections; in distributed mode the group's local half, the boundary to the leader and
  the corrections when its shift arrives or its deadline passes; the step log
  (:data:`STEP_LOG_KEYS`);
* :mod:`.targets` and :mod:`.carrying`: every 1/``target_rate_hz`` every link's pose target
  from the trajectory, the carried links' weight taken by their neighbours (whole-chain
  feed-forward), CPG targets from the leader in distributed mode;
* :mod:`.arming`: ARM once a link reports a usable EKF, the state stream on its heartbeat;
* :mod:`.core`: the schedule (the step grid, the target period, the 1 Hz heartbeat, the health
  report every ``health_period_s``) and the reports (:meth:`~CompanionEngine.health_rows`,
  :meth:`~CompanionEngine.summary`).

What each link is known by: :mod:`.links` (:class:`LinkTrack`); the outputs: :mod:`.outputs`.
"""

from .admission import CLOCK_SAMPLES, READMIT_CYCLES
from .arming import ARM_FAST_TRIES, ARM_RETRY_S, RETRY_S
from .core import CompanionEngine
from .links import LinkTrack
from .outputs import Command, CommandOut, CorrectionOut, HealthDue, Heartbeat, TargetOut
from .selection import EXCLUSION_REASONS, LAG_LIMIT_US
from .step import STEP_LOG_KEYS

__all__ = [
    "LAG_LIMIT_US",
    "EXCLUSION_REASONS",
    "READMIT_CYCLES",
    "CLOCK_SAMPLES",
    "RETRY_S",
    "ARM_RETRY_S",
    "ARM_FAST_TRIES",
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

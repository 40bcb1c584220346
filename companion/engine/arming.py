"""Arming and the state stream: the commands the engine sends each link.

* arming (``arm = true``) once a link reports a usable EKF, until it reports armed: retried every
  :data:`ARM_RETRY_S` for the first :data:`ARM_FAST_TRIES` commands, then each :data:`RETRY_S`
  (a link rebooted in flight has its rotors off until armed: one lost command must not cost a
  second; a link that keeps refusing is not flooded). A link that reported armed and then
  disarmed while it kept streaming was disarmed by someone (its pilot, a failsafe): it is not
  armed again until its stream breaks off (``carry_silence_s`` of silence, or a new clock: it may
  have powered off and on);
* the state stream (SET_MESSAGE_INTERVAL) on a link's heartbeat, retried each :data:`RETRY_S`
  until acknowledged.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from ..messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK
from .links import LinkTrack
from .outputs import Command, CommandOut

__all__ = ["RETRY_S", "ARM_RETRY_S", "ARM_FAST_TRIES", "Arming"]

log = logging.getLogger(__name__)

#: Retry period of unacknowledged commands, the heartbeat period [s].
RETRY_S = 1.0
#: Retry period of the first ARM commands to a disarmed link with a usable EKF [s], and how many
#: are sent that fast before :data:`RETRY_S` (MAVSDK retransmits a command after 0.5 s).
ARM_RETRY_S = 0.2
ARM_FAST_TRIES = 5


class Arming:
    """The ARM and stream-rate commands under ``cfg`` (a :class:`~companion.config.CompanionConfig`),
    each given to ``emit`` as a :class:`~.outputs.CommandOut`."""

    def __init__(self, cfg, emit: Callable[[object], None]):
        self.arm = cfg.arm
        self.state_rate_hz = cfg.state_rate_hz
        self._emit = emit

    def on_heartbeat(self, lk: LinkTrack, now_s: float) -> None:
        """A link's heartbeat: ask for its state stream until it acknowledges."""
        if lk.stream_acked or now_s - lk.stream_sent_s < RETRY_S:
            return
        self._emit(CommandOut(lk.row, lk.system_id, Command.STREAM, 1e6 / self.state_rate_hz))
        lk.stream_sent_s = now_s

    def on_command_ack(self, lk: LinkTrack, command: Command, accepted: bool, result: int = 0) -> None:
        """A link's answer to a command (``result``: its MAV_RESULT)."""
        if command is Command.ARM and accepted:
            lk.armed_ack = True
        elif command is Command.STREAM and not lk.stream_acked:
            lk.stream_acked = True
            if not accepted:
                log.warning("link %d refused the state stream rate (MAV_RESULT %d): using its own rate", lk.index + 1,
                            result)

    def run(self, links: list[LinkTrack], now_s: float) -> None:
        """ARM to every link that is due one at ``now_s``."""
        if not self.arm:
            return
        for lk in links:
            if lk.flags & STATE_FLAG_ARMED:
                lk.arm_tries = 0
                continue
            if lk.was_armed and lk.flags & STATE_FLAG_EKF_OK and not lk.disarm_logged:
                lk.disarm_logged = True
                log.warning("link %d was disarmed (its pilot, a failsafe): not arming it again", lk.index + 1)
            if not self.due(lk, now_s):
                continue
            self._emit(CommandOut(lk.row, lk.system_id, Command.ARM))
            lk.arm_sent_s = now_s
            lk.arm_tries += 1

    def any_due(self, links: list[LinkTrack], now_s: float) -> bool:
        """Whether :meth:`run` at ``now_s`` would send an ARM."""
        return self.arm and any(self.due(lk, now_s) for lk in links)

    @staticmethod
    def due(lk: LinkTrack, now_s: float) -> bool:
        """A disarmed link with a healthy EKF whose last ARM was sent its retry interval ago, and
        that nobody disarmed since it powered on."""
        if lk.flags & STATE_FLAG_ARMED or not lk.flags & STATE_FLAG_EKF_OK or lk.was_armed:
            return False
        return now_s - lk.arm_sent_s >= (ARM_RETRY_S if lk.arm_tries < ARM_FAST_TRIES else RETRY_S)

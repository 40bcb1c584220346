"""The firmware's pose target from the companion's (or an operator's) messages:
SET_POSITION_TARGET_LOCAL_NED, SET_ATTITUDE_TARGET and SKELETON_TARGET_FEEDFORWARD, the last
applied to the position target of the same ``time_boot_ms``. A position target that carries a
heading (its yaw not masked out, as a stock PX4's offboard setpoints do) and no attitude target
with it: level at that heading, turning at its yaw rate.

The messages of one read of a link make one target (:meth:`TargetMessages.apply`, after the read),
so the companion's three in one datagram reach the firmware as one target (under PSPM, one set
pose), not as three partial ones at the same flight-controller time.
"""

from __future__ import annotations

import logging

import numpy as np

from companion.mavlink.codec import MessageError, decode_target_feedforward
from companion.estimation.so3 import quat_from_euler_zyx
from companion.mavlink.frames import flu_frd, quat_ned_frd_to_enu_flu
from companion.mavlink.standard import decode_attitude_target, decode_position_target, decode_position_target_yaw
from companion.messages import PoseTarget

__all__ = ["FEEDFORWARD_HOLD_MS", "TargetMessages"]

log = logging.getLogger(__name__)

#: How long a SKELETON_TARGET_FEEDFORWARD goes on applying to later position targets when theirs
#: has not come (lost, or still on its way) [ms of time_boot_ms]: five 50 Hz target periods.
FEEDFORWARD_HOLD_MS = 100


class TargetMessages:
    """The newest target messages of vehicle ``vehicle`` (its firmware, its flight-controller time,
    its error counters) and the target they make."""

    def __init__(self, vehicle):
        self.vehicle = vehicle
        self.position: tuple | None = None  # (p, v, a) ENU
        self.position_ms = -1  # its time_boot_ms
        self.feedforward: tuple | None = None  # (time_boot_ms, omega_dot FLU, force ENU, torque FLU)
        self._ff_applied: tuple | None = None  # the newest one that met its position target
        self.attitude: tuple | None = None  # (q ENU/FLU, omega FLU)
        self.heading: tuple | None = None  # (yaw, yaw rate) NED of the newest position target, when it had one
        #: a target message came: :meth:`apply` after the link's read
        self.due = False

    def on_position_target(self, msg) -> None:
        self.position, self.heading = decode_position_target(msg), decode_position_target_yaw(msg)
        self.position_ms = msg.time_boot_ms
        self.due = True

    def on_attitude_target(self, msg) -> None:
        self.attitude = decode_attitude_target(msg)
        self.heading = None  # (an attitude target is the whole attitude)
        self.due = True

    def on_feedforward(self, msg) -> None:
        self.feedforward = (msg.time_boot_ms, *decode_target_feedforward(msg))
        if msg.time_boot_ms == self.position_ms:  # after its position target: applies now
            self.due = True

    def apply(self) -> None:
        """:meth:`update` after a read; a target the firmware refuses is counted as a bad message
        (``errors["mavlink"]``), as it was when each message applied its own."""
        try:
            self.update()
        except MessageError as exc:
            self.vehicle.errors["mavlink"] += 1
            log.warning("link %d: rejected a target: %s", self.vehicle.system_id, exc)

    def update(self) -> None:
        """The firmware's target from the newest position, attitude and feed-forward messages: once
        per read of a link, after all its messages."""
        self.due = False
        if self.position is None and self.attitude is None:
            return
        v = self.vehicle
        fw = v.fw
        if fw.initialized:
            p_now, _, q_now = fw.control_estimate(v.fc_time_s)
        else:
            p_now, q_now = np.zeros(3), np.array([1.0, 0, 0, 0])
        p, vel, a = self.position if self.position is not None else (p_now, np.zeros(3), np.zeros(3))
        if self.heading is not None:  # level at the position target's heading
            yaw, rate = self.heading
            q, w = quat_ned_frd_to_enu_flu(quat_from_euler_zyx(yaw, 0.0, 0.0)), flu_frd(np.array([0.0, 0.0, rate]))
        else:
            q, w = self.attitude if self.attitude is not None else (q_now, np.zeros(3))
        # The rest of the target (angular acceleration, whole-chain feed-forward) comes in its own
        # message stamped with its position target's time_boot_ms: it applies to that position
        # target and, while the next one's is still to come or was lost on the wire, to the
        # position targets of the next FEEDFORWARD_HOLD_MS (dropping it for a lost message would
        # drop, for one target period, the weight a link carries for a neighbour without rotors).
        # One that comes before its position target waits for it (the companion sends it first).
        ff = self.feedforward
        if ff is not None and ff[0] == self.position_ms:
            self._ff_applied = ff
        ff = self._ff_applied
        held = ff is not None and (self.position_ms - ff[0]) & 0xFFFFFFFF <= FEEDFORWARD_HOLD_MS
        wd, f_ff, tau_ff = ff[1:] if held else (np.zeros(3), np.zeros(3), np.zeros(3))
        # The target rate is in the desired body frame (eq. 1): FLU rates of the target attitude.
        fw.set_target(v.fc_time_s, PoseTarget(p, q, vel, a, w, wd, f_ff, tau_ff))

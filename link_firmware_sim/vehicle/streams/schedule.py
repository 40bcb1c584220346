"""Which message each stream id builds (:data:`BUILDERS`), the default rates of each link
(:func:`default_rates`), and :class:`Streams`: every link's streams on flight-controller time,
sent when due.

A stream runs in integer microseconds of flight-controller time, so it does not drift off the
simulator's tick grid, and its first message is at the next multiple of its interval: every
link's stream of one rate has the same phase whenever it was requested, and the companion gets
coherent snapshots of the chain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.mavlink.dialect import load_dialect

from ..params import StreamRates
from . import controller, link_state, position, system

__all__ = ["Stream", "BUILDERS", "UNSTREAMED", "RATE_PARAMS", "default_rates", "Streams"]

D = load_dialect()

#: message id -> the builder of that message (a function of the vehicle; ``None``: nothing to send)
BUILDERS = {
    D.MAVLINK_MSG_ID_SKELETON_LINK_STATE: link_state.link_state,
    D.MAVLINK_MSG_ID_ODOMETRY: link_state.odometry,
    D.MAVLINK_MSG_ID_ATTITUDE: position.attitude,
    D.MAVLINK_MSG_ID_LOCAL_POSITION_NED: position.local_position_ned,
    D.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: position.global_position_int,
    D.MAVLINK_MSG_ID_AUTOPILOT_VERSION: system.autopilot_version,
    D.MAVLINK_MSG_ID_SYS_STATUS: system.sys_status,
    D.MAVLINK_MSG_ID_HEARTBEAT: system.heartbeat,
    D.MAVLINK_MSG_ID_SYSTEM_TIME: system.system_time,
    D.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: position.gps_global_origin,
    D.MAVLINK_MSG_ID_HOME_POSITION: position.home_position,
    D.MAVLINK_MSG_ID_SKELETON_EXTERNAL_WRENCH: controller.external_wrench,
    D.MAVLINK_MSG_ID_DEBUG_VECT: controller.pspm,
}
#: built on request only, never streamed (HEARTBEAT keeps its own 1 Hz on the wall clock)
UNSTREAMED = frozenset({D.MAVLINK_MSG_ID_HEARTBEAT, D.MAVLINK_MSG_ID_AUTOPILOT_VERSION})
#: the stream rates a parameter sets (SKL_STATE_HZ, SKL_ODOM_HZ, SKL_WRENCH_HZ), on the onboard link
RATE_PARAMS = ("SKL_STATE_HZ", "SKL_ODOM_HZ", "SKL_WRENCH_HZ")


@dataclass
class Stream:
    """A periodic message on flight-controller time, in integer microseconds (no drift off the
    simulator's tick grid)."""

    interval_us: int
    next_us: int = 0

    @classmethod
    def at_rate(cls, hz: float, now_us: int = 0) -> Stream:
        return cls.every(int(round(1e6 / hz)), now_us)

    @classmethod
    def every(cls, interval_us: int, now_us: int = 0) -> Stream:
        """First message at the next multiple of the interval: every link's stream of one rate has
        the same phase whenever it was requested, so the companion gets coherent snapshots."""
        interval_us = max(int(interval_us), 1)
        return cls(interval_us, -(-now_us // interval_us) * interval_us)


def default_rates(rates: StreamRates, endpoint: int) -> dict[int, float]:
    """Message id -> default rate [Hz] of endpoint 0 (onboard) or 1 (GCS); ``rates``: the
    onboard link's configured ones."""
    if endpoint == 0:
        return {
            D.MAVLINK_MSG_ID_SKELETON_LINK_STATE: rates.state_hz,
            D.MAVLINK_MSG_ID_ODOMETRY: rates.odometry_hz,
            D.MAVLINK_MSG_ID_ATTITUDE: 10.0,
            D.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 10.0,
            D.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
            D.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
            D.MAVLINK_MSG_ID_SKELETON_EXTERNAL_WRENCH: rates.wrench_hz,
            D.MAVLINK_MSG_ID_HOME_POSITION: 0.5,  # as PX4's onboard mode (a client that asked too early gets it)
        }
    return {
        D.MAVLINK_MSG_ID_ATTITUDE: 10.0,
        D.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 5.0,
        D.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
        D.MAVLINK_MSG_ID_DEBUG_VECT: 5.0,  # PSPM's reservoirs (nothing is sent while PSPM is off)
        # the link's state and covariance, for a ground station with the dialect (SET_MESSAGE_INTERVAL: faster)
        D.MAVLINK_MSG_ID_SKELETON_LINK_STATE: 1.0,
        D.MAVLINK_MSG_ID_HOME_POSITION: 0.5,  # as PX4 streams it (nothing until the home is set)
    }


class Streams:
    """Every link's streams (``Endpoint.streams``) of ``vehicle``: set to their defaults, changed
    by SET_MESSAGE_INTERVAL and the rate parameters, and sent on the ticks they are due, each
    link's messages of one tick together (one UDP datagram). The vehicle is what the builders
    read: its firmware, its flight-controller time, its origin and links."""

    def __init__(self, vehicle):
        self.vehicle = vehicle
        #: the earliest time [us] a stream is due (0: look at every one on the next tick)
        self.due_us = 0
        self._tick_us = -1  # no tick yet: tick_values computes on first use
        self._tick = None

    def defaults(self, endpoint: int) -> dict[int, float]:
        """Message id -> default rate [Hz] of endpoint 0 (onboard) or 1 (GCS), the parameters' rates."""
        return default_rates(self.vehicle.params.rates(), endpoint)

    def set_defaults(self) -> None:
        for k, ep in enumerate(self.vehicle.endpoints):
            ep.streams = {mid: Stream.at_rate(hz) for mid, hz in self.defaults(k).items() if hz > 0}
        self.due_us = 0

    def set_interval(self, ep, mid: int, interval_us: float) -> bool:
        """SET_MESSAGE_INTERVAL on link ``ep``: message ``mid`` every ``interval_us`` from the next
        multiple of it (0: its default rate, negative: off). ``False`` (nothing changed) for a
        message that is not a stream."""
        if mid not in BUILDERS or mid in UNSTREAMED:
            return False
        if interval_us == 0:  # the default rate (MAVLink semantics)
            hz = self.defaults(self.vehicle.endpoints.index(ep)).get(mid, 0.0)
            interval_us = 1e6 / hz if hz > 0 else -1
        if interval_us < 0:
            ep.streams.pop(mid, None)
        else:
            ep.streams[mid] = Stream.every(int(round(interval_us)), self.vehicle.fc_time_us)
        self.due_us = 0
        return True

    def reset_onboard_rates(self) -> None:
        """The onboard link's streams of the rate parameters restarted at their parameters' rates."""
        defaults = self.defaults(0)
        streams = self.vehicle.endpoints[0].streams
        for mid in (D.MAVLINK_MSG_ID_SKELETON_LINK_STATE, D.MAVLINK_MSG_ID_ODOMETRY,
                    D.MAVLINK_MSG_ID_SKELETON_EXTERNAL_WRENCH):
            hz = defaults[mid]
            if hz > 0:
                streams[mid] = Stream.at_rate(hz, self.vehicle.fc_time_us)
            else:
                streams.pop(mid, None)
        self.due_us = 0

    def send_due(self) -> None:
        """Every stream whose time has come; ticks before the earliest one due return at once."""
        v = self.vehicle
        t = v.fc_time_us
        if t < self.due_us:
            return
        due = math.inf
        for ep in v.endpoints:
            msgs = []  # one link's messages due on this tick leave together (one UDP datagram)
            for mid, stream in ep.streams.items():
                if t >= stream.next_us:
                    msg = BUILDERS[mid](v)
                    if msg is not None:
                        msgs.append(msg)
                    stream.next_us = max(stream.next_us + stream.interval_us, t)
                due = min(due, stream.next_us)
            if msgs:
                ep.port.send_many(msgs)
        self.due_us = due

    def tick_values(self):
        """(control estimate, state report) of the current tick, computed once for all streams."""
        v = self.vehicle
        if self._tick_us != v.fc_time_us:
            self._tick_us = v.fc_time_us
            self._tick = (v.fw.control_estimate(v.fc_time_s), v.fw.state_report())
        return self._tick

    def estimate(self):
        """The control estimate ``(p, v, q)`` of the current tick."""
        return self.tick_values()[0]

    def report(self):
        """The firmware's state report of the current tick."""
        return self.tick_values()[1]

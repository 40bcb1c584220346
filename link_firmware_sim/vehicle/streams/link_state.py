"""The EKF's estimate with its covariance, for the companion: SKELETON_LINK_STATE (the dialect's,
with the firmware's flags, EKF resets and the last correction's sequence number and latency) or,
with standard messages only, ODOMETRY."""

from __future__ import annotations

from companion.mavlink.codec import encode_link_state, usec
from companion.mavlink.dialect import load_dialect
from companion.mavlink.standard import encode_odometry

__all__ = ["link_state", "odometry"]

D = load_dialect()


def link_state(v):
    fw = v.fw
    return encode_link_state(v.streams.report(), fw.flags(v.fc_time_s), fw.ekf.resets, fw.correction_seq,
                             fw.correction_latency_us)


def odometry(v):
    """Raw EKF output with its variances, as a stock PX4 publishes it (standard messages: velocity
    in the local frame, the covariances' diagonals only)."""
    st = v.streams.report()
    return encode_odometry(st, usec(st.time_s), estimator_type=D.MAV_ESTIMATOR_TYPE_AUTOPILOT, px4=True)

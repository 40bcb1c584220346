"""The vehicle's telemetry streams on flight-controller time, one module per family of messages
(PX4's mavlink ``streams/``): which message each id builds, at what rate and when it is due
(:mod:`.schedule`); the vehicle's identity, health and clock (:mod:`.system`: HEARTBEAT, SYS_STATUS,
AUTOPILOT_VERSION, SYSTEM_TIME); the pose estimate in standard messages (:mod:`.position`: ATTITUDE,
LOCAL_POSITION_NED, GLOBAL_POSITION_INT, GPS_GLOBAL_ORIGIN); the estimate with its covariance for
the companion (:mod:`.link_state`: SKELETON_LINK_STATE, ODOMETRY); the controllers' reports
(:mod:`.controller`: SKELETON_EXTERNAL_WRENCH, DEBUG_VECT ``PSPM``).

A builder is a function of the vehicle that returns the message, or ``None`` when there is
nothing to send (a stream of a controller that is not running sends nothing).
"""

"""The vehicle's identity, health and clock: HEARTBEAT, SYS_STATUS, AUTOPILOT_VERSION, SYSTEM_TIME."""

from __future__ import annotations

from companion.mavlink.dialect import load_dialect

from ..hil import sitl_gps_time_us

__all__ = ["heartbeat", "sys_status", "autopilot_version", "system_time"]

D = load_dialect()
_PX4_OFFBOARD = 6 << 16  # PX4 custom_mode: main mode OFFBOARD
_FLIGHT_SW_VERSION = (0 << 24) | (1 << 16) | (0 << 8) | 255  # 0.1.0 (release)
_CAPABILITIES = (
    D.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | D.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | D.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | D.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | D.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
)
_SENSORS = (D.MAV_SYS_STATUS_SENSOR_3D_GYRO | D.MAV_SYS_STATUS_SENSOR_3D_ACCEL | D.MAV_SYS_STATUS_SENSOR_3D_MAG
            | D.MAV_SYS_STATUS_SENSOR_GPS | D.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
            | D.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION | D.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
            | D.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL | D.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            | D.MAV_SYS_STATUS_PREARM_CHECK)


def heartbeat(v):
    base = D.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (D.MAV_MODE_FLAG_SAFETY_ARMED if v.fw.armed else 0)
    status = D.MAV_STATE_ACTIVE if v.fw.armed else D.MAV_STATE_STANDBY
    # A PX4-style autopilot (PX4's parameter encoding, names, ports, failsafes and signing): the
    # stock tools pick the parameter encoding from this field (MAVProxy and QGroundControl decode
    # bytewise only for MAV_AUTOPILOT_PX4, MAVSDK casts only for ArduPilot). Custom mode: PX4's
    # OFFBOARD (main mode 6), what the link flies in: the companion's targets.
    return D.MAVLink_heartbeat_message(D.MAV_TYPE_OCTOROTOR, D.MAV_AUTOPILOT_PX4, base, _PX4_OFFBOARD, status, 3)


def sys_status(v):
    """The sensors present, enabled and healthy (GPS unhealthy while the EKF has no fix or the
    firmware reports a GPS fault; the gyro or the accelerometer while it is stale; the pre-arm
    check, PX4's "armable", healthy once arming would be accepted: the EKF runs), and the frames
    the links dropped."""
    gps_ok = v.fw.initialized and not v.fw.gps_health.fault
    health = _SENSORS if gps_ok else _SENSORS & ~D.MAV_SYS_STATUS_SENSOR_GPS
    if not v.fw.initialized:
        health &= ~D.MAV_SYS_STATUS_PREARM_CHECK
    if v.fw.imu_health.gyro.stale:
        health &= ~D.MAV_SYS_STATUS_SENSOR_3D_GYRO
    if v.fw.imu_health.accel.stale:
        health &= ~D.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    health |= D.MAV_SYS_STATUS_GEOFENCE  # no fence, so none breached (a ground station reads 0 as a breach)
    dropped = sum(ep.port.stats.dropped for ep in v.endpoints)
    return D.MAVLink_sys_status_message(_SENSORS, _SENSORS, health, 0, 16200, -1, 100, 0, min(dropped, 65535),
                                        0, 0, 0, 0)


def autopilot_version(v):
    return D.MAVLink_autopilot_version_message(
        _CAPABILITIES, _FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0x1209, 0x5A4B, v.system_id,
    )


def system_time(v):
    """GPS time (0 until the EKF has its first fix) against boot time, as PX4 sends it; in SITL
    the simulated GPS's clock is :func:`~link_firmware_sim.vehicle.hil.sitl_gps_time_us` of
    simulation time."""
    unix_us = sitl_gps_time_us(v.fc_time_us) if v.fw.initialized else 0
    return D.MAVLink_system_time_message(unix_us, v.time_boot_ms)

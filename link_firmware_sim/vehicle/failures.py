"""Injected failures of one vehicle (MAV_CMD_INJECT_FAILURE, as PX4's simulator applies them):
which unit and instance fails how, and the sensor samples and rotor commands as that makes them.

Pure: no sockets, no clock; :mod:`.commands` parses and applies the command
(:func:`parse_failure`, :meth:`FailureInjector.inject`), :mod:`.lockstep` passes every sample that
enters the firmware through the filters (:meth:`~FailureInjector.gps`,
:meth:`~FailureInjector.imu`, :meth:`~FailureInjector.thrust`).

What is supported (anything else: :meth:`~FailureInjector.inject` returns ``None``, the command is
MAV_RESULT_UNSUPPORTED):

* FAILURE_UNIT_SENSOR_GPS: ``ok`` (cleared), ``off`` (no fix reaches the firmware), ``stuck`` (the
  last fix before the failure repeated, position and velocity, at each new fix's time), ``wrong``
  (every fix's position moved by :data:`GPS_WRONG_OFFSET_ENU_M`, 50 m east; velocity unchanged);
* FAILURE_UNIT_SENSOR_GYRO / FAILURE_UNIT_SENSOR_ACCEL: ``ok``, ``stuck`` (the first sample after
  the failure held), ``garbage`` (white noise of :data:`GYRO_GARBAGE_STD_RAD_S` /
  :data:`ACCEL_GARBAGE_STD_M_S2` per axis added). Not ``off``: the IMU sample is the lockstep tick
  itself, the firmware has no clock without it;
* FAILURE_UNIT_SYSTEM_MOTOR: ``ok``, ``off`` (that rotor's thrust zero: the motor stops, and its
  ESC's telemetry, the thrust :meth:`~FailureInjector.thrust` returns, says so; the firmware finds
  it failed from that, :mod:`link_firmware_sim.motor_failure`);
* FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL: ``ok``, ``off`` (the onboard link to the companion goes
  dead both ways: nothing sent on it, whatever arrives on it dropped, each counted; the
  ground-station link stays up, so a ground station can clear it). :class:`SeveredTransport` is
  what the vehicle puts under that link's port meanwhile.

Instance 0 is every instance of the unit (one GPS, one gyro, one accelerometer, ``n_motors``
motors numbered from 1), as on PX4; an instance the vehicle does not have is unsupported.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

__all__ = ["GPS", "GYRO", "ACCEL", "MOTOR", "MAVLINK", "OK", "OFF", "STUCK", "GARBAGE", "WRONG", "GPS_WRONG_OFFSET_ENU_M",
           "GYRO_GARBAGE_STD_RAD_S", "ACCEL_GARBAGE_STD_M_S2", "UNIT_NAMES", "TYPE_NAMES", "parse_failure",
           "FailureInjector", "SeveredTransport"]

# FAILURE_UNIT and FAILURE_TYPE of MAVLink's common.xml
GYRO, ACCEL, GPS, MOTOR, MAVLINK = 0, 1, 4, 101, 105
OK, OFF, STUCK, GARBAGE, WRONG = 0, 1, 2, 3, 4
UNIT_NAMES = {GYRO: "gyro", ACCEL: "accel", GPS: "gps", MOTOR: "motor", MAVLINK: "mavlink_signal"}
TYPE_NAMES = {OK: "ok", OFF: "off", STUCK: "stuck", GARBAGE: "garbage", WRONG: "wrong"}
#: the failure types each unit supports
SUPPORTED = {GPS: {OK, OFF, STUCK, WRONG}, GYRO: {OK, STUCK, GARBAGE}, ACCEL: {OK, STUCK, GARBAGE}, MOTOR: {OK, OFF},
             MAVLINK: {OK, OFF}}

#: a ``wrong`` GPS's position offset, world ENU [m]
GPS_WRONG_OFFSET_ENU_M = np.array([50.0, 0.0, 0.0])
#: a ``garbage`` gyro's and accelerometer's noise, standard deviation per axis
GYRO_GARBAGE_STD_RAD_S = 0.5
ACCEL_GARBAGE_STD_M_S2 = 5.0
#: the largest unit, type or instance number a command may carry (all are small enums)
_PARAM_MAX = 255


def parse_failure(param1: float, param2: float, param3: float) -> tuple[int, int, int]:
    """MAV_CMD_INJECT_FAILURE's ``(unit, type, instance)`` from its params 1-3, rounded to the
    nearest integer as PX4 reads them; ``ValueError`` when one is not finite or outside
    ``[0, 255]``."""
    out = []
    for name, value in (("unit", param1), ("type", param2), ("instance", param3)):
        value = float(value)
        if not math.isfinite(value) or not -0.5 < value < _PARAM_MAX + 0.5:
            raise ValueError(f"failure {name} {value!r}: not a number in [0, {_PARAM_MAX}]")
        out.append(int(round(value)))
    return out[0], out[1], out[2]


class FailureInjector:
    """The failures injected into one vehicle, per ``(unit, instance)`` (instances from 1), and
    how many samples or commands each unit's failures changed (:attr:`changed`)."""

    def __init__(self, n_motors: int = 8, seed: int = 0):
        self.instances = {GPS: 1, GYRO: 1, ACCEL: 1, MOTOR: n_motors, MAVLINK: 1}
        #: ``(unit, instance) -> failure type`` of every failure in effect
        self.active: dict[tuple[int, int], int] = {}
        #: samples dropped or altered (rotor commands zeroed) so far, by unit name
        self.changed: Counter[str] = Counter()
        self.injected = 0
        self._last_gps: tuple[np.ndarray, np.ndarray] | None = None
        self._held: dict[int, object] = {}  # a stuck unit's held sample (None: the next one)
        self._rng = np.random.default_rng(seed)

    # -- the command ---------------------------------------------------------------------------
    def inject(self, unit: int, ftype: int, instance: int) -> str | None:
        """Apply a failure (``OK``: clear it) to ``instance`` of ``unit`` (0: every instance);
        returns its description for the operator (``"gps off"``, ``"motor 3 off"``), ``None``
        (nothing changed) when the unit, the type or the instance is not supported."""
        if ftype not in SUPPORTED.get(unit, ()) or not 0 <= instance <= self.instances[unit]:
            return None
        targets = range(1, self.instances[unit] + 1) if instance == 0 else (instance,)
        for k in targets:
            if ftype == OK:
                self.active.pop((unit, k), None)
            else:
                self.active[(unit, k)] = ftype
        if ftype == STUCK:
            self._held[unit] = self._last_gps if unit == GPS else None
        else:
            self._held.pop(unit, None)
        self.injected += 1
        name = UNIT_NAMES[unit] + (f" {instance}" if instance and self.instances[unit] > 1 else "")
        return f"{name} {TYPE_NAMES[ftype]}"

    def failure(self, unit: int, instance: int = 1) -> int:
        """The failure type in effect for ``instance`` of ``unit`` (``OK``: none)."""
        return self.active.get((unit, instance), OK)

    @property
    def imu_or_motor(self) -> bool:
        """A gyro, accelerometer or motor failure is in effect: the ticks must go through
        :meth:`imu` and :meth:`thrust` (the compiled lockstep paths do not)."""
        return any(unit not in (GPS, MAVLINK) for unit, _ in self.active)

    @property
    def link_off(self) -> bool:
        """The onboard link's MAVLink signal is off."""
        return self.failure(MAVLINK) == OFF

    # -- the samples ---------------------------------------------------------------------------
    def gps(self, pos_w_m, vel_w_m_s) -> tuple[np.ndarray, np.ndarray] | None:
        """A GPS fix (world ENU position [m] and velocity [m/s]) as the failure makes it; ``None``:
        no fix reaches the firmware."""
        ftype = self.failure(GPS)
        if ftype == OK:
            self._last_gps = (pos_w_m, vel_w_m_s)
            return pos_w_m, vel_w_m_s
        self.changed["gps"] += 1
        if ftype == OFF:
            return None
        if ftype == STUCK:
            if self._held.get(GPS) is None:
                self._held[GPS] = (pos_w_m, vel_w_m_s)
            return self._held[GPS]
        return np.asarray(pos_w_m, dtype=float) + GPS_WRONG_OFFSET_ENU_M, vel_w_m_s  # WRONG

    def imu(self, gyro_b_rad_s, accel_b_m_s2) -> tuple[np.ndarray, np.ndarray]:
        """An IMU sample (body gyro [rad/s], accelerometer [m/s^2]) as the failures make it."""
        gyro = self._imu_axis(GYRO, gyro_b_rad_s, GYRO_GARBAGE_STD_RAD_S)
        accel = self._imu_axis(ACCEL, accel_b_m_s2, ACCEL_GARBAGE_STD_M_S2)
        return gyro, accel

    def _imu_axis(self, unit: int, sample, std: float):
        ftype = self.failure(unit)
        if ftype == OK:
            return sample
        self.changed[UNIT_NAMES[unit]] += 1
        if ftype == STUCK:
            if self._held.get(unit) is None:
                self._held[unit] = np.array(sample, dtype=float)
            return self._held[unit]
        return np.asarray(sample, dtype=float) + self._rng.normal(0.0, std, 3)  # GARBAGE

    def thrust(self, thrust_n) -> np.ndarray:
        """Rotor thrust commands [N] with the failed motors' zeroed (a copy when any is)."""
        off = [k - 1 for (unit, k), ftype in self.active.items() if unit == MOTOR and ftype == OFF]
        if not off:
            return thrust_n
        out = np.array(thrust_n, dtype=float)
        out[[k for k in off if k < out.size]] = 0.0
        self.changed["motor"] += 1
        return out

    def report(self) -> dict:
        """What the vehicle's stats show: the failures in effect, the commands applied, the samples changed."""
        return {"active": sorted(f"{UNIT_NAMES[u]} {k} {TYPE_NAMES[t]}" for (u, k), t in self.active.items()),
                "injected": self.injected, "changed": dict(self.changed)}


class SeveredTransport:
    """A MAVLink port's transport with its signal off: ``inner``'s socket stays open (and is
    drained), nothing is sent on it and nothing it receives is handed on; each write dropped and
    each read drained counts one in ``counts["mavlink_signal"]`` (the failure filter's
    :attr:`FailureInjector.changed`)."""

    def __init__(self, inner, counts: Counter):
        self.inner = inner
        self.counts = counts

    def send(self, data: bytes) -> None:
        self.counts["mavlink_signal"] += 1

    def recv_chunks(self) -> list:
        if self.inner.recv_chunks():
            self.counts["mavlink_signal"] += 1
        return []

    def __getattr__(self, name):  # fileno, datagram, connected, close ...: the socket's own
        return getattr(self.inner, name)

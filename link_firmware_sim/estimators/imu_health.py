"""Is an IMU sensor still alive? A stuck sensor repeats one sample exactly (pure).

A MEMS gyro or accelerometer always reads some noise: the same sample, bit for bit, for a while
means the sensor (or its bus) stopped and something repeats its last value. PX4 flags such a
sensor stale (its ``DataValidator`` counts equal samples) and stops using it. :class:`StaleSensor`
does the same on one sensor's samples: stale once the sample has not changed for ``stale_s`` of
the caller's time (the caller may see one sample per tick or one per batch of ticks, as the
compiled lockstep loop returns); alive again at the first sample that differs. Each transition is
a :class:`~link_firmware_sim.events.StatusEvent` for the shell to report.

:class:`ImuHealth` watches the gyro and the accelerometer and gives what stands in for a stale
one: the body rate of the rigid body under the commanded torque, corrected by the attitude
references (:class:`~.stale_rate.StaleGyroRate`); for a stale accelerometer the firmware takes the
specific force of the thrust the rotors were commanded (what an accelerometer reads, drag aside).
"""

from __future__ import annotations

import numpy as np

from ..events import StatusEvent
from .stale_rate import StaleGyroRate

__all__ = ["STALE_S", "StaleSensor", "ImuHealth"]

#: a sample unchanged this long [s] is a stuck sensor (PX4: 100 equal samples at its rate)
STALE_S = 0.2


class StaleSensor:
    """One sensor's staleness (see the module docstring); ``name`` for the reports."""

    def __init__(self, name: str, stale_s: float = STALE_S):
        if not stale_s > 0.0:
            raise ValueError(f"stale_s must be positive, got {stale_s!r}")
        self.name = name
        self.stale_s = stale_s
        self._last: tuple | None = None
        self._since_s = 0.0
        self.stale = False
        #: times it went stale, and for how long in all [s]
        self.episodes = 0
        self.stale_time_s = 0.0
        self._stale_at_s = 0.0

    def on_sample(self, t_s: float, sample) -> list[StatusEvent]:
        """A sample at ``t_s``; the transition it causes, if any."""
        s = tuple(np.asarray(sample, dtype=float).ravel().tolist())  # (NaN equals nothing, as in numpy)
        same = s == self._last
        if not same:
            self._last = s
            self._since_s = t_s
            if self.stale:
                self.stale = False
                self.stale_time_s += t_s - self._stale_at_s
                return [StatusEvent("recovered", f"{self.name} ok again after {t_s - self._stale_at_s:.1f} s"[:50])]
            return []
        if not self.stale and t_s - self._since_s >= self.stale_s:
            self.stale = True
            self.episodes += 1
            self._stale_at_s = t_s
            return [StatusEvent("fault", f"{self.name} stale: no change for {self.stale_s:g} s"[:50])]
        return []

    def stop(self, t_s: float) -> None:
        """Stop watching at ``t_s`` (a stale episode going on ends there, unreported); the next
        sample starts afresh."""
        if self.stale:
            self.stale_time_s += t_s - self._stale_at_s
        self.stale = False
        self._last = None

    def report(self, t_s: float) -> dict:
        return {"episodes": self.episodes, "stale_now": self.stale,
                "stale_s": round(self.stale_time_s + (t_s - self._stale_at_s if self.stale else 0.0), 3)}


class ImuHealth:
    """The gyro's and the accelerometer's staleness (:attr:`gyro`, :attr:`accel`) on the newest
    tick's samples (:meth:`sample`), shown to them on the shell's grid (:meth:`watch`), and what
    stands in for a stale gyro: the rate of :attr:`rate` (:meth:`stale_rate`,
    :meth:`on_attitude_reference`)."""

    def __init__(self, rate: StaleGyroRate, stale_s: float = STALE_S):
        self.gyro = StaleSensor("Gyro", stale_s)
        self.accel = StaleSensor("Accel", stale_s)
        self.gyro_sample = np.zeros(3)  # the newest tick's samples, as they came
        self.accel_sample = np.zeros(3)
        self.rate = rate

    @property
    def stale(self) -> bool:
        """Either sensor stale."""
        return self.gyro.stale or self.accel.stale

    def sample(self, gyro_b_rad_s, accel_b_m_s2) -> None:
        self.gyro_sample, self.accel_sample = gyro_b_rad_s, accel_b_m_s2

    def watch(self, t_s: float) -> list[StatusEvent]:
        """The newest samples to both watches at ``t_s``: the transitions (a gyro alive again
        stops its stand-in, whichever path the next ticks take)."""
        events = self.gyro.on_sample(t_s, self.gyro_sample) + self.accel.on_sample(t_s, self.accel_sample)
        if not self.gyro.stale:
            self.rate.stop()
        return events

    def stop(self, t_s: float) -> None:
        self.gyro.stop(t_s)
        self.accel.stop(t_s)
        self.rate.stop()

    def stale_rate(self, q_wxyz, torque_cmd_b_nm, dt_s: float) -> np.ndarray:
        """A tick with the gyro stale: the body rate [rad/s] after ``dt_s`` under the commanded
        torque [N m] (the observer started at the first such tick, from the attitude estimate
        ``q_wxyz``)."""
        if not self.rate.running:
            self.rate.start(q_wxyz, torque_cmd_b_nm)
        return self.rate.predict(torque_cmd_b_nm, dt_s)

    def on_attitude_reference(self, q_wxyz) -> None:
        """An attitude reference: it corrects the stale gyro's stand-in, if one runs."""
        if self.rate.running:
            self.rate.update(q_wxyz)

    def report(self, t_s: float) -> dict:
        """``gyro`` and ``accel``: each sensor's :meth:`StaleSensor.report`."""
        return {"gyro": self.gyro.report(t_s), "accel": self.accel.report(t_s)}

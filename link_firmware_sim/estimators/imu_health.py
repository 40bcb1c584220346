"""Is an IMU sensor still alive? A stuck sensor repeats one sample exactly (pure).

A MEMS gyro or accelerometer always reads some noise: the same sample, bit for bit, for a while
means the sensor (or its bus) stopped and something repeats its last value. PX4 flags such a
sensor stale (its ``DataValidator`` counts equal samples) and stops using it. :class:`StaleSensor`
does the same on one sensor's samples: stale once the sample has not changed for ``stale_s`` of
the caller's time (the caller may see one sample per tick or one per batch of ticks, as the
compiled lockstep loop returns); alive again at the first sample that differs. Each transition is
a :class:`~link_firmware_sim.events.StatusEvent` for the shell to report.

:class:`ImuHealth` watches the gyro and the accelerometer and gives what stands in for a stale
one: the body rate from the change of the attitude estimate (low-passed), and the specific force
of the thrust the rotors were commanded (what an accelerometer reads, drag aside).
"""

from __future__ import annotations

import numpy as np

from companion.estimation.so3 import quat_conj, quat_mul, quat_to_rotvec

from ..events import StatusEvent

__all__ = ["STALE_S", "STALE_RATE_TAU_S", "StaleSensor", "ImuHealth"]

#: a sample unchanged this long [s] is a stuck sensor (PX4: 100 equal samples at its rate)
STALE_S = 0.2
#: the low-pass time constant of the body rate taken from the attitude estimate while the gyro is
#: stale [s]
STALE_RATE_TAU_S = 0.05


class StaleSensor:
    """One sensor's staleness (see the module docstring); ``name`` for the reports."""

    def __init__(self, name: str, stale_s: float = STALE_S):
        if not stale_s > 0.0:
            raise ValueError(f"stale_s must be positive, got {stale_s!r}")
        self.name = name
        self.stale_s = stale_s
        self._last: np.ndarray | None = None
        self._since_s = 0.0
        self.stale = False
        #: times it went stale, and for how long in all [s]
        self.episodes = 0
        self.stale_time_s = 0.0
        self._stale_at_s = 0.0

    def on_sample(self, t_s: float, sample) -> list[StatusEvent]:
        """A sample at ``t_s``; the transition it causes, if any."""
        s = np.asarray(sample, dtype=float)
        same = self._last is not None and np.array_equal(s, self._last)
        if not same:
            self._last = s.copy()
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
    stands in for a stale one (:meth:`rate_from_attitude`, :meth:`thrust_specific_force`)."""

    def __init__(self, stale_s: float = STALE_S):
        self.gyro = StaleSensor("Gyro", stale_s)
        self.accel = StaleSensor("Accel", stale_s)
        self.gyro_sample = np.zeros(3)  # the newest tick's samples, as they came
        self.accel_sample = np.zeros(3)
        self._q_prev: np.ndarray | None = None
        self.rate_lp = np.zeros(3)

    @property
    def stale(self) -> bool:
        """Either sensor stale."""
        return self.gyro.stale or self.accel.stale

    def sample(self, gyro_b_rad_s, accel_b_m_s2) -> None:
        self.gyro_sample, self.accel_sample = gyro_b_rad_s, accel_b_m_s2

    def watch(self, t_s: float) -> list[StatusEvent]:
        """The newest samples to both watches at ``t_s``: the transitions."""
        return self.gyro.on_sample(t_s, self.gyro_sample) + self.accel.on_sample(t_s, self.accel_sample)

    def stop(self, t_s: float) -> None:
        self.gyro.stop(t_s)
        self.accel.stop(t_s)

    def rate_from_attitude(self, q_wxyz: np.ndarray, dt_s: float) -> np.ndarray:
        """The body rate from the change of the attitude estimate since the last call, low-passed
        over :data:`STALE_RATE_TAU_S` (what damps the attitude loop while the gyro is stale)."""
        prev, self._q_prev = self._q_prev, np.array(q_wxyz, dtype=float)
        if prev is None:
            self.rate_lp = np.zeros(3)
            return self.rate_lp
        raw = quat_to_rotvec(quat_mul(quat_conj(prev), self._q_prev)) / dt_s  # body frame
        self.rate_lp = self.rate_lp + dt_s / (STALE_RATE_TAU_S + dt_s) * (raw - self.rate_lp)
        return self.rate_lp

    def gyro_used(self) -> None:
        """A tick that used the gyro: the attitude's rate starts afresh at the next stale one."""
        self._q_prev = None

    @staticmethod
    def thrust_specific_force(mapping_matrix: np.ndarray, command_n: np.ndarray, mass_kg: float) -> np.ndarray:
        """The specific force [m/s^2] (body frame) of thrusts ``command_n`` through the rotors'
        mapping matrix (their force over the link's mass: what an accelerometer reads in flight,
        drag and the rotors' lag aside)."""
        return (np.asarray(mapping_matrix) @ np.asarray(command_n, dtype=float))[:3] / mass_kg

    def report(self, t_s: float) -> dict:
        """``gyro`` and ``accel``: each sensor's :meth:`StaleSensor.report`."""
        return {"gyro": self.gyro.report(t_s), "accel": self.accel.report(t_s)}

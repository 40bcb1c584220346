"""GPS health of one link's firmware (pure: times are passed in).

The EKF's innovation gate rejects a position fix that disagrees with the estimate (a multipath
jump, a drifting or spoofed solution); :class:`GpsHealth` turns the stream of accepted and
rejected fixes into a fault state, as PX4's EKF2 does with its GNSS checks:

* **fault** when a fix was rejected, when the fixes repeat bit for bit in flight for ``stuck_s``
  (a receiver or a bus that repeats its last fix: no real fix is ever exactly the last one, as
  PX4's ``DataValidator`` counts equal samples; watched in flight only: a still link on the
  ground of a noiseless simulation repeats its fixes honestly), when the fixes drift against the
  GPS's own velocity (over
  the last ``drift_window_s`` the horizontal positions move away from the track integrated
  from the reported velocities faster than ``drift_max_m_s``: a slow ramp that the gate would
  let in, as spoofing and multipath drift do), or when no fix arrived for ``timeout_s`` (an
  outage).
  While the fault lasts the EKF fuses no GPS position (the fixes are only tested against it):
  the estimate rides on the IMU, the GPS velocity and the companion's chain correction;
* **recovered** once fixes have been accepted again for ``recover_s`` without a rejection;
* **reset** when the position fixes have been rejected for ``reset_s`` while nothing else aided
  the estimate (no companion correction active): the EKF's position is reset to the GPS, as
  EKF2 resets to GNSS after its fusion timeout (``reset_timeout_max``) when GNSS is the only
  horizontal aiding source. The estimate jumps; the reset is counted and reported.

Each transition is returned as a :class:`~link_firmware_sim.events.StatusEvent` for the shell to
report (STATUSTEXT).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.configfile import require_nonnegative, require_positive

from ..events import StatusEvent
from .imu_health import StaleSensor

__all__ = ["GpsHealthConfig", "GpsHealth", "FULL_WINDOW"]

#: the consistency test runs once its fixes span this fraction of ``drift_window_s``: a shorter
#: span's slope is noisier (white position noise: as the span to the power -1.5), and half a
#: window raised false faults at start-up (hovering receivers, 200 seeds x 7 links: 20 tests over
#: the outdoor receiver's 0.5 m/s in the first 2.5 s, none later and none with 0.8 of the window)
FULL_WINDOW = 0.8


@dataclass(frozen=True)
class GpsHealthConfig:
    """``timeout_s``: no fix for this long is a fault (SKL_GPS_TOUT); ``recover_s``: accepted
    fixes for this long clear it (SKL_GPS_RECOV); ``reset_s``: rejected this long with no other
    aiding resets the position to GPS (SKL_GPS_RST_T; EKF2's reset_timeout_max is 7 s);
    ``drift_max_m_s`` / ``drift_window_s``: the position-velocity consistency test
    (SKL_GPS_DRIFT; the outdoor profile's slow GPS drift moves at most about 0.3 m/s, the
    window's slope noise is about 0.06 m/s); ``aid_std_m``: while in fault, the companion's
    corrected position is fused with this standard deviation (SKL_GPS_AID; 0: never,
    :mod:`.correction_aid`); ``aid_reset_s``: while in fault, corrections refused for their
    bound this long in a row reset the position and velocity to the corrected ones
    (SKL_GPS_AID_RST); ``stuck_s``: a fix repeated bit for bit this long in flight is stuck and
    rejected (SKL_GPS_STUCK; 0: never)."""

    timeout_s: float = 1.0
    recover_s: float = 2.0
    reset_s: float = 7.0
    drift_max_m_s: float = 0.5
    drift_window_s: float = 2.0
    aid_std_m: float = 0.2
    aid_reset_s: float = 0.5
    stuck_s: float = 0.5

    def __post_init__(self) -> None:
        require_positive(self, "timeout_s", "reset_s", "drift_max_m_s", "drift_window_s", "aid_reset_s")
        require_nonnegative(self, "recover_s", "aid_std_m", "stuck_s")


class GpsHealth:
    """See the module docstring; feed it every fix (:meth:`on_fix`) and every tick (:meth:`on_tick`)."""

    def __init__(self, config: GpsHealthConfig = GpsHealthConfig(), t0_s: float = 0.0):
        self.config = config
        self.fault = False
        self.reason = ""
        self.last_fix_s = t0_s
        self.rejecting_since_s: float | None = None  # first rejection of the current run
        self.accepting_since_s: float | None = t0_s
        self.faults = 0
        self.resets = 0
        self.rejected = 0
        self.fault_time_s = 0.0
        self._fault_since_s = 0.0
        # the recent fixes' times, horizontal positions and horizontal velocities: rows lo:hi of
        # buffers kept from fix to fix (the test reads them as arrays, not rebuilt per fix)
        self._t = np.empty(32)
        self._p = np.empty((32, 2))
        self._v = np.empty((32, 2))
        self._lo = self._hi = 0
        self.drift_m_s = 0.0  # the last consistency test's figure
        #: the fixes' staleness (position and velocity, in flight): episodes and time stuck
        self.stuck = StaleSensor("GPS", max(config.stuck_s, 1e-9))

    def repeats(self, t_s: float, pos_w_m, vel_w_m_s, in_flight: bool) -> bool:
        """Record a fix; ``True`` once the fixes have repeated bit for bit for ``stuck_s`` in
        flight (``in_flight``; on the ground the watch starts afresh). ``stuck_s`` 0: never."""
        watch = self.stuck
        if not (in_flight and self.config.stuck_s > 0.0):
            watch.stop(t_s)
            return False
        watch.stale_s = self.config.stuck_s  # (the parameter may change in flight)
        watch.on_sample(t_s, np.concatenate([np.asarray(pos_w_m, dtype=float), np.asarray(vel_w_m_s, dtype=float)]))
        return watch.stale

    def _raise(self, t_s: float, reason: str, text: str) -> StatusEvent | None:
        if self.fault:
            return None
        self.fault, self.reason = True, reason
        self.faults += 1
        self._fault_since_s = t_s
        return StatusEvent("fault", text)

    def consistent(self, t_s: float, pos_w_m, vel_w_m_s) -> bool:
        """Record a fix; ``False`` if the horizontal positions of the last ``drift_window_s`` (once
        they span :data:`FULL_WINDOW` of it) move away from the reported velocities faster than
        ``drift_max_m_s``: the least-squares slope of the positions less the track the velocities
        integrate to (trapezoids). At a constant velocity that is the positions' slope less the
        velocity; under acceleration the track follows the velocity's changes, which a slope
        against the window's mean velocity would take for drift (0.7 m/s for a link going from
        rest to 9 m/s in 1 s)."""
        self._append(t_s, pos_w_m, vel_w_m_s)
        lo, hi, times = self._lo, self._hi, self._t
        while times[lo] < t_s - self.config.drift_window_s:  # (the newest is never dropped)
            lo += 1
        self._lo = lo
        if hi - lo < 5 or times[hi - 1] - times[lo] < FULL_WINDOW * self.config.drift_window_s:
            return True
        t, p, v = times[lo:hi], self._p[lo:hi], self._v[lo:hi]
        track = np.zeros_like(p)
        np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t)[:, None], axis=0, out=track[1:])
        off = p - track  # constant for positions that follow the velocities
        tc = t - t.mean()
        slope = tc @ (off - off.mean(axis=0)) / (tc @ tc)
        self.drift_m_s = float(np.linalg.norm(slope))
        return self.drift_m_s <= self.config.drift_max_m_s

    def _append(self, t_s: float, pos_w_m, vel_w_m_s) -> None:
        lo, hi = self._lo, self._hi
        if hi == self._t.size:  # full: the window moved to the front, the buffers doubled if it fills them
            n = hi - lo
            size = self._t.size * (2 if n > self._t.size // 2 else 1)
            for name in ("_t", "_p", "_v"):
                old = getattr(self, name)
                new = np.empty((size,) + old.shape[1:])
                new[:n] = old[lo:hi]
                setattr(self, name, new)
            lo, hi = 0, n
        self._t[hi] = t_s
        self._p[hi] = np.asarray(pos_w_m, dtype=float)[:2]
        self._v[hi] = np.asarray(vel_w_m_s, dtype=float)[:2]
        self._lo, self._hi = lo, hi + 1

    def on_fix(self, t_s: float, accepted: bool, aided: bool, why: str = "position fix rejected") -> list[StatusEvent]:
        """One position fix, accepted or rejected (by the EKF's gate, or the consistency test:
        ``why``). ``aided``: a companion correction is active (the estimate has another source).
        A ``reset`` event asks the caller to reset the EKF's position to this fix."""
        out: list[StatusEvent] = []
        self.last_fix_s = t_s
        if accepted:
            self.rejecting_since_s = None
            if self.accepting_since_s is None:
                self.accepting_since_s = t_s
            if self.fault and t_s - self.accepting_since_s >= self.config.recover_s:
                self.fault = False
                self.fault_time_s += t_s - self._fault_since_s
                out.append(StatusEvent("recovered", f"GPS ok again after {t_s - self._fault_since_s:.1f} s"))
            return out
        self.rejected += 1
        self.accepting_since_s = None
        if self.rejecting_since_s is None:
            self.rejecting_since_s = t_s
        ev = self._raise(t_s, "rejected", f"GPS glitch: {why}"[:50])
        if ev is not None:
            out.append(ev)
        if not aided and t_s - self.rejecting_since_s >= self.config.reset_s:
            self.resets += 1
            self.rejecting_since_s = t_s  # a new run starts from the reset
            out.append(StatusEvent("reset", f"GPS rejected {self.config.reset_s:g} s: position reset"))
        return out

    def on_tick(self, t_s: float) -> list[StatusEvent]:
        """The outage check: no fix for ``timeout_s``."""
        if not self.fault and t_s - self.last_fix_s >= self.config.timeout_s:
            self.accepting_since_s = None
            return [ev for ev in [self._raise(t_s, "lost", f"GPS lost: no fix for {self.config.timeout_s:g} s")] if ev]
        if self.fault and self.reason == "lost" and t_s - self.last_fix_s >= self.config.timeout_s:
            self.accepting_since_s = None
        return []

    def fault_seconds(self, t_s: float) -> float:
        """Time spent in the fault state so far."""
        return self.fault_time_s + (t_s - self._fault_since_s if self.fault else 0.0)

    def report(self, t_s: float) -> dict:
        return {"faults": self.faults, "resets": self.resets, "rejected_fixes": self.rejected,
                "stuck": self.stuck.report(t_s),
                "fault_s": round(self.fault_seconds(t_s), 3), "fault_now": self.fault,
                "last_fix_age_s": round(t_s - self.last_fix_s, 3) if math.isfinite(self.last_fix_s) else None}

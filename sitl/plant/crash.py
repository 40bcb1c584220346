"""The crash rule of a flight, in batch and fleet mode alike.

A flight crashes when the simulation diverges or, once the chain has flown (every link clear of
the ground by :data:`TAKEOFF_CLEARANCE_M`) and the take-off window is over, when a link touches the
ground or is more than :data:`CRASH_TILT_DEG` off its target attitude. A chain that never left the
ground has not crashed; a scenario that rests (``trajectory.kind = "rest"``) is not judged.

Batch mode judges every logged tick as it flies (:meth:`CrashWatch.check`). A fleet's harness sees
the truth but not the vehicles' targets: it judges the ground while it flies and the attitudes over
the merged log after the flight (:meth:`CrashWatch.check_logged`); the earlier crash stands.
"""

from __future__ import annotations

import math

import numpy as np

from companion.estimation.so3 import attitude_error

__all__ = ["CrashWatch", "CRASH_TILT_DEG", "TAKEOFF_CLEARANCE_M", "attitude_errors_deg"]

CRASH_TILT_DEG = 60.0
#: height above the crash floor every link must clear once for the chain to count as taken off [m]
TAKEOFF_CLEARANCE_M = 0.2
_COS_HALF_NEAR_CRASH = math.cos(math.radians(CRASH_TILT_DEG - 5.0) / 2.0)  # (CrashWatch.check)


def attitude_errors_deg(q_true: np.ndarray, q_target: np.ndarray) -> np.ndarray:
    """Each link's rotation from its target attitude [deg], (..., n) from (..., n, 4) quaternions;
    NaN where the target is not finite (a link without power or EKF has none)."""
    ok = np.all(np.isfinite(q_target), axis=-1)
    out = np.full(ok.shape, np.nan)
    out[ok] = np.degrees(np.linalg.norm(attitude_error(q_true[ok], q_target[ok]), axis=-1))
    return out


class CrashWatch:
    """The crash rule of scenario ``sc``: whether and when the flight crashed, and why."""

    def __init__(self, sc):
        self.scenario = sc
        #: a link centre lower than this has touched the ground [m]
        self.floor_m = sc.skeleton.bar_radius_m + 0.05
        self.crashed = False
        self.crash_reason = ""
        self.crash_time_s: float | None = None
        #: whether the chain ever flew (every link clear of the ground): a chain that never took off
        #: (nobody armed it) rests on the ground without having crashed
        self.took_off = False

    def judged(self, t):
        """Whether the ground and attitude rules apply at ``t`` (a time or an array of them): after
        the take-off window, in a scenario that flies."""
        sc = self.scenario
        return (t >= sc.flight_start_s) & (sc.trajectory.kind != "rest")

    def check(self, t: float, p_w_m: np.ndarray, q_wxyz: np.ndarray, target_q: np.ndarray | None) -> None:
        """Judge the instant ``t``: link centres ``p_w_m`` (n, 3), attitudes ``q_wxyz`` (n, 4) and
        every link's target attitude ``target_q`` (n, 4; NaN rows: no target; ``None``: not known
        here, as in a fleet's harness)."""
        if self.crashed:
            return
        if not np.all(np.isfinite(p_w_m)):
            self._crash(t, f"simulation diverged at t = {t:.3f} s")
            return
        lowest = p_w_m[:, 2].min()
        if not self.took_off and lowest > self.floor_m + TAKEOFF_CLEARANCE_M:
            self.took_off = True
        if not self.judged(t) or not self.took_off:
            return
        if lowest < self.floor_m:
            self._crash(t, f"link below {self.floor_m:.2f} m at t = {t:.2f} s")
            return
        if target_q is None:
            return
        ok = np.all(np.isfinite(target_q), axis=1)
        # every link's rotation from its target, 2 acos |<q, q_target>|, well inside the limit:
        # no crash (the rotation vectors are worked out only near it)
        if not np.any(np.abs(np.einsum("ij,ij->i", q_wxyz[ok], target_q[ok])) < _COS_HALF_NEAR_CRASH):
            return
        tilt = np.nan_to_num(attitude_errors_deg(q_wxyz, target_q))
        if tilt.max() > CRASH_TILT_DEG:
            self._attitude_crash(t, tilt)

    def check_logged(self, t: np.ndarray, p_w_m: np.ndarray, q_wxyz: np.ndarray, q_target: np.ndarray) -> None:
        """The attitude rule of :meth:`check` over a flight's log: ``t`` (k,) the logged times,
        ``p_w_m`` (k, n, 3) and ``q_wxyz`` (k, n, 4) the truth then, ``q_target`` (k, n, 4) the
        targets. The first judged row, once the chain has flown, with a link more than
        :data:`CRASH_TILT_DEG` off its target is the crash if it comes before the one found so far."""
        t = np.asarray(t, dtype=float)
        if t.size == 0:
            return
        flown = np.maximum.accumulate(p_w_m[:, :, 2].min(axis=1) > self.floor_m + TAKEOFF_CLEARANCE_M)
        rows = flown & self.judged(t)
        if self.crashed and self.crash_time_s is not None:
            rows &= t < self.crash_time_s
        if not np.any(rows):
            return
        tilt = np.nan_to_num(attitude_errors_deg(q_wxyz[rows], q_target[rows]))
        over = np.flatnonzero(tilt.max(axis=1) > CRASH_TILT_DEG)
        if over.size:
            self._attitude_crash(float(t[rows][over[0]]), tilt[over[0]])

    def _attitude_crash(self, t: float, tilt: np.ndarray) -> None:
        self._crash(t, f"attitude error {tilt.max():.0f} deg on link {int(tilt.argmax()) + 1} at t = {t:.2f} s")

    def _crash(self, t: float, reason: str) -> None:
        self.crashed, self.crash_reason, self.crash_time_s = True, reason, t

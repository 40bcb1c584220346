"""While a link's GPS is in fault, the companion's corrected position aids its EKF.

The companion's correction is the chain's view of where the link is; for a link that reports a GPS
fault it is its neighbours' view alone (such a link takes part one way). Control adds the
correction to the EKF's output and, in normal flight, never feeds it to the EKF (paper
sec. III-A). A link without GPS, though, dead-reckons: its EKF drifts and the correction grows
with the drift until the firmware's bound (``correction_max_dp_m``) refuses it and the link flies
on its raw estimate.

So while the GPS is in fault, :class:`CorrectionAid` fuses each correction's position, the EKF's
position plus ``dp``, as an external position of standard deviation ``std_m`` (as PX4's EKF2 fuses
an external vision position), through the EKF's gate. What the update moved is taken off the
correction, so control sees the same estimate at that instant (``EKF' + dp' = EKF + dp``), and
off every later correction computed against a state from before the move (the corrections still
on their way): the EKF stays near where the chain puts the link, and the correction stays small.

A link that was alone for a while (its neighbours unheard) got no corrections and dead-reckoned
past the bound; the corrections that come back are refused. So, as EKF2 resets to a source whose
fusion keeps failing, corrections refused for their position or velocity bound in a row for
``reset_s`` while the GPS is in fault (:meth:`CorrectionAid.refused`) reset the EKF's position and
velocity to the corrected ones; the move is kept like a fused one. The run's corrections must agree
with each other: each corrected position within ``std_m`` of the previous one carried forward by the
two corrected velocities (trapezoid over their states' time). A companion's view of a link moves as
the link does; a source whose corrected positions jump (a glitch, or an unsigned forger who does not
keep a coherent track) restarts the run and is counted (``disagreed``), never reset to.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace

import numpy as np

from companion.messages import Correction

from .ekf_config import X_P, X_V

__all__ = ["CorrectionAid"]

#: how long a move of the EKF is remembered for the corrections computed before it [s]: longer
#: than any correction's way (a correction older than ``correction_stale_s`` no longer counts)
SHIFT_MEMORY_S = 2.0


class CorrectionAid:
    """The moves a fused correction made (time, position, velocity), kept for
    :data:`SHIFT_MEMORY_S` (the EKF counts the updates, fused and gated, as ``ext_pos``).
    ``std_m``: the corrected position's standard deviation per axis [m]; 0 turns the aid off."""

    def __init__(self, std_m: float, reset_s: float = 0.5):
        if not (np.isfinite(std_m) and std_m >= 0.0):
            raise ValueError(f"the correction aid's std_m must be >= 0 (0: off), got {std_m!r}")
        if not (np.isfinite(reset_s) and reset_s > 0.0):
            raise ValueError(f"the correction aid's reset_s must be > 0, got {reset_s!r}")
        self.var_m2 = float(std_m) ** 2
        self.reset_s = float(reset_s)
        self._shifts: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        #: the current run of refused corrections: its first and last EKF time [s], and the last one's
        #: state time [s], corrected position [m] and corrected velocity [m/s]
        self._refused: tuple[float, float, float, np.ndarray, np.ndarray] | None = None
        self.resets = 0
        #: refused corrections whose corrected position disagreed with the run's (the run restarted)
        self.disagreed = 0

    @property
    def enabled(self) -> bool:
        return self.var_m2 > 0.0

    def apply(self, correction: Correction, ekf, t_s: float, gps_fault: bool) -> Correction:
        """What control adds to the EKF's output: ``correction`` rebased (:meth:`rebase`) and,
        while the GPS is in fault (``gps_fault``) and the aid is on, fused into ``ekf`` at its
        time ``t_s`` (:meth:`fuse`; ``ekf`` ``None``: not yet initialised, nothing fused)."""
        correction = self.rebase(correction)
        if self.enabled and ekf is not None and gps_fault:
            correction = self.fuse(ekf, t_s, correction)
        return correction

    def refused(self, correction: Correction, ekf, t_s: float, gps_fault: bool, gap_s: float) -> float | None:
        """A correction refused for its position or velocity bound at the EKF time ``t_s``: once
        such refusals have run for :attr:`reset_s` (no correction accepted between them, none more
        than ``gap_s`` after the last, each one's corrected position agreeing with the last one's:
        :meth:`agrees`) while the GPS is in fault (``gps_fault``) and the aid is on, the EKF's
        position and velocity are reset to the corrected ones (``correction`` rebased): returns the
        position's jump [m]; else ``None`` (still refused)."""
        if not (self.enabled and gps_fault and ekf is not None):
            self._refused = None
            return None
        correction = self.rebase(correction)
        p0, v0 = ekf.x[X_P].copy(), ekf.x[X_V].copy()
        p, v, stamp = p0 + correction.dp_w_m, v0 + correction.dv_w_m_s, correction.ekf_time_s
        run, first = self._refused, t_s
        if run is not None and t_s - run[1] <= gap_s:
            if self.agrees(run[2:], (stamp, p, v)):
                first = run[0]
            else:
                self.disagreed += 1
        self._refused = (first, t_s, stamp, p, v)
        if t_s - first < self.reset_s:
            return None
        ekf.reset_position(p, self.var_m2)
        ekf.reset_velocity(v)
        self._shifts.append((t_s, ekf.x[X_P] - p0, ekf.x[X_V] - v0))
        self._refused = None
        self.resets += 1
        return float(np.linalg.norm(ekf.x[X_P] - p0))

    def agrees(self, last: tuple[float, np.ndarray, np.ndarray], new: tuple[float, np.ndarray, np.ndarray]) -> bool:
        """Whether the corrected position of ``new`` (state time [s], position [m], velocity [m/s])
        is within ``std_m`` of ``last``'s carried forward to its state time by the mean of the two
        velocities; a state not later than the last one's never agrees."""
        (t0, p0, v0), (t1, p1, v1) = last, new
        dt = t1 - t0
        if not dt > 0.0:
            return False
        return float(np.linalg.norm(p1 - (p0 + 0.5 * (v0 + v1) * dt))) <= np.sqrt(self.var_m2)

    def report(self) -> dict:
        return {"resets": self.resets, "disagreed": self.disagreed}

    def accepted(self) -> None:
        """A correction within its bounds: a run of refused ones ends."""
        self._refused = None

    def rebase(self, correction: Correction) -> Correction:
        """``correction`` against the EKF as it is now: less the moves made since the state it was
        computed against (``ekf_time_s``; a move at that same EKF time came after the state was
        reported: states are reported after their tick, corrections fused between ticks)."""
        if not self._shifts:
            return correction
        dp, dv = np.zeros(3), np.zeros(3)
        for t_s, sp, sv in self._shifts:
            if t_s >= correction.ekf_time_s:
                dp += sp
                dv += sv
        if not dp.any() and not dv.any():
            return correction
        return replace(correction, dp_w_m=correction.dp_w_m - dp, dv_w_m_s=correction.dv_w_m_s - dv)

    def fuse(self, ekf, t_s: float, correction: Correction) -> Correction:
        """The corrected position fused into ``ekf`` (a :class:`~.link_ekf.LinkEkf`) at its time
        ``t_s``; returns the correction less what the update moved (``correction`` itself if the gate
        rejected it)."""
        while self._shifts and self._shifts[0][0] < t_s - SHIFT_MEMORY_S:
            self._shifts.popleft()
        p0, v0 = ekf.x[X_P].copy(), ekf.x[X_V].copy()
        if not ekf.update_external_position(p0 + correction.dp_w_m, self.var_m2).accepted:
            return correction
        sp, sv = ekf.x[X_P] - p0, ekf.x[X_V] - v0
        self._shifts.append((t_s, sp, sv))
        return replace(correction, dp_w_m=correction.dp_w_m - sp, dv_w_m_s=correction.dv_w_m_s - sv)

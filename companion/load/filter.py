"""The slung load's pose filter on a time line of vehicle samples and late images (the report's
sec. IV).

Model and measurements: :mod:`.model` (eq. 8 dynamics with estimated cable tensions in the
prediction), :mod:`.measurements` (eq. 4, the marker's attitude, the taut cables' lengths); the
EKF and UKF steps: :mod:`.kalman`. What differs from the report:

* the dynamics are in the prediction, not folded into a control input (the report's eq. 5/7),
  so the EKF (linearised) and the UKF (sigma points through the nonlinear model) are different
  filters and give different numbers;
* the attitude is a quaternion with a 3-d world-frame error (``q = Exp(dtheta) (x) q_hat``),
  not roll-pitch-yaw, and the load's orientation is estimated;
* the filter fuses all it knows: each image's eq. 4 measurement and the load's attitude the
  marker shows (with the vehicle's attitude), then the lengths of the taut cables;
* images may arrive late: :class:`LoadPoseFilter` keeps the processed events of the last
  ``lag_s`` seconds with the estimate after each, rolls back to the last estimate before a late
  image's capture time and replays the later events (re-propagation), so a late image gives the
  same estimate as one that arrived in order;
* chi-square gating of each image (a PnP spike, e.g. P3P's when the marker is small in the
  image, is rejected instead of pulling the estimate);
* an estimate that is no longer finite (the model driven by vehicle positions that contradict the
  cables, with every image rejected, until its numbers overflow) restarts the filter from
  ``restart`` at that event (as EKF2 resets a diverged state), counted in ``stats.restarts``.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .estimate import LoadEstimate, LoadFilterConfig, initial_estimate, with_vehicle_bias
from .kalman import FILTER_KINDS, FilterKind, correct, predict
from .measurements import cable_measurement, image_measurement
from .model import LoadObservation, LoadParams, VehicleStates

__all__ = ["FilterStats", "LoadPoseFilter"]

log = logging.getLogger(__name__)

_OBS, _VEH = 0, 1  # at equal stamps an image is applied before the vehicles' sample


@dataclass
class _Event:
    stamp_s: float
    rank: int
    payload: object
    after: LoadEstimate | None = None
    nis: float = math.nan
    dof: int = 0
    accepted: bool = False
    restarted: bool = False

    @property
    def key(self) -> tuple[float, int]:
        return (self.stamp_s, self.rank)


@dataclass
class FilterStats:
    """Counters of a :class:`LoadPoseFilter`."""

    images: int = 0
    accepted: int = 0
    rejected: int = 0
    late: int = 0
    dropped_too_late: int = 0
    replayed_events: int = 0
    #: events after which the estimate was not finite and the filter restarted
    restarts: int = 0
    #: images applied without a finite NIS (a singular innovation covariance, refused; a diverged estimate)
    singular: int = 0
    nis_sum: float = 0.0
    dof_sum: int = 0

    @property
    def mean_nis(self) -> float:
        """Mean normalised innovation squared of the images applied with a finite one (their mean
        degrees of freedom, :attr:`mean_dof`, for a consistent filter)."""
        n = self.accepted + self.rejected - self.singular
        return self.nis_sum / n if n else math.nan

    @property
    def mean_dof(self) -> float:
        """Mean degrees of freedom of the images applied (3: eq. 4 alone; 6: with the attitude)."""
        n = self.accepted + self.rejected
        return self.dof_sum / n if n else math.nan


class LoadPoseFilter:
    """EKF or UKF of the load's pose over a time line of vehicle samples and images.

    ``push_vehicles`` advances the estimate to the sample's time (applying every image captured
    before it, in capture order); ``push_observation`` queues an image captured after the
    current time, or, if it is late (captured before the current time, arriving now), rolls back
    to the last kept estimate before its capture time and replays the later events with it:
    buffering and re-propagation, exact up to rounding. Events older than ``cfg.lag_s`` before
    the latest time are forgotten; images older than that are dropped (``stats.dropped_too_late``).
    ``restart(t_s, vehicles)``: the estimate the filter starts again from when its own is no longer
    finite after an event (default: at rest at the last finite estimate's pose, with
    :func:`~.estimate.initial_estimate`'s spreads).
    """

    def __init__(self, kind: FilterKind, params: LoadParams, cfg: LoadFilterConfig, initial: LoadEstimate,
                 restart: Callable[[float, VehicleStates], LoadEstimate] | None = None) -> None:
        if kind not in FILTER_KINDS:
            raise ValueError(f"kind must be 'ekf' or 'ukf', got {kind!r}")
        if initial.n_cables != params.n_cables:
            raise ValueError(f"initial estimate has {initial.n_cables} cables, params {params.n_cables}")
        self.kind: FilterKind = kind
        self.params = params
        self.cfg = cfg
        self._base = initial  # estimate before every kept event
        self._events: list[_Event] = []  # processed, in key order
        self._pending: list[_Event] = []  # images captured after the latest processed event
        self._vehicles: list[VehicleStates] = []
        self._restart = restart
        self.stats = FilterStats()

    @property
    def _latest(self) -> LoadEstimate:
        return self._events[-1].after if self._events else self._base  # type: ignore[return-value]

    @property
    def estimate(self) -> LoadEstimate:
        """The estimate after the latest processed event, its position covariance with the
        vehicles' unobserved bias (:func:`~.estimate.with_vehicle_bias`)."""
        return with_vehicle_bias(self._latest, self.cfg)

    def estimate_at(self, t_s: float) -> LoadEstimate:
        """The estimate at a past ``t_s`` from everything processed so far: the kept estimate
        after the last event at or before ``t_s``, predicted to ``t_s``. With ``t_s`` at least the
        images' delivery delay in the past, every image captured before it is in (a fixed-lag
        estimate, comparable with the camera-only solve of the same instant). ``ValueError``
        before the kept history or after the latest event."""
        if t_s < self._base.stamp_s - 1e-12 or t_s > self._latest.stamp_s + 1e-12:
            raise ValueError(f"t = {t_s} outside the kept history [{self._base.stamp_s}, {self._latest.stamp_s}]")
        i = bisect.bisect_right([e.key for e in self._events], (t_s, _VEH))
        est = self._events[i - 1].after if i else self._base
        if est.stamp_s < t_s:
            est = predict(self.kind, est, self._vehicles_at(est.stamp_s), t_s, self.params, self.cfg)
        return with_vehicle_bias(est, self.cfg)

    def _vehicles_at(self, t_s: float) -> VehicleStates:
        stamps = [v.stamp_s for v in self._vehicles]
        i = bisect.bisect_right(stamps, t_s + 1e-12) - 1
        if i < 0:
            raise ValueError(f"no vehicle sample at or before t = {t_s}")
        return self._vehicles[i]

    def _apply(self, est: LoadEstimate, ev: _Event) -> LoadEstimate:
        if est.stamp_s < ev.stamp_s:
            est = predict(self.kind, est, self._vehicles_at(est.stamp_s), ev.stamp_s, self.params, self.cfg)
        if ev.rank == _VEH:
            return est
        obs: LoadObservation = ev.payload  # type: ignore[assignment]
        vehicles = self._vehicles_at(obs.stamp_s)
        m = image_measurement(est.x, obs, vehicles, attitude=self.cfg.marker_attitude)
        try:
            est, nis, ok = correct(self.kind, est, m, self.cfg, self.cfg.gate_chi2(m.dof))
        except np.linalg.LinAlgError as exc:  # a singular innovation: the image is refused, not fatal
            nis, ok = math.inf, False
            log.warning("image of vehicle %d at %.3f s refused: %s", obs.vehicle, obs.stamp_s, exc)
        ev.nis, ev.dof, ev.accepted = nis, m.dof, ok
        if math.isfinite(nis):
            self.stats.nis_sum += nis
        else:
            self.stats.singular += 1
        self.stats.dof_sum += m.dof
        if ok:
            self.stats.accepted += 1
            est = self._cables(est, vehicles)
        else:
            self.stats.rejected += 1
            log.debug("image of vehicle %d at %.3f s rejected (NIS %.1f)", obs.vehicle, obs.stamp_s, nis)
        return est

    def _cables(self, est: LoadEstimate, vehicles: VehicleStates) -> LoadEstimate:
        """The taut cables' lengths after an accepted image (no gate: a cable's length is known).
        With the image, not at every vehicle sample: the vehicles' position errors are biases
        that repeated lengths would not average out, and between images (the attitude least
        certain) they would tilt the estimate towards them."""
        if not self.cfg.cable_lengths:
            return est
        m = cable_measurement(est.x, vehicles, est.stamp_s, self.params, self.cfg.cable_length_sigma_m,
                              self.cfg.cable_taut_fraction)
        if m is None:
            return est
        try:
            return correct(self.kind, est, m, self.cfg, None)[0]
        except np.linalg.LinAlgError as exc:
            log.warning("cable lengths at %.3f s not applied: %s", est.stamp_s, exc)
            return est

    def _process(self, events: list[_Event]) -> None:
        est = self._latest
        for ev in events:
            after = self._apply(est, ev)
            ev.restarted = not (np.all(np.isfinite(after.x)) and np.all(np.isfinite(after.P)))
            if ev.restarted:
                after = self._restarted(est, ev.stamp_s)
            est = ev.after = after
            self._events.append(ev)

    def _restarted(self, last: LoadEstimate, t_s: float) -> LoadEstimate:
        """The estimate the filter starts again from at ``t_s``, its last finite one being ``last``."""
        self.stats.restarts += 1
        vehicles = self._vehicles_at(t_s)
        log.warning("%s load filter diverged at %.3f s (its estimate not finite): restarted", self.kind, t_s)
        if self._restart is not None:
            return self._restart(t_s, vehicles)
        return initial_estimate(t_s, last.pos_w_m, last.q_wxyz, vehicles, self.params)

    def push_vehicles(self, vehicles: VehicleStates) -> LoadEstimate:
        """A sample of every vehicle (stamps increasing); returns the estimate at its time."""
        if vehicles.pos_w_m.shape[0] != self.params.n_cables:
            raise ValueError(f"{vehicles.pos_w_m.shape[0]} vehicles for {self.params.n_cables} cables")
        if self._vehicles and vehicles.stamp_s <= self._vehicles[-1].stamp_s:
            raise ValueError(f"vehicle samples must arrive in time order ({vehicles.stamp_s} after "
                             f"{self._vehicles[-1].stamp_s})")
        if vehicles.stamp_s < self._latest.stamp_s:
            raise ValueError(f"vehicle sample at {vehicles.stamp_s} before the estimate ({self._latest.stamp_s})")
        self._vehicles.append(vehicles)
        ready = [e for e in self._pending if e.stamp_s <= vehicles.stamp_s]
        self._pending = [e for e in self._pending if e.stamp_s > vehicles.stamp_s]
        self._process(ready + [_Event(vehicles.stamp_s, _VEH, vehicles)])
        self._forget(vehicles.stamp_s - self.cfg.lag_s)
        return self.estimate

    def push_observation(self, obs: LoadObservation) -> None:
        """An image's measurement, possibly late (its ``stamp_s`` is the capture time)."""
        self.stats.images += 1
        ev = _Event(obs.stamp_s, _OBS, obs)
        if obs.stamp_s < self._base.stamp_s or not self._vehicles or obs.stamp_s < self._vehicles[0].stamp_s:
            self.stats.dropped_too_late += 1
            log.debug("image of vehicle %d at %.3f s is older than the kept history; dropped", obs.vehicle, obs.stamp_s)
            return
        if not self._events or ev.key > self._events[-1].key:
            # captured after the latest vehicle sample: applied when time gets there
            bisect.insort(self._pending, ev, key=lambda e: e.key)
            return
        # late: roll back to the last event before it and replay
        self.stats.late += 1
        keys = [e.key for e in self._events]
        i = bisect.bisect_left(keys, ev.key)
        replay = self._events[i:]
        self._events = self._events[:i]
        for e in replay:
            e.after = None
            self.stats.restarts -= e.restarted
            if e.rank == _OBS:  # its update is undone and redone
                if math.isfinite(e.nis):
                    self.stats.nis_sum -= e.nis
                else:
                    self.stats.singular -= 1
                self.stats.dof_sum -= e.dof
                if e.accepted:
                    self.stats.accepted -= 1
                else:
                    self.stats.rejected -= 1
        self.stats.replayed_events += len(replay)
        self._process([ev] + replay)

    def _forget(self, cutoff_s: float) -> None:
        """Drop events before ``cutoff_s``; the estimate after the last dropped one becomes the base."""
        k = 0
        while k < len(self._events) - 1 and self._events[k].stamp_s < cutoff_s:
            k += 1
        if k:
            self._base = self._events[k - 1].after  # type: ignore[assignment]
            self._events = self._events[k:]
        # keep the vehicle sample in force at the base time and everything after it
        stamps = [v.stamp_s for v in self._vehicles]
        j = bisect.bisect_right(stamps, self._base.stamp_s + 1e-12) - 1
        if j > 0:
            self._vehicles = self._vehicles[j:]

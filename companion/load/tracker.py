"""The slung load's estimate as a carrying companion keeps it: vehicle samples and camera
observations in, the load's pose out, with a log of every estimate.

:class:`LoadTracker` holds one :class:`~.filter.LoadPoseFilter` per kind (``"ekf"``, ``"ukf"``).
The filters start at the first vehicle sample, from the rigging's prior below the vehicles' own
estimated positions (:meth:`~.config.LoadConfig.camera_free_pose`, 0.1 m and 0.1 rad), never
from a truth. At every vehicle sample the tracker logs, per filter, the real-time estimate (what a
controller would get, predicted past the images still on their way) and, with ``fixed_lag_s``,
the estimate of the instant ``fixed_lag_s`` ago (every image of that instant in); beside them the
camera-free pose of the same sample (the baseline without cameras). Observations before the first
vehicle sample are counted and dropped.

:func:`vehicle_states` makes a vehicle sample of the companion's link states
(:class:`~companion.messages.LinkState`: position, velocity, attitude, body rate and their 9x9
covariance), each carried with its velocity and body rate to the time every vehicle has reached. Pure: no clocks, sockets
or threads; time is the links' (the flight controllers' shared clock, simulation time in SITL).
"""

from __future__ import annotations

import numpy as np

from companion.estimation.so3 import quat_from_rotvec, quat_mul, quat_normalize

from .config import LoadConfig
from .estimate import LoadEstimate, initial_estimate
from .filter import LoadPoseFilter
from .kalman import FILTER_KINDS
from .model import ERR_ATT, ERR_POS, LoadObservation, VehicleStates

__all__ = ["LoadTracker", "vehicle_states", "log_keys"]

_POSE = np.r_[ERR_POS, ERR_ATT]


def log_keys(kinds) -> tuple[str, ...]:
    """The tracker's log columns for filters ``kinds``: ``t``; per kind ``<kind>_p``, ``_q``, ``_P``
    (the pose's 6x6 covariance, position then attitude); ``camera_free_p``, ``_q``; with a fixed lag
    ``lag_t`` and per kind ``<kind>_fixed_lag_p``, ``_q``, ``_P``."""
    keys = ["t", "camera_free_p", "camera_free_q", "lag_t"]
    for k in kinds:
        keys += [f"{k}_p", f"{k}_q", f"{k}_P", f"{k}_fixed_lag_p", f"{k}_fixed_lag_q", f"{k}_fixed_lag_P"]
    return tuple(keys)


def vehicle_states(states, max_age_s: float = 0.5) -> VehicleStates | None:
    """A sample of every carrying vehicle from their newest link states (in cable order), at the
    oldest of their times (the time every vehicle has reached: in a lockstep the newest states are
    all of one time once each has arrived), each carried there with its velocity and body rate;
    ``None`` if one has no state yet or one is more than ``max_age_s`` older than the newest (a
    silent vehicle is not guessed at)."""
    if any(s is None for s in states):
        return None
    times = np.array([s.time_s for s in states])
    t = float(times.min())
    if float(times.max()) - t > max_age_s:
        return None
    dt = (t - times)[:, None]
    v = np.array([s.v_w_m_s for s in states])
    w = np.array([s.omega_b_rad_s for s in states])
    P = np.array([s.P for s in states])
    q = quat_normalize(quat_mul(np.array([s.q_wxyz for s in states]), quat_from_rotvec(w * dt)))
    return VehicleStates(t, np.array([s.p_w_m for s in states]) + v * dt, v, P[:, 0:3, 0:3], q, P[:, 6:9, 6:9], w)


class LoadTracker:
    """The load's filters and their log (module docstring). ``kinds``: the filters run;
    ``fixed_lag_s``: the fixed-lag estimates' delay (0: none; it must be shorter than the filters'
    history, ``load.filter.lag_s``)."""

    def __init__(self, load: LoadConfig, kinds=("ekf",), fixed_lag_s: float = 0.0):
        if not kinds or any(k not in FILTER_KINDS for k in kinds):
            raise ValueError(f"kinds: some of {FILTER_KINDS}, got {kinds!r}")
        if not 0.0 <= fixed_lag_s < load.filter.lag_s:
            raise ValueError(f"fixed_lag_s must be in [0, load.filter.lag_s = {load.filter.lag_s:g}), got {fixed_lag_s}")
        self.load = load
        self.params = load.params()
        self.kinds = tuple(kinds)
        self.fixed_lag_s = float(fixed_lag_s)
        self.filters: dict[str, LoadPoseFilter] = {}
        self._t0 = 0.0  # the first vehicle sample's time (the filters' start)
        self.rows: dict[str, list] = {k: [] for k in log_keys(self.kinds)}
        self.early_observations = 0
        self.vehicle_samples = 0

    @property
    def started(self) -> bool:
        return bool(self.filters)

    def push_vehicles(self, veh: VehicleStates) -> dict[str, LoadEstimate]:
        """A vehicle sample (stamps increasing): every filter advanced to it and logged; returns the
        real-time estimates by kind."""
        if not self.filters:
            init = self._initial(veh.stamp_s, veh)
            self.filters = {k: LoadPoseFilter(k, self.params, self.load.filter, init, restart=self._initial)
                            for k in self.kinds}
            self._t0 = veh.stamp_s
        self.vehicle_samples += 1
        r = self.rows
        t = veh.stamp_s
        r["t"].append(t)
        out = {}
        for kind, filt in self.filters.items():
            est = out[kind] = filt.push_vehicles(veh)
            self._log(kind, est)
        t_lag = t - self.fixed_lag_s
        if self.fixed_lag_s and t_lag >= self._t0 - 1e-9:
            r["lag_t"].append(t_lag)
            for kind, filt in self.filters.items():
                self._log(f"{kind}_fixed_lag", filt.estimate_at(t_lag))
        free = self.load.camera_free_pose(veh.pos_w_m)
        r["camera_free_p"].append(free.pos_m)
        r["camera_free_q"].append(free.q_wxyz)
        return out

    def _initial(self, t_s: float, veh: VehicleStates) -> LoadEstimate:
        """The filters' start at ``t_s`` (and their restart after a divergence): the camera-free
        pose of the vehicles ``veh``, at rest."""
        prior = self.load.camera_free_pose(veh.positions_at(t_s))
        return initial_estimate(t_s, prior.pos_m, prior.q_wxyz, veh, self.params, pos_sigma_m=0.1, att_sigma_rad=0.1)

    def _log(self, name: str, est: LoadEstimate) -> None:
        self.rows[f"{name}_p"].append(est.pos_w_m.copy())
        self.rows[f"{name}_q"].append(est.q_wxyz.copy())
        self.rows[f"{name}_P"].append(est.P[np.ix_(_POSE, _POSE)])

    def push_observation(self, obs: LoadObservation) -> None:
        """A camera's measurement (its ``stamp_s``: the capture time); ``ValueError`` for a vehicle
        the load has no cable to."""
        if not 0 <= obs.vehicle < self.params.n_cables:
            raise ValueError(f"observation of vehicle {obs.vehicle + 1}: the load hangs from {self.params.n_cables}")
        if not self.filters:
            self.early_observations += 1
            return
        for filt in self.filters.values():
            filt.push_observation(obs)

    def arrays(self, prefix: str = "load_") -> dict[str, np.ndarray]:
        """The log as arrays (``prefix`` + column), columns without a row left out."""
        return {f"{prefix}{k}": np.asarray(v) for k, v in self.rows.items() if v}

    def stats(self) -> dict:
        """Per filter its counters (images, accepted, rejected, late, dropped, replayed, mean NIS and
        degrees of freedom); the vehicle samples and the observations before the first one."""
        out = {k: {"images": f.stats.images, "accepted": f.stats.accepted, "rejected": f.stats.rejected,
                   "late": f.stats.late, "dropped_too_late": f.stats.dropped_too_late,
                   "replayed_events": f.stats.replayed_events, "restarts": f.stats.restarts,
                   "singular": f.stats.singular,
                   "mean_nis": f.stats.mean_nis,
                   "mean_dof": f.stats.mean_dof} for k, f in self.filters.items()}
        return {"filters": out, "vehicle_samples": self.vehicle_samples,
                "observations_before_start": self.early_observations}

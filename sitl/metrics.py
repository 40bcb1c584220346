"""Flight metrics from a run log (pure numpy over the recorded arrays).

All figures are taken over the flight window (after the take-off, ``t >= flight_start_s``):

* ``rms_track_est_m`` per link: RMS of ``|p_target - p_estimate|`` where the estimate is what
  the controller used (EKF plus the held correction): the paper's Fig. 5 figure;
* ``rms_track_true_m`` per link: the same against the true position, the targets taken into the
  simulator's world frame (:func:`companion.trajectory.planned_positions`: the trajectory from the
  true start);
* ``rms_att_track_true_deg`` per link: RMS attitude angle between target and truth;
* ``rms_est_err_m``: per link, RMS of ``|p_estimate - p_true|`` at the companion ticks, for the
  EKF alone (``ekf``) and for the SCKF-corrected estimate (``sckf``, absent without SCKF);
* ``rms_rel_err`` (two links or more): per joint, the RMS error of the neighbours' relative
  position and relative attitude at the companion ticks, EKF alone and corrected
  (:func:`relative_error_metrics`);
* ``constraint_pos_p95_m`` / ``constraint_vel_p95_m_s``: 95th percentile over joints and
  companion ticks of the eq. 3 tip position / velocity error, ``before`` (EKF states) and
  ``after`` the constraint application;
* with several groups, ``constraint_pos_p95_m`` / ``constraint_vel_p95_m_s`` also split the
  ``after`` figure into ``after_within_groups`` and ``after_between_groups`` (the joints the
  global step of eq. 6 closes);
* ``static`` (a resting chain, thesis sec. 3.5.2): per link and axis the standard deviation
  over the window of the estimated position and its RMS error against the truth, for the EKF
  alone (``ekf``), after the local constraint application (``local``) and after the global step
  (``semi_distributed``) (:func:`static_metrics`); ``link4_std_m``: link 4's standard deviations
  with the thesis's figures beside them (``thesis``) and the true position's own (``truth``);
* ``rms_pose_track_pos_m`` / ``rms_pose_track_att_deg``: per link the RMS position / attitude
  error between target and estimate (what the controller used: the thesis's sec. 5.2 figure),
  averaged over the links; ``rms_pose_track_true_*`` the same against the true pose (the targets
  in the world frame, as for ``rms_track_true_m``). Window: from
  the CPG motion's start (``pose_track_window_s``) if there is one, else the flight window;
* ``motion`` (CPG runs): per command, the commanded forward speed, the expected physics' speed
  (the targets' centroid) and the achieved speed (the true centroid), horizontal and averaged
  over the second half of the command, and the direction of travel at its end;
* ``cable`` (two links or more): per joint the cable tension over the window (the simulator's
  force on the child link against the chain direction; positive: the cable pulls) as ``min``,
  ``p5``, ``mean``, ``max`` [N], the overall ``min_tension_n`` and the fraction of samples
  ``compression_fraction`` in which a cable would have to push (a real cable goes slack there);
  with the whole-chain feed-forward also the model's predicted tension (``model_*``);
* ``rotor_zero_crossings``: thrust sign changes over all rotors (the ESC singularity);
* ``rotor_limit_s_per_link``: per link, the simulated seconds (whole run) with one of its rotors
  commanded at the thrust limit: the link asked for more than it can do (its firmware then
  scales the wrench onto the limit above the link's weight, ``SKL_SAT_SCALE``, and reports it:
  ``thrust_limit`` in ``linkN_ports.json`` in a fleet, in ``metrics.json`` in batch mode);
* ``thrust_limit`` (batch mode): per link its firmware's report since its
  last boot: ``at_limit_s``, ``episodes`` (each announced by STATUSTEXT after ``SKL_TLIM_WARN``),
  ``min_scale``, ``at_limit_now``;
* ``min_altitude_m``: lowest true link-centre altitude; ``took_off`` (whether every link ever
  cleared the ground: a chain nobody armed stays on it, and that is not a crash); ``crashed``,
  ``crash_reason`` and ``crash_time_s`` (simulated time of the crash; ``None`` without one);
* ``nees``: per link and 3-dof block (position, velocity, attitude) the time-averaged normalised
  estimation error squared of the links' EKF estimates (``ekf``) and of the corrected ones
  (``corrected``: the constraint application's covariance), against the truth at the companion's
  steps, with ``bounds95``, the 95 % bounds of that average for a consistent filter (3 is the
  expected value; above: over-confident);
* ``estimate_coverage``: per link the fraction of the window in which its firmware logged an
  estimate (below 1: the vehicle was killed or rebooting; the RMS figures cover the rest);
* ``outages``: every window in which a link was out, with its ``kind``: ``uncorrected`` (no
  correction that step: left out by the plausibility checks, silent, rebooting, alone in its
  segment), ``no_global_step`` (distributed: the leader's shift did not arrive or was refused),
  and, in fleet mode, the scripted faults (``vehicle_down``, ``companion_down``); with the
  tracking and constraint figures ``during_outages`` and ``outside_outages`` (the whole-flight
  figures above include both).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.special import chdtri

from companion.estimation.so3 import attitude_error, quat_conj, quat_mul, quat_to_rotmat
from companion.estimation.whiten import whitened
from companion.trajectory import planned_positions

__all__ = ["PAPER_THREE_LINK", "THESIS_STATIC_LINK4_STD_M", "THESIS_CPG_POSE_TRACK", "compute_metrics",
           "motion_segments", "cable_metrics", "nees_metrics", "nees_series", "nees_whitened", "nees_bounds95",
           "correlation_time", "static_metrics", "carrying_metrics", "rms", "p95"]

#: Paper sec. V (outdoor, three links): RMS desired vs estimated position per link [m], and
#: the constraint error after SCKF ("under 5 cm and 2 cm/s").
PAPER_THREE_LINK = {
    "rms_track_est_m": [0.1161, 0.1340, 0.1257],
    "constraint_pos_after_max_m": 0.05,
    "constraint_vel_after_max_m_s": 0.02,
}


#: Thesis sec. 3.5.2: std of link 4's position [x, y, z] in the 7-link static test.
THESIS_STATIC_LINK4_STD_M = {
    "ekf": [0.558, 0.542, 0.098],
    "local": [0.194, 0.311, 0.052],
    "semi_distributed": [0.081, 0.125, 0.046],
}


#: Thesis sec. 5.2: RMS pose tracking (position m, attitude deg) averaged over the seven links.
THESIS_CPG_POSE_TRACK = {
    "forward_speed_horizontal_fig_5_4": [0.1579, 7.74],
    "yaw_vertical_fig_5_5": [0.2042, 9.01],
    "gait_transition_fig_5_6": [0.1857, 7.64],
}


def motion_segments(log: dict[str, np.ndarray], motion, end_s: float) -> list[dict]:
    """Commanded, expected and achieved forward speed per command of ``motion`` (MotionConfig)."""
    t = log["t"]
    out = []
    starts = [motion.start_s + c.at_s for c in motion.commands] + [end_s]
    for command, a, b in zip(motion.commands, starts[:-1], starts[1:]):
        half = (t >= 0.5 * (a + b)) & (t <= b)
        if half.sum() < 2:
            continue
        entry = {"start_s": a, "end_s": min(b, float(t[-1])), "gait": command.gait,
                 "speed_cmd_m_s": command.speed_m_s, "yaw_deg_cmd": command.yaw_deg}
        for name, positions in (("expected", planned_positions(log)), ("achieved", log["p_true"])):
            c = positions[half].mean(axis=1)
            v = (c[-1] - c[0]) / (t[half][-1] - t[half][0])
            entry[f"speed_{name}_m_s"] = float(np.linalg.norm(v[:2]))
            entry[f"travel_heading_{name}_deg"] = float(np.degrees(np.arctan2(-v[1], -v[0])))
        out.append(entry)
    return out


def cable_metrics(tension_true: np.ndarray, tension_model: np.ndarray | None = None) -> dict:
    """Cable tension figures over a window (rows: samples, columns: joints) [N]."""
    out = {
        "tension_n": {"min": tension_true.min(axis=0).tolist(), "p5": np.percentile(tension_true, 5, axis=0).tolist(),
                      "mean": tension_true.mean(axis=0).tolist(), "max": tension_true.max(axis=0).tolist()},
        "min_tension_n": float(tension_true.min()),
        "compression_fraction": float(np.mean(tension_true < 0.0)),
    }
    if tension_model is not None and np.any(np.isfinite(tension_model)):
        out["model_tension_n"] = {"min": np.nanmin(tension_model, axis=0).tolist(),
                                  "mean": np.nanmean(tension_model, axis=0).tolist(),
                                  "max": np.nanmax(tension_model, axis=0).tolist()}
        out["model_min_tension_n"] = float(np.nanmin(tension_model))
        err = tension_model - tension_true
        out["model_error_rms_n"] = float(np.sqrt(np.nanmean(err * err)))
    return out


def rms(x: np.ndarray, axis=0) -> np.ndarray:
    """RMS over the rows that hold a value (NaN rows: a link not flying its firmware then, a
    vehicle killed or rebooting; its ``coverage`` says how many)."""
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN column: NaN, reported so
        return np.sqrt(np.nanmean(x * x, axis=axis))


NEES_BLOCKS = ("pos", "vel", "att")


def nees_whitened(p_true, v_true, q_true, p, v, q, P_blocks) -> np.ndarray:
    """Whitened errors ``L^-1 e`` (``P_bb = L L^T``) per sample and 3-dof block (position,
    velocity, attitude), shape ``(..., 3 blocks, 3)``: ``e`` the truth minus the estimate (the
    attitude error world-frame, as the EKF's error state), ``P_blocks`` (..., 3, 3, 3) the
    diagonal blocks of its covariance. For a consistent filter three independent unit normals,
    whose squared norm is the NEES; NaN where the estimate is unknown or its block cannot whiten it
    (:func:`~companion.estimation.whiten.whitened`)."""
    return whitened(np.stack([p_true - p, v_true - v, attitude_error(q_true, q)], axis=-2), P_blocks)


def _log_whitened(log: dict[str, np.ndarray], which: str) -> np.ndarray | None:
    """:func:`nees_whitened` of the ``which`` estimate at the companion's steps, or ``None`` if
    the log lacks the covariances or the truth."""
    need = (f"p_{which}_sckf", f"P_{which}_sckf", "p_true_sckf", "v_true_sckf", "q_true_sckf")
    if not all(k in log for k in need):
        return None
    return nees_whitened(log["p_true_sckf"], log["v_true_sckf"], log["q_true_sckf"], log[f"p_{which}_sckf"],
                         log[f"v_{which}_sckf"], log[f"q_{which}_sckf"], log[f"P_{which}_sckf"])


def nees_series(log: dict[str, np.ndarray], which: str) -> np.ndarray | None:
    """(steps, n, 3) NEES of the ``which`` estimate (``"ekf"``: the links' reports, ``"corr"``:
    after the constraint application) per 3-dof block (position, velocity, attitude): ``e^T
    P_bb^-1 e`` with ``e`` the truth minus the estimate (the attitude error world-frame, as the
    EKF's error state) and ``P_bb`` the block of the covariance logged with it; NaN where the
    estimate is unknown. ``None`` if the log lacks the covariances or the truth."""
    w = _log_whitened(log, which)
    return None if w is None else np.sum(w * w, axis=-1)


def correlation_time(w: np.ndarray, c: float = 5.0) -> np.ndarray:
    """Integrated correlation time (in samples) of the NEES built from whitened errors ``w``
    (time on axis 0, the 3 components on the last axis, any axes between; NaN: no sample).

    For Gaussian errors the NEES' autocorrelation at lag ``j`` is the mean over components of
    the squared autocorrelation of the whitened error, ``rho(j)^2`` (``cov(x^2, y^2) = 2
    cov(x, y)^2``). ``rho`` is taken about zero (the consistent filter's mean, so that a bias that
    persists counts as correlation, as it does for the average), from the samples present; the
    sum ``tau = 1 + 2 sum_j rho_nees(j)`` is cut with Sokal's automatic window (the first lag
    ``j >= c tau(j)``). ``K / tau`` samples of such a series are worth ``K`` independent ones."""
    k = w.shape[0]
    x = np.nan_to_num(w, nan=0.0)
    m = np.isfinite(w).astype(float)
    nfft = 1 << int(np.ceil(np.log2(2 * k)))

    def acf(a: np.ndarray) -> np.ndarray:
        f = np.fft.rfft(a, n=nfft, axis=0)
        return np.fft.irfft(f * np.conj(f), n=nfft, axis=0)[:k]

    num, cnt = acf(x), acf(m)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = num / np.maximum(cnt, 1.0)
        rho = cov / cov[:1]
    rho = np.where(cnt >= 10, rho, 0.0)  # lags with too few pairs: no estimate
    rho_nees = np.nanmean(rho * rho, axis=-1)  # (k, ...)
    tau = 1.0 + 2.0 * np.cumsum(rho_nees[1:], axis=0)  # tau(j) for j = 1..k-1
    lags = np.arange(1, k).reshape((-1,) + (1,) * (tau.ndim - 1))
    stop = lags >= c * tau
    first = np.where(np.any(stop, axis=0), np.argmax(stop, axis=0), k - 2) if k > 1 else np.zeros(tau.shape[1:], int)
    out = np.take_along_axis(tau, first[None], axis=0)[0] if k > 1 else np.ones(w.shape[1:-1])
    return np.maximum(np.nan_to_num(out, nan=1.0), 1.0)


def nees_bounds95(samples: np.ndarray | float, dof: int = 3) -> np.ndarray:
    """Two-sided 95 % bounds (last axis: lo, hi) of the average of ``samples`` independent
    ``dof``-dof NEES values of a consistent filter (``K * mean ~ chi2(dof K)``): the chi-square
    quantiles by ``scipy.special.chdtri``, the upper tail's inverse (scipy.stats is slow to import,
    and a run needs nothing else from it)."""
    k = np.asarray(samples, dtype=float)
    return np.stack([chdtri(dof * k, 0.975) / k, chdtri(dof * k, 0.025) / k], axis=-1)


def relative_error_metrics(log: dict, rows: np.ndarray, sckf: bool) -> dict:
    """Per joint, the RMS error at the companion steps ``rows`` of the neighbours' relative
    position (``pos_m``: of ``p_{i+1} - p_i``, in the world frame; ``pos_body_m``: of ``R_i^T
    (p_{i+1} - p_i)``, where link ``i`` sees its neighbour, the relative pose's own position,
    which no error of the two links' common attitude moves) and relative attitude (``att_deg``:
    the angle of ``R_i^T R_{i+1}``'s error), for the EKF states and, with the SCKF, the corrected
    ones: what a measurement between neighbours (a camera seeing its neighbour) improves."""
    def rel_q(q):
        return quat_mul(quat_conj(q[:, :-1]), q[:, 1:])

    def in_body(p, q):
        return np.einsum("knji,knj->kni", quat_to_rotmat(q[:, :-1]), np.diff(p, axis=1))

    p_true, q_true = log["p_true_sckf"][rows], log["q_true_sckf"][rows]
    d_true, b_true, r_true = np.diff(p_true, axis=1), in_body(p_true, q_true), rel_q(q_true)
    out: dict = {"pos_m": {}, "pos_body_m": {}, "att_deg": {}}
    for tag, (pk, qk) in (("ekf", ("p_ekf_sckf", "q_ekf_sckf")), ("sckf", ("p_corr_sckf", "q_corr_sckf"))):
        if tag == "sckf" and not sckf:
            continue
        p, q = log[pk][rows], log[qk][rows]
        d_err = np.linalg.norm(np.diff(p, axis=1) - d_true, axis=-1)
        b_err = np.linalg.norm(in_body(p, q) - b_true, axis=-1)
        a_err = np.degrees(np.linalg.norm(attitude_error(rel_q(q), r_true), axis=-1))
        out["pos_m"][tag] = rms(d_err).tolist()
        out["pos_body_m"][tag] = rms(b_err).tolist()
        out["att_deg"][tag] = rms(a_err).tolist()
    return out


def nees_metrics(log: dict[str, np.ndarray], flight_start_s: float) -> dict | None:
    """The time-averaged NEES per link and 3-dof block over the flight window, for the links'
    EKF estimates (``ekf``) and the corrected ones (``corrected``), with the 95 % bounds of such
    an average for a consistent filter.

    ``bounds95`` takes the ``samples`` steps as independent (e.g. 2.85-3.15 over a
    60 s flight at 20 Hz). They are not: the GPS and attitude-reference errors stay correlated for
    tens of seconds, so one flight holds far fewer independent NEES values.
    ``effective_samples`` (per estimate, block and link) divides the steps by the NEES'
    integrated correlation time (:func:`correlation_time`, from the whitened errors' own
    autocorrelation, which does not depend on the covariance's scale: an over-confident filter
    is not excused by it), ``bounds95_effective`` are the bounds for that many and ``inside95``
    says whether each average lies within them. The Monte Carlo form of the test (the same
    average over several seeds) is ``python -m sitl.bench nees``."""
    out: dict = {}
    win = log.get("t_sckf", np.zeros(0)) >= flight_start_s
    eff: dict = {}
    for name, which in (("ekf", "ekf"), ("corrected", "corr")):
        w = _log_whitened(log, which)
        if w is None or not np.any(win):
            return None
        w = w[win]  # (k, n, 3 blocks, 3)
        series = np.sum(w * w, axis=-1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(series, axis=0)  # (n, 3)
        present = np.sum(np.isfinite(series), axis=0)  # (n, 3)
        k_eff = present / correlation_time(w)
        out[name] = {b: mean[:, j].tolist() for j, b in enumerate(NEES_BLOCKS)}
        eff[name] = (mean, np.maximum(k_eff, 1.0))
    k = int(np.sum(win))
    out["samples"] = k
    out["bounds95"] = nees_bounds95(k).tolist()
    out["effective_samples"] = {name: {b: k_eff[:, j].round(1).tolist() for j, b in enumerate(NEES_BLOCKS)}
                                for name, (_, k_eff) in eff.items()}
    out["bounds95_effective"] = {}
    out["inside95"] = {}
    for name, (mean, k_eff) in eff.items():
        bounds = nees_bounds95(k_eff)  # (n, 3, 2)
        out["bounds95_effective"][name] = {b: bounds[:, j].tolist() for j, b in enumerate(NEES_BLOCKS)}
        out["inside95"][name] = {b: ((bounds[:, j, 0] <= mean[:, j]) & (mean[:, j] <= bounds[:, j, 1])).tolist()
                                 for j, b in enumerate(NEES_BLOCKS)}
    return out


def flag_windows(t: np.ndarray, out: np.ndarray) -> list[dict]:
    """Every window (start, end, links 1-based) in which the set of links flagged in ``out``
    (rows: times, columns: links) stayed the same and was not empty."""
    out = np.asarray(out, dtype=bool)
    windows, start = [], None
    for k in range(out.shape[0] + 1):
        links = tuple(int(i) + 1 for i in np.flatnonzero(out[k])) if k < out.shape[0] else ()
        prev = tuple(int(i) + 1 for i in np.flatnonzero(out[k - 1])) if k > 0 else ()
        if links != prev:
            if prev:
                windows.append({"start_s": float(t[start]), "end_s": float(t[k - 1]), "links": list(prev)})
            start = k
    return windows


def outage_split(log: dict[str, np.ndarray], flight_start_s: float, windows: list[dict]) -> dict:
    """The flight figures inside every outage window (any link out, any kind) and outside them:
    true and estimated tracking RMS per link, constraint p95 after the SCKF. The windows are
    those of :func:`flag_windows` and the fleet's scripted faults (``kind`` names which); each
    gets ``corrected_fraction``: per link, the fraction of the companions' steps in it that
    corrected that link (``None`` for the window's own links and where no step fell in it)."""
    t = log["t"]
    if "t_sckf" in log and "corrected_sckf" in log:
        windows = [{**w, "corrected_fraction": _corrected_fraction(log["t_sckf"], log["corrected_sckf"], w)}
                   for w in windows]
    flight = t >= flight_start_s

    def inside(times: np.ndarray) -> np.ndarray:
        mask = np.zeros(times.shape, dtype=bool)
        for w in windows:
            mask |= (times >= w["start_s"]) & (times <= w["end_s"])
        return mask

    rows = inside(t)
    out: dict = {"windows": windows, "time_in_outages_s": float(np.sum(rows & flight) / max(np.sum(flight), 1)
                                                               * (t[-1] - flight_start_s)) if np.any(flight) else 0.0}
    steps = None
    if "t_sckf" in log and "con_pos_after" in log:
        steps = log["t_sckf"] >= flight_start_s
        in_steps = inside(log["t_sckf"])
    for name, sel in (("during_outages", rows), ("outside_outages", ~rows)):
        w = flight & sel
        part: dict = {"samples": int(np.sum(w))}
        if np.any(w):
            planned = planned_positions(log)[w]
            part["rms_track_true_m"] = rms(np.linalg.norm(planned - log["p_true"][w], axis=-1)).tolist()
            part["rms_track_est_m"] = rms(np.linalg.norm(log["p_target"][w] - log["p_ctrl"][w], axis=-1)).tolist()
        if steps is not None:
            ws = steps & (in_steps if name == "during_outages" else ~in_steps)
            part["constraint_pos_p95_m_after"] = p95(log["con_pos_after"][ws]) if np.any(ws) else None
        out[name] = part
    return out


def _corrected_fraction(t_steps: np.ndarray, corrected: np.ndarray, window: dict) -> list[float | None]:
    sel = (t_steps >= window["start_s"]) & (t_steps <= window["end_s"])
    own = set(window.get("links") or ())
    if not np.any(sel):
        return [None] * corrected.shape[1]
    frac = np.asarray(corrected, dtype=bool)[sel].mean(axis=0)
    return [None if i + 1 in own else round(float(f), 4) for i, f in enumerate(frac)]


def p95(values: list | np.ndarray) -> float | None:
    """The 95th percentile of the finite values (``None``: none)."""
    a = np.asarray(values, dtype=float)
    a = a[np.isfinite(a)]  # NaN: a joint of a group whose companion was down (an outage window)
    return float(np.percentile(a, 95)) if a.size else None


def uncorrected_metrics(t: np.ndarray, corrected: np.ndarray, nis_max: np.ndarray | None = None) -> dict:
    """Steps in which links got no correction (left out by the companion's plausibility checks,
    or alone in their segment): the fraction per link, and every window (start, end, links) in
    which the set of uncorrected links stayed the same. ``nis_max``: the joint gate's largest NIS
    per step (its p50 / p99 / max)."""
    corrected = np.asarray(corrected, dtype=bool)
    out: dict = {"steps": int(corrected.shape[0]),
                 "fraction_per_link": (1.0 - corrected.mean(axis=0)).tolist() if corrected.size else [],
                 "windows": flag_windows(t, ~corrected)}
    if nis_max is not None:
        finite = np.asarray(nis_max, dtype=float)
        finite = finite[np.isfinite(finite)]
        if finite.size:
            out["gate_nis_max"] = {"p50": float(np.percentile(finite, 50)), "p99": float(np.percentile(finite, 99)),
                                   "max": float(finite.max())}
    return out


def carrying_metrics(summaries: dict[str, dict]) -> dict:
    """``carrying``: how long the companions carried each link (its rotors taken to be off, the
    whole-chain feed-forward giving its weight to its neighbours), from their summaries (``name``
    -> summary; a restarted companion's time is added to its predecessor's): ``carried_s``,
    ``carried_stretches`` and ``carry_released`` (taken to lift itself while silent) per link
    (system id) by its own group's companion, ``state_loss`` the
    estimated loss of its state stream (the newest companion's), ``carried_by_other_groups_s`` per
    companion (distributed mode: the other groups' links it carried on their word) and
    ``bridged_steps``, the steps in which a link in a GPS fault was corrected along a neighbour
    left out of the step (:mod:`companion.engine.bridge`), over all companions."""
    own: dict[str, float] = {}
    stretches: dict[str, int] = {}
    released: dict[str, int] = {}
    loss: dict[str, float | None] = {}
    others: dict[str, dict] = {}
    for name, summ in summaries.items():
        for sysid, entry in (summ.get("links") or {}).items():
            own[sysid] = round(own.get(sysid, 0.0) + float(entry.get("carried_s", 0.0)), 3)
            stretches[sysid] = stretches.get(sysid, 0) + int(entry.get("carried_stretches", 0))
            released[sysid] = released.get(sysid, 0) + int(entry.get("carry_released", 0))
            loss[sysid] = entry.get("state_loss", loss.get(sysid))
        if summ.get("carried_by_other_groups_s"):
            others[name] = summ["carried_by_other_groups_s"]

    def by_link(d: dict) -> dict:
        return dict(sorted(d.items(), key=lambda kv: int(kv[0])))

    out: dict = {"carried_s": by_link(own), "carried_stretches": by_link(stretches), "carry_released": by_link(released),
                 "state_loss": by_link(loss),
                 "bridged_steps": sum(int(summ.get("bridged_steps", 0)) for summ in summaries.values())}
    if others:
        out["carried_by_other_groups_s"] = others
    return out


def vehicle_down_windows(link_fault: dict, end_s: float) -> list[dict]:
    """The outage window of a link reboot (``faults.link_reboot`` so far): its firmware killed
    until it is back (``rejoined_at_s``; the end of the run if never)."""
    if "killed_at_s" not in link_fault:
        return []
    return [{"kind": "vehicle_down", "start_s": link_fault["killed_at_s"],
             "end_s": link_fault.get("rejoined_at_s", end_s), "links": [link_fault["link"]]}]


def reboot_timeline(link_fault: dict, steps: dict) -> dict:
    """``faults.link_reboot``: the reboot's timeline (killed, restarted, back, rotors on) and when
    the companion first corrected the link after its restart (``readmitted_at_s``, from the step
    log ``steps``; ``None`` if never)."""
    entry = dict(link_fault)
    if "restarted_at_s" in link_fault and "corrected_sckf" in steps:
        t, corrected = steps["t_sckf"], steps["corrected_sckf"][:, link_fault["link"] - 1]
        after = np.flatnonzero((t >= link_fault["restarted_at_s"]) & corrected)
        entry["readmitted_at_s"] = round(float(t[after[0]]), 3) if after.size else None
        if after.size:
            entry["readmitted_after_restart_s"] = round(float(t[after[0]]) - link_fault["restarted_at_s"], 3)
    return entry


def compute_metrics(
    log: dict[str, np.ndarray],
    flight_start_s: float,
    zero_crossings: np.ndarray,
    crashed: bool,
    crash_reason: str,
    realtime_factor: float,
    sckf_enabled: bool,
    groups=None,
    resting: bool = False,
    motion=None,
    fault_windows: list[dict] | None = None,
    rotor_limit_s: np.ndarray | None = None,
    took_off: bool = True,
    crash_time_s: float | None = None,
) -> dict:
    """The figures of the module docstring; ``fault_windows``: outage windows the run knows of
    besides the step log's (fleet mode's scripted faults, each with its ``kind``); ``took_off``:
    whether the chain ever left the ground (a run that never did has not crashed either)."""
    t = log["t"]
    win = t >= flight_start_s
    if not np.any(win):
        raise ValueError(f"the run ended before the flight window (t >= {flight_start_s} s)")
    n = log["p_true"].shape[1]
    err_est = np.linalg.norm(log["p_target"][win] - log["p_ctrl"][win], axis=-1)
    err_true = np.linalg.norm(planned_positions(log)[win] - log["p_true"][win], axis=-1)
    att_err = np.degrees(
        np.linalg.norm(attitude_error(log["q_true"][win], log["q_target"][win]), axis=-1)
    )
    # fleet mode without a companion (or one that never stepped in the window) has no step log
    has_steps = "t_sckf" in log and bool(np.any(log["t_sckf"] >= flight_start_s))
    if has_steps:
        wins = log["t_sckf"] >= flight_start_s
        ekf_err = np.linalg.norm(log["p_ekf_sckf"][wins] - log["p_true_sckf"][wins], axis=-1)
    else:
        ekf_err = np.linalg.norm(log["p_ekf"][win] - log["p_true"][win], axis=-1)
    pose_start = motion.start_s if motion is not None else flight_start_s
    pw = t >= pose_start
    pose = {}
    if np.any(pw):
        for tag, (pk, qk, target) in (("", ("p_ctrl", "q_ctrl", log["p_target"])),
                                      ("true_", ("p_true", "q_true", planned_positions(log)))):
            pos = rms(np.linalg.norm(target[pw] - log[pk][pw], axis=-1))
            att = rms(np.degrees(np.linalg.norm(attitude_error(log[qk][pw], log["q_target"][pw]), axis=-1)))
            pose[f"rms_pose_track_{tag}pos_m"] = float(pos.mean())
            pose[f"rms_pose_track_{tag}att_deg"] = float(att.mean())
        pose["pose_track_window_s"] = [float(pose_start), float(t[-1])]
    metrics = {
        "n_links": n,
        **pose,
        "flight_window_s": [float(flight_start_s), float(t[-1])],
        "rms_track_est_m": rms(err_est).tolist(),
        "rms_track_true_m": rms(err_true).tolist(),
        "rms_att_track_true_deg": rms(att_err).tolist(),
        "rms_est_err_m": {"ekf": rms(ekf_err).tolist()},
        "constraint_pos_p95_m": {},
        "constraint_vel_p95_m_s": {},
        "rotor_zero_crossings": int(np.sum(zero_crossings)),
        "rotor_zero_crossings_per_link": np.asarray(zero_crossings).reshape(n, -1).sum(axis=1).tolist(),
        "rotor_limit_s_per_link": (None if rotor_limit_s is None else
                                   [round(float(x), 3) for x in np.asarray(rotor_limit_s, dtype=float)]),
        "min_altitude_m": float(log["p_true"][win][..., 2].min()),
        "estimate_coverage": np.mean(np.all(np.isfinite(log["p_ctrl"][win]), axis=-1), axis=0).tolist(),
        "took_off": bool(took_off),
        "crashed": bool(crashed),
        "crash_reason": crash_reason,
        "crash_time_s": None if crash_time_s is None else round(float(crash_time_s), 3),
        "realtime_factor": float(realtime_factor),
        "sckf": bool(sckf_enabled),
    }
    if n > 1 and has_steps:
        metrics["constraint_pos_p95_m"]["before"] = p95(log["con_pos_before"][wins])
        metrics["constraint_vel_p95_m_s"]["before"] = p95(log["con_vel_before"][wins])
    if sckf_enabled and has_steps and "corrected_sckf" in log:
        metrics["uncorrected"] = uncorrected_metrics(log["t_sckf"][wins], log["corrected_sckf"][wins],
                                                     log["nis_max_sckf"][wins] if "nis_max_sckf" in log else None)
    if sckf_enabled and has_steps:
        corr_err = np.linalg.norm(log["p_corr_sckf"][wins] - log["p_true_sckf"][wins], axis=-1)
        metrics["rms_est_err_m"]["sckf"] = rms(corr_err).tolist()
        metrics["sckf_iterations_mean"] = float(np.mean(log["iterations"][wins]))
        if n > 1:
            metrics["constraint_pos_p95_m"]["after"] = p95(log["con_pos_after"][wins])
            metrics["constraint_vel_p95_m_s"]["after"] = p95(log["con_vel_after"][wins])
            metrics["constraint_pos_max_m"] = {"after": float(np.nanmax(log["con_pos_after"][wins]))}
            metrics["constraint_vel_max_m_s"] = {"after": float(np.nanmax(log["con_vel_after"][wins]))}
            if groups is not None and len(groups) > 1:
                between = np.zeros(n - 1, dtype=bool)
                between[[g[-1] for g in groups[:-1]]] = True
                for key, name in (("constraint_pos_p95_m", "con_pos_after"), ("constraint_vel_p95_m_s", "con_vel_after")):
                    values = log[name][wins]
                    metrics[key]["after_within_groups"] = p95(values[:, ~between]) if np.any(~between) else None
                    metrics[key]["after_between_groups"] = p95(values[:, between])
    if n > 1 and has_steps and {"p_true_sckf", "q_true_sckf", "q_ekf_sckf", "q_corr_sckf"} <= set(log):
        metrics["rms_rel_err"] = relative_error_metrics(log, wins, sckf_enabled)
    nees = nees_metrics(log, flight_start_s) if has_steps else None
    if nees is not None:
        metrics["nees"] = nees
    windows = [dict(w, kind="uncorrected") for w in metrics.get("uncorrected", {}).get("windows", [])]
    if has_steps and groups is not None and len(groups) > 1 and np.shape(log.get("global_applied"))[-1] == len(groups):
        for w in flag_windows(log["t_sckf"][wins], ~np.asarray(log["global_applied"][wins], dtype=bool)):
            links = sorted(i + 1 for g in w["links"] for i in groups[g - 1])
            windows.append(dict(w, links=links, groups=w["links"], kind="no_global_step"))
    windows += list(fault_windows or [])
    metrics["outages"] = outage_split(log, flight_start_s, sorted(windows, key=lambda w: w["start_s"]))
    if n > 1 and "tension_true" in log:
        metrics["cable"] = cable_metrics(log["tension_true"][win],
                                         log["tension_model"][win] if "tension_model" in log else None)
    if motion is not None:
        metrics["motion"] = motion_segments(log, motion, float(t[-1]))
        metrics["thesis_pose_track"] = THESIS_CPG_POSE_TRACK
    if resting and has_steps:
        metrics["static"] = static_metrics(log, wins, sckf_enabled)
        if n >= 4:
            stds = {name: v[3] for name, v in metrics["static"]["std_m"].items()}
            stds["thesis"] = THESIS_STATIC_LINK4_STD_M
            metrics["link4_std_m"] = stds
    return metrics


#: The estimates a resting chain's figures compare (name in the metrics, step-log key).
STATIC_ESTIMATES = (("ekf", "p_ekf_sckf"), ("local", "p_local_sckf"), ("semi_distributed", "p_corr_sckf"))


def static_metrics(log: dict[str, np.ndarray], wins: np.ndarray, sckf_enabled: bool) -> dict:
    """A resting chain (thesis sec. 3.5.2): per link and world axis, the standard deviation of
    each position estimate over the window (``std_m``: what the thesis reports) and its RMS error
    against the truth (``rms_err_m``: the deviation plus the offset the std leaves out), for the
    EKF alone, after the local constraint application (groups alone) and after the global step
    (the corrected estimate; with one group the local and the semi-distributed are the same);
    ``std_m["truth"]``: the true position's own deviation (the resting chain's sway)."""
    truth = log["p_true_sckf"][wins]
    out: dict = {"std_m": {}, "rms_err_m": {}}
    for name, key in STATIC_ESTIMATES:
        if key not in log or (name != "ekf" and not sckf_enabled):
            continue
        est = log[key][wins]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            out["std_m"][name] = np.nanstd(est, axis=0).tolist()
        out["rms_err_m"][name] = rms(est - truth).tolist()
    out["std_m"]["truth"] = np.std(truth, axis=0).tolist()
    return out

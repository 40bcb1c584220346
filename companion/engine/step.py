"""The 20 Hz step: constraint application over the links a step uses, its corrections, its log.

Every 1/``rate_hz`` (:meth:`ChainStep.run`), the links :class:`~.selection.LinkSelection` lets
take part are time-aligned to the step time (:func:`companion.corrections.align_states`) and
every segment of two or more links gets its constraint application (Alg. 1, or Alg. 2 + eq. 6
with several groups) and its links their corrections, stamped on each link's own clock. With
``enabled = false`` the step only logs the links' EKF states.

Distributed mode (one engine per group, ``net`` a :class:`~companion.fleetnet.group.GroupLink`):
the step is the group's local half at the cycle time (a multiple of the step period, the same
instant in every group); the boundary goes to the leader and the corrections go out when the
leader's shift arrives or its deadline passes (:meth:`ChainStep.finish`). A group with a link
left out (or a joint cut) is split into parts, a part being as little as one link: each part
gets its local step and publishes its own boundary, and the global step joins the part that
touches a neighbouring group to that group, so every live link keeps being corrected. A
one-link part that no neighbouring group joins gets no correction (nothing constrains it), unless
it flags a GPS fault next to a link left out: then its position is corrected along that link, a
link length from the link beyond (:mod:`.bridge`).

The step log keeps one row per step (per cycle in distributed mode), every array on the time
base (:data:`STEP_LOG_KEYS`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ..corrections import compute_corrections, finish_step, local_step
from ..estimation.so3 import quat_from_rotvec, quat_mul
from ..fleetnet.outcomes import PartBoundary, PartShift
from ..messages import LinkState
from ..quantiles import Quantiles
from .bridge import bridge_correction
from .links import LinkTrack, usec
from .neighbours import NeighbourQueue
from .outputs import CorrectionOut
from .selection import LinkSelection

__all__ = ["STEP_LOG_KEYS", "ChainStep"]

log = logging.getLogger(__name__)

#: The step log, one row per step (per cycle in distributed mode), every array on the time base.
STEP_LOG_KEYS = ("t_sckf", "cycle_us", "p_ekf_sckf", "v_ekf_sckf", "q_ekf_sckf", "w_sckf", "p_local_sckf",
                 "p_corr_sckf", "v_corr_sckf", "q_corr_sckf", "iterations", "global_applied", "leader",
                 "corrected_sckf", "nis_max_sckf", "P_ekf_sckf", "P_corr_sckf", "home_offset_sckf")


def _blocks(P: np.ndarray) -> np.ndarray:
    """(n, 3, 3, 3): the position, velocity and attitude blocks of (n, 9, 9) covariances (what
    the step log keeps of them: enough for the NEES of each, a third of the size)."""
    return np.stack([P[:, 3 * b:3 * b + 3, 3 * b:3 * b + 3] for b in range(3)], axis=1)


def _stacked(states: list[LinkState]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(p, v, q, w)`` of ``states``, stacked (n, 3 or 4)."""
    return (np.array([s.p_w_m for s in states]), np.array([s.v_w_m_s for s in states]),
            np.array([s.q_wxyz for s in states]), np.array([s.omega_b_rad_s for s in states]))


class ChainStep:
    """The step of one engine's ``links`` (``d``: their tip vectors; ``groups``: the configured
    groups, rows of this engine) under ``cfg`` (a :class:`~companion.config.CompanionConfig`).

    ``selection`` decides who takes part; ``net`` is the distributed mode's group link (else
    ``None``); ``emit`` takes each :class:`~.outputs.CorrectionOut`; ``timer`` measures the
    step's compute time only (``step_times_ms``, never a decision); ``home`` gives the home
    offset the engine's targets are flown from (world, m; logged with each step as
    ``home_offset_sckf``: where a view puts the targets back in the truth's frame)."""

    def __init__(self, cfg, links: list[LinkTrack], d: np.ndarray, groups, selection: LinkSelection, net,
                 emit: Callable[[object], None], timer: Callable[[], float],
                 home: Callable[[], np.ndarray] = lambda: np.zeros(3)):
        self.enabled = cfg.enabled
        self.params = cfg.params
        self.links = links
        self.d = d
        self.groups = groups
        self.selection = selection
        self.net = net
        self._emit = emit
        self._timer = timer
        self._home = home
        self.seq = 0
        self._local: dict[int, tuple] = {}  # cycle -> (states, LocalStep, NIS, reported P) awaiting the shift
        #: neighbour camera measurements for the next step (applied before the constraint)
        self.neighbours = NeighbourQueue(hold_s=cfg.neighbour_hold_s)
        self.log: dict[str, list] = {k: [] for k in STEP_LOG_KEYS}
        self.step_times_ms = Quantiles()
        #: ``(p, q)``: the newest step's estimate of this engine's links (corrected, or a link's EKF
        #: state where nothing corrected it); ``None`` before the first step
        self.latest: tuple[np.ndarray, np.ndarray] | None = None
        #: steps in which a link was corrected along a link left out (:mod:`.bridge`)
        self.bridged_steps = 0

    def run(self, now_s: float, t_us: int, cycle_us: int) -> None:
        """The step due at ``now_s``: at ``t_us`` (the cycle clock), or at the cycle ``cycle_us``
        in distributed mode."""
        if not self.enabled:
            self._observe(t_us, cycle_us)
            return
        if self.net is not None:
            self._local_half(now_s, cycle_us)
            return
        segs, _, nis_max = self.selection.plan(t_us, now_s)
        ekf, p, v, q, p_local, iterations, corrected, P = self._correct_segments(segs, None, True, t_us)
        self._record(t_us, -1, ekf, p, v, q, p_local, iterations, bool(corrected.any()), -1, corrected, nis_max, P)

    def _segment_groups(self, seg: tuple[int, ...]) -> list[tuple[int, ...]]:
        """This engine's groups cut to segment ``seg`` (rows), numbered from its first link."""
        members = set(seg)
        out = [tuple(r - seg[0] for r in g if r in members) for g in self.groups]
        return [g for g in out if g]

    def _correct_segments(self, segs, t_s: float | None, split_groups: bool, t_us: int):
        """Constraint application on every segment on its own, aligned to ``t_s`` (default: each
        segment's newest stamp), and its links' corrections out. ``split_groups``: a segment keeps
        its part of the configured groups (Alg. 2 + eq. 6 inside it); else it is one group (Alg. 1,
        a group companion's local-only step). Returns the step log's ``(ekf, p, v, q, p_local,
        iterations, corrected, (P_ekf, P_corr))`` over this engine's links (a link not corrected keeps
        its EKF state; a silent one, whose newest state is too old to say where it is, is NaN; P_ekf
        is what the links reported, P_corr the constraint application's covariance). ``t_us``: the
        cycle clock, for the warnings."""
        states = [self.selection.step_state(lk) for lk in self.links]
        ekf = self._logged_states(states)
        p, v, q = (a.copy() for a in ekf[:3])
        P_ekf = np.array([lk.state.P for lk in self.links])
        P_corr = P_ekf.copy()
        p_local = p.copy()
        corrected = np.zeros(len(self.links), dtype=bool)
        iterations = 0
        t0 = self._timer()
        done = []
        seen = self.neighbours.take(segs, t_us * 1e-6 if t_s is None else t_s)
        for seg, neighbours in zip(segs, seen):
            rows = list(seg)
            groups = self._segment_groups(seg) if split_groups else [tuple(range(len(rows)))]
            try:
                result, corrections = compute_corrections([states[r] for r in rows], self.d[rows], groups,
                                                          self.params, self.seq, t_s, neighbours)
                self.neighbours.applied(result.neighbour_accepted)
            except (ValueError, np.linalg.LinAlgError) as exc:
                self.neighbours.applied(np.zeros(len(neighbours), dtype=bool))
                log.warning("constraint application failed at t = %.3f s (links %s): %s",
                            t_us * 1e-6 if t_s is None else t_s, [self.links[r].index + 1 for r in rows], exc)
                continue
            p[rows], v[rows], q[rows] = result.p, result.v, result.q
            P_seg = self.selection.restore_common(P_ekf[rows], result.P)
            P_corr[rows] = P_seg
            p_local[rows] = np.concatenate([r.p for r in result.local])
            corrected[rows] = True
            iterations = max(iterations, int(result.iterations.max()))
            done.append((seg, corrections, (result.p, result.v, result.q, P_seg)))
        done += self._bridged(self.selection.bridges, states, corrected, p, P_corr, done)
        self.step_times_ms.add((self._timer() - t0) * 1e3)
        for seg, corrections, result in done:
            self._send_corrections(seg, corrections, result)
        if done:
            self.seq = (self.seq + 1) & 0xFFFF or 1
        return ekf, p, v, q, p_local, iterations, corrected, (P_ekf, P_corr)

    def _bridged(self, bridges, states: list[LinkState], corrected: np.ndarray, p: np.ndarray, P: np.ndarray,
                 sent) -> list[tuple]:
        """The faulty neighbours of ``bridges`` (:class:`~.bridge.Bridge`) that nothing corrected,
        corrected along the link left out (:func:`~.bridge.bridge_correction`) from the healthy
        neighbour's state (at its own stamp: with its correction of this step added, when ``sent``,
        the step's ``(rows, corrections, result)``, has one): each as ``(rows, corrections, (p, v,
        q, P))`` to send; ``corrected``, ``p`` and ``P`` (the step log's) updated."""
        fixes = {r: c for rows, corrections, _ in sent for r, c in zip(rows, corrections)}
        out = []
        for b in bridges:
            if corrected[b.faulty]:
                continue
            healthy = states[b.healthy]
            fix = fixes.get(b.healthy)
            if fix is not None:
                healthy = replace(healthy, p_w_m=healthy.p_w_m + fix.dp_w_m, v_w_m_s=healthy.v_w_m_s + fix.dv_w_m_s,
                                  q_wxyz=quat_mul(quat_from_rotvec(fix.dtheta_w_rad), healthy.q_wxyz))
            corr, state = bridge_correction(states[b.faulty], healthy, self.d[[b.healthy, b.out, b.faulty]],
                                            b.faulty > b.out, self.seq)
            p[b.faulty], P[b.faulty], corrected[b.faulty] = state.p_w_m, state.P, True
            self.links[b.faulty].bridged_steps += 1
            one = (state.p_w_m[None], state.v_w_m_s[None], state.q_wxyz[None], state.P[None])
            out.append(((b.faulty,), [corr], one))
        self.bridged_steps += bool(out)
        return out

    def _logged_states(self, states: list[LinkState]):
        """``(p, v, q, w)`` of the links' states for the log: NaN for a silent link (its newest
        state is too old to say where it is)."""
        ekf = _stacked(states)
        for lk in self.links:
            if lk.status == "stale":
                for a in ekf:
                    a[lk.row] = np.nan
        return ekf

    def _observe(self, t_us: int, cycle_us: int) -> None:
        """``enabled = false``: log the links' EKF states at the step time, correct nothing."""
        ekf = _stacked([lk.state for lk in self.links])
        cycle = cycle_us if self.net is not None else -1
        p, v, q, _ = ekf
        P = np.array([lk.state.P for lk in self.links])
        self._record(t_us if cycle < 0 else cycle, cycle, ekf, p, v, q, p, 0, False, -1,
                     np.zeros(len(self.links), dtype=bool), float("nan"), (P, P))

    def _local_half(self, now_s: float, cycle: int) -> None:
        """Distributed mode: local constraint application at the cycle time on every part of the
        group (the whole group, or what a link left out or a cut joint left of it), the parts'
        boundaries out."""
        segs, _, nis_max = self.selection.plan(cycle, now_s, singles=True)
        states = [self.selection.step_state(lk) for lk in self.links]
        if not segs:  # no link usable: nothing to publish, every link on its own EKF
            ekf = self._logged_states(states)
            P = np.array([lk.state.P for lk in self.links])
            self._record(cycle, cycle, ekf, *ekf[:3], ekf[0], 0, False, -1, np.zeros(len(self.links), dtype=bool),
                         nis_max, (P, P))
            return
        t0 = self._timer()
        parts = []
        seen = self.neighbours.take(segs, cycle * 1e-6)
        try:
            for seg, neighbours in zip(segs, seen):
                rows = list(seg)
                parts.append((rows, local_step([states[r] for r in rows], self.d[rows], self.params, t=cycle * 1e-6,
                                               neighbours=neighbours)))
                self.neighbours.applied(parts[-1][1].neighbour_accepted)
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.neighbours.applied(np.zeros(sum(len(m) for m in seen[len(parts):]), dtype=bool))
            log.warning("local constraint application failed at t = %.3f s: %s", cycle * 1e-6, exc)
            return
        self.step_times_ms.add((self._timer() - t0) * 1e3)
        # (the links' reported covariances, for the log and the common GNSS error to put back)
        self._local[cycle] = (states, parts, nis_max, np.array([lk.state.P for lk in self.links]),
                              tuple(self.selection.bridges))
        last = len(self.links) - 1
        bounds = [PartBoundary(s.boundary.left_tip, s.boundary.right_tip, s.boundary.info_pv, s.boundary.tip_cov,
                               joins_left=rows[0] == 0, joins_right=rows[-1] == last) for rows, s in parts]
        # stamped when they go out, after the computation (the shift deadline runs from there)
        self.finish(self.net.local_parts(bounds, cycle, self.net.clock()))

    def finish(self, resolved) -> None:
        """Distributed mode: corrections for the cycles that ended (``resolved``, from the group
        link: with the leader's shift, or local-only)."""
        for res in resolved:
            entry = self._local.pop(res.cycle_us, None)
            for old in [c for c in self._local if c < res.cycle_us]:
                del self._local[old]
            if entry is None:
                continue
            states, parts, nis_max, P_reported, bridges = entry
            if len(res.parts) != len(parts):
                log.warning("cycle t = %.3f s: %d part(s) resolved for %d published; local-only", res.cycle_us * 1e-6,
                            len(res.parts), len(parts))
                res = replace(res, parts=tuple(PartShift(None, "parts mismatch") for _ in parts))
            ekf = self._logged_states(states)
            p, v, q = (a.copy() for a in ekf[:3])
            p_local = p.copy()
            P = P_reported.copy()
            corrected = np.zeros(len(self.links), dtype=bool)
            iterations = 0
            out = []
            for (rows, step), part in zip(parts, res.parts):
                if part.shift is None and part.reason:
                    log.debug("cycle t = %.3f s: links %s local-only (%s)", res.cycle_us * 1e-6,
                              [self.links[r].index + 1 for r in rows], part.reason)
                for a, b in zip(ekf, (step.p, step.v, step.q, step.w)):
                    a[rows] = b
                if len(rows) == 1 and part.shift is None:  # alone, and no neighbouring group joined it
                    lk = self.links[rows[0]]
                    lk.status = "alone"
                    lk.excluded["alone"] = lk.excluded.get("alone", 0) + 1
                    continue
                pp, vv, qq, PP, corrections = finish_step([states[r] for r in rows], step, part.shift, self.seq,
                                                          part.gain, part.cov)
                PP = self.selection.restore_common(P_reported[rows], PP)
                p[rows], v[rows], q[rows], P[rows], p_local[rows] = pp, vv, qq, PP, step.result.p
                corrected[rows] = True
                iterations = max(iterations, int(step.result.iterations))
                out.append((tuple(rows), corrections, (pp, vv, qq, PP)))
            out += self._bridged(bridges, states, corrected, p, P, out)
            for rows, corrections, result in out:
                self._send_corrections(rows, corrections, result)
            if out:
                self.seq = (self.seq + 1) & 0xFFFF or 1
            self._record(res.cycle_us, res.cycle_us, ekf, p, v, q, p_local, iterations, res.global_applied,
                         -1 if res.leader_group is None else res.leader_group + 1, corrected, nis_max, (P_reported, P))

    def _record(self, t_us: int, cycle_us: int, ekf, p, v, q, p_local, iterations: int, global_applied: bool,
                leader: int, corrected: np.ndarray, nis_max: float, P) -> None:
        """One step log row; ``ekf`` is ``(p, v, q, w)`` of the links' states the step started from
        (aligned to the cycle in distributed mode), ``p, v, q`` the corrected estimate (a link's
        EKF state where ``corrected`` is false), ``nis_max`` the largest joint NIS of the gate,
        ``P`` the ``(n, 9, 9)`` covariances ``(reported by the links, after the constraint
        application)`` (carried through the global step of eq. 6 when there was one:
        :func:`~companion.estimation.semi.shifted_covariance`), logged as their 3x3 position,
        velocity and attitude blocks."""
        pe, ve, qe, we = ekf
        self.latest = (p, q)
        row = {"t_sckf": t_us * 1e-6, "cycle_us": cycle_us, "p_ekf_sckf": pe, "v_ekf_sckf": ve, "q_ekf_sckf": qe,
               "w_sckf": we, "p_local_sckf": p_local, "p_corr_sckf": p, "v_corr_sckf": v, "q_corr_sckf": q,
               "iterations": iterations, "global_applied": global_applied, "leader": leader,
               "corrected_sckf": corrected, "nis_max_sckf": nis_max,
               "P_ekf_sckf": _blocks(P[0]), "P_corr_sckf": _blocks(P[1]),
               "home_offset_sckf": np.array(self._home(), dtype=float)}
        for key, value in row.items():
            self.log[key].append(value)

    def _send_corrections(self, rows: tuple[int, ...], corrections, result) -> None:
        """Links ``rows`` their corrections and corrected estimates, stamped on each link's own
        clock; ``result`` is ``(p, v, q, P)`` of those links, in their order."""
        p, v, q, P = result
        for j, (r, corr) in enumerate(zip(rows, corrections)):
            lk = self.links[r]
            t_link = lk.to_link_clock_us(usec(corr.ekf_time_s)) * 1e-6
            self._emit(CorrectionOut(lk.row, lk.system_id, replace(corr, ekf_time_s=t_link),
                                     LinkState(lk.index, t_link, p[j], v[j], q[j], lk.state.omega_b_rad_s, P[j])))

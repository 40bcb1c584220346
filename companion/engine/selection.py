"""Which links a step uses, and the state each takes part with (withholding before use).

A link is left out of a step when it is silent (its newest state more than :data:`LAG_LIMIT_US`
behind the step time, and nothing from it for that long on the companion's own clock: a link
whose states keep arriving is not silent because another link's stamps were forged ahead), on a
clock that does not share the time base (its newest state more than :data:`LAG_LIMIT_US` ahead of
the step time or :data:`OFF_BASE_LIMIT_US` behind it, however often it sends), its EKF is not usable, it is
back from a silence or a reboot and still waits its re-admission cycles, or the joint chi-square
gate (:mod:`companion.estimation.gate`) finds it inconsistent with its neighbours; the gate also
cuts inconsistent joints. The chain splits where links are left out or joints cut; every segment
of two or more links is corrected on its own, and a link left out gets no correction that cycle
(it flies on its own EKF). Why each link is out is counted (:data:`EXCLUSION_REASONS`).

A link that flags a GPS fault (``STATE_FLAG_GPS_FAULT``: its EKF rejects its fixes, or they
stopped) and that the gate finds at odds with its neighbours is not left out but takes part one
way: its position variance is raised by :data:`GPS_FAULT_POS_VAR_M2`, so the step puts it where
its neighbours say it is and leaves them unmoved (while it agrees with them it takes part as
usual, its dead-reckoned position still informative).

A link left out between a usable neighbour that flags a GPS fault and a usable, healthy one is a
:class:`~.bridge.Bridge` (:attr:`LinkSelection.bridges`): the step corrects the faulty neighbour's
position along it if nothing else corrects it.

The GNSS error common to every link (``gnss_common_pos_var_m2``) is taken out of the states the
step uses (no constraint sees it) and put back into the corrected covariances.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from ..corrections import align_states
from ..estimation.chain import ERR_P
from ..estimation.gate import gate_chain, segments
from ..messages import STATE_FLAG_EKF_OK, STATE_FLAG_GPS_FAULT, LinkState
from .bridge import Bridge
from .links import LAG_LIMIT_US, OFF_BASE_LIMIT_US, LinkTrack, LinkWarnings, usec

__all__ = ["LAG_LIMIT_US", "OFF_BASE_LIMIT_US", "EXCLUSION_REASONS", "GPS_FAULT_POS_VAR_M2", "LinkSelection"]

log = logging.getLogger(__name__)

#: Why a link took no part in a step: it is silent, or on a clock that does not share the time
#: base (``stale``: see the module docstring); its EKF is not usable; it is
#: back after a silence or a reboot and waits READMIT_CYCLES usable cycles; the joint gate found
#: it inconsistent with its neighbours (:mod:`companion.estimation.gate`); or it is usable but
#: alone in its segment.
EXCLUSION_REASONS = ("stale", "ekf", "returning", "gate", "alone")
#: Position variance added to the state of a link that flags a GPS fault [m^2] ((10 m)^2): the
#: constraint application then moves that link onto its neighbours and leaves them where they
#: are (their corrections change by about their variance over this, under 1e-5), so a glitching
#: GPS is corrected by the chain instead of pulling it.
GPS_FAULT_POS_VAR_M2 = 100.0


class LinkSelection:
    """The links of a step and their states as the step uses them, for the ``links`` of one
    engine (``d``: their tip vectors) under ``cfg`` (a :class:`~companion.config.CompanionConfig`).

    Counts: ``degraded`` steps (some link left out), ``withheld`` steps (no link corrected),
    ``common_mode_kept`` (link-steps whose position covariance was not larger than the common
    GNSS error); ``one_way``: the rows taking part one way in the last step (GPS fault);
    ``bridges``: the last step's links left out between a neighbour in GPS fault and a healthy one
    (:class:`~.bridge.Bridge`)."""

    def __init__(self, cfg, links: list[LinkTrack], d: np.ndarray, warnings: LinkWarnings):
        self.links = links
        self.d = d
        self.gate_params = cfg.gate
        self.clock_rate_max = cfg.clock_rate_max
        self.warnings = warnings
        c = cfg.gnss_common_pos_var_m2
        #: the GNSS error common to every link (CompanionConfig.gnss_common_pos_var_m2), or None
        self._common = np.diag([c[0], c[0], c[1]]) if c is not None and any(c) else None
        self.common_mode_kept = 0
        self.withheld = 0
        self.degraded = 0
        self.one_way: set[int] = set()
        self.bridges: list[Bridge] = []

    def plan(self, t_us: int, now_s: float, singles: bool = False) -> tuple[list[tuple[int, ...]], bool, float]:
        """Which of the links the step at ``t_us`` uses (see the module docstring). Returns the
        segments (rows, at least two consecutive links each; ``singles``: a usable link alone
        between links left out or cut joints is a segment too, for the global step of a group
        companion to join to the neighbouring group), whether every link is usable with no joint
        cut (``whole``), and the largest joint NIS. Each link's
        :attr:`~companion.engine.links.LinkTrack.status` says why it is out ("" if it is in)."""
        usable = []
        for lk in self.links:
            off_us = usec(lk.state.time_s) - t_us
            if (off_us > LAG_LIMIT_US or -off_us > OFF_BASE_LIMIT_US
                    or (-off_us > LAG_LIMIT_US and lk.quiet(now_s, LAG_LIMIT_US * 1e-6, self.clock_rate_max))):
                why = "stale"
                self.warnings.warn(lk, "stale", now_s, "newest state %.3f s from the step time: it stopped streaming, "
                                   "or its clock does not share the chain's time base; left out, the others go on",
                                   off_us * 1e-6)
            elif not lk.flags & STATE_FLAG_EKF_OK:
                why = "ekf"
            elif lk.readmit_cycles > 0:
                why = "returning"
                lk.readmit_cycles -= 1
            else:
                why = ""
            lk.status = why
            usable.append(not why)
        cut = [False] * (len(self.links) - 1)
        nis_max = float("nan")
        self.one_way = set()
        for run in segments(usable):
            rows = list(run)
            _, p, v, q = align_states([self.links[r].state for r in rows], t_us * 1e-6)
            w = np.array([self.links[r].state.omega_b_rad_s for r in rows])
            P = np.array([self.step_state(self.links[r]).P for r in rows])
            res = gate_chain(p, v, q, w, self.d[rows], P, self.gate_params)
            # A link that flags a GPS fault and disagrees with its neighbours is not left out: its
            # state is the suspect (its own firmware says so), so it takes part one way.
            suspects = {k for k, r in enumerate(rows) if self.links[r].flags & STATE_FLAG_GPS_FAULT
                        and (k in res.excluded or (k > 0 and res.cut[k - 1]) or (k < len(rows) - 1 and res.cut[k]))}
            if suspects:
                self.one_way.update(rows[k] for k in suspects)
                P = np.array([self.step_state(self.links[r]).P for r in rows])
                res = gate_chain(p, v, q, w, self.d[rows], P, self.gate_params)
            for j, c in enumerate(res.cut):
                cut[run[0] + j] = bool(c)
            for k in res.excluded:
                self.links[run[k]].status = "gate"
                usable[run[k]] = False
            if res.nis.size:
                nis_max = float(np.nanmax(np.append(res.nis, nis_max)))
        for r in self.one_way:
            self.links[r].gps_fault_steps += 1
        whole = all(usable) and not any(cut)
        self.bridges = self._bridges(usable)
        segs = segments(usable, cut, 1 if singles else 2)
        in_segment = {r for seg in segs for r in seg}
        for lk in self.links:
            if not lk.status and lk.row not in in_segment and not whole:
                lk.status = "alone"
            if lk.status:
                lk.excluded[lk.status] = lk.excluded.get(lk.status, 0) + 1
        if not whole:
            self.degraded += 1
            if not segs:
                self.withheld += 1
        return segs, whole, nis_max

    def _bridges(self, usable: list[bool]) -> list[Bridge]:
        """The links left out with a usable neighbour that flags a GPS fault on one side and a
        usable one that does not on the other (see the module docstring)."""
        out = []
        for r in range(1, len(self.links) - 1):
            if usable[r]:
                continue
            for faulty, healthy in ((r - 1, r + 1), (r + 1, r - 1)):
                if (usable[faulty] and usable[healthy] and self.links[faulty].flags & STATE_FLAG_GPS_FAULT
                        and not self.links[healthy].flags & STATE_FLAG_GPS_FAULT):
                    out.append(Bridge(r, faulty, healthy))
        return out

    def _common_removable(self, P: np.ndarray) -> bool:
        """Whether the configured common GNSS error can come out of ``P`` (its position block is larger)."""
        return self._common is not None and np.linalg.eigvalsh(P[ERR_P, ERR_P] - self._common).min() > 0.0

    def step_state(self, lk: LinkTrack) -> LinkState:
        """``lk``'s state as the step uses it: without the GNSS error common to all links
        (:meth:`restore_common` puts it back), and one way (position variance raised by
        :data:`GPS_FAULT_POS_VAR_M2`) when :meth:`plan` found its flagged GPS fault at odds with
        its neighbours, so the step moves it onto them and leaves them unmoved."""
        common = self._common_removable(lk.state.P)
        if lk.row not in self.one_way and not common:
            return lk.state
        P = lk.state.P.copy()
        if common:
            P[ERR_P, ERR_P] -= self._common
        if lk.row in self.one_way:
            P[ERR_P, ERR_P] += GPS_FAULT_POS_VAR_M2 * np.eye(3)
        return replace(lk.state, P=P)

    def restore_common(self, P_reported: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The corrected covariances ``P`` with the common GNSS error that :meth:`step_state`
        took out of the links' reported ones, ``P_reported`` (same order), put back."""
        if self._common is None:
            return P
        P = np.array(P, dtype=float)
        for j, Pr in enumerate(P_reported):
            if self._common_removable(Pr):
                P[j][ERR_P, ERR_P] += self._common
            else:
                self.common_mode_kept += 1
                if self.common_mode_kept == 1:
                    log.warning("a link's position covariance is not larger than gnss_common_pos_var_m2: it keeps "
                                "its covariance as reported (its EKF does not report the receiver's bias?)")
        return P

"""Admission of link states: the time base and plausibility before use.

Every state is moved onto the engine's time base and checked before anything uses it:

* time base ``gps`` (real Pixhawks count from their own boot): each link's SYSTEM_TIME gives the
  offset of its boot clock to GPS time (median of its last :data:`CLOCK_SAMPLES` reports, which
  follows crystal drift); stamps are moved onto GPS time on arrival (and back onto the link's
  clock in what is sent to it, :meth:`~companion.engine.links.LinkTrack.to_link_clock_us`); a
  link is not used before its offset is known. With ``flight_controller`` the links' clocks are
  the time base;
* a state whose stamp is not newer than the link's last (a replay) or further ahead than the
  link's clock can have run (:mod:`companion.plausibility`) is rejected and counted, and never
  moves the cycle clock; a link silent for a while that comes back on a new clock has rebooted;
  a link back from a silence (or a reboot) is re-admitted after :data:`READMIT_CYCLES` usable
  cycles (the step counts them down).

:class:`Admission` owns the cycle clock (:attr:`Admission.fc_time_us`), which every decision of
the engine runs on: the second newest of the links' newest stamps on the time base (the newest
while one link is heard), so that no single link, whose states may be forged ahead or whose
clock may be off the time base, moves it for the others.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from ..messages import STATE_FLAG_ARMED, LinkState
from ..plausibility import StampVerdict
from .links import OFF_BASE_LIMIT_US, LinkTrack, LinkWarnings, usec

__all__ = ["READMIT_CYCLES", "CLOCK_SAMPLES", "Admission"]

log = logging.getLogger(__name__)

#: Usable cycles a link back from a silence of ``reboot_silence_s`` or more (or a reboot) waits
#: before it is constrained again (its EKF may still be settling).
READMIT_CYCLES = 10
#: SYSTEM_TIME reports whose median is a link's boot-to-GPS clock offset.
CLOCK_SAMPLES = 5


class Admission:
    """The time base and the plausibility checks of ``cfg`` (a
    :class:`~companion.config.CompanionConfig`), rejections warned through ``warnings``."""

    def __init__(self, cfg, warnings: LinkWarnings, links: list[LinkTrack]):
        self.cfg = cfg
        self.warnings = warnings
        self.links = links
        #: the cycle clock on the time base [us] (:meth:`_move_cycle_clock`)
        self.fc_time_us = 0

    def on_system_time(self, lk: LinkTrack, time_unix_us: int, time_boot_ms: int) -> None:
        """``gps`` time base: the link's boot-to-GPS offset from SYSTEM_TIME."""
        if self.cfg.time_base != "gps":
            return
        if time_unix_us <= 0:
            if lk.offset_us is None and not lk.gps_wait_logged:
                log.info("link %d: no GPS time yet (SYSTEM_TIME.time_unix_usec = 0): waiting", lk.index + 1)
                lk.gps_wait_logged = True
            return
        sample = int(time_unix_us) - int(time_boot_ms) * 1000
        if lk.offset_us is not None and abs(sample - lk.offset_us) > 1_000_000:
            # the boot clock jumped (a reboot): the old samples describe another clock
            log.warning("link %d: its boot clock moved %.3f s against GPS time (a reboot): offset re-learnt",
                        lk.index + 1, (lk.offset_us - sample) * 1e-6)
            lk.clock_samples_us = []
        lk.clock_samples_us = (lk.clock_samples_us + [sample])[-CLOCK_SAMPLES:]
        first = lk.offset_us is None
        lk.offset_us = int(np.median(lk.clock_samples_us))
        if first:
            log.info("link %d: boot clock + %.3f s = GPS time", lk.index + 1, lk.offset_us * 1e-6)

    def on_state(self, lk: LinkTrack, state: LinkState, flags: int, now_s: float, correction_seq: int = 0,
                 correction_latency_us: int = 0) -> bool:
        """Admit a validated state of ``lk`` (stamped on the link's clock) with the flags and the
        correction it reports: on the time base, plausible, then kept in ``lk``. ``False``: not
        usable yet (no GPS time offset for this link, or its stamp was rejected: then nothing it
        carries is used, flags and reported latency included)."""
        if self.cfg.time_base == "gps":
            if lk.offset_us is None:
                return False
            state = replace(state, time_s=(usec(state.time_s) + lk.offset_us) * 1e-6)
        stamp_us = usec(state.time_s)
        verdict = lk.stamps.check(stamp_us, now_s)
        if verdict in (StampVerdict.REPLAY, StampVerdict.FUTURE):
            lk.stamp_rejected_s = self.fc_time_us * 1e-6  # its flags are not believed for a while
        if verdict is StampVerdict.REPLAY:
            lk.replayed += 1
            self.warnings.warn(lk, "replay", now_s, "state stamped %.3f s, not newer than its last (%.3f s): a "
                               "replay or a reordered frame", stamp_us * 1e-6, lk.stamps.last_us * 1e-6)
            return False
        if verdict is StampVerdict.FUTURE:
            lk.future += 1
            self.warnings.warn(lk, "future", now_s, "state stamped %.3f s, %.3f s after its last: further than "
                               "its clock can have run", stamp_us * 1e-6, (stamp_us - lk.stamps.last_us) * 1e-6)
            return False
        if verdict is StampVerdict.REBASED:
            lk.reboots += 1
            lk.was_armed = False  # (a new power-on: its rotors off until armed again)
            lk.readmit_cycles = READMIT_CYCLES
            log.warning("link %d: silent, then back on a new clock (%.3f s): rebooted; re-admitted after %d usable "
                        "cycles", lk.index + 1, stamp_us * 1e-6, READMIT_CYCLES)
            if lk.loss is not None:
                lk.loss.restart()
        elif lk.last_state_s is not None and now_s - lk.last_state_s >= self.cfg.reboot_silence_s:
            lk.readmit_cycles = READMIT_CYCLES
            log.warning("link %d: back after %.1f s of silence; re-admitted after %d usable cycles", lk.index + 1,
                        now_s - lk.last_state_s, READMIT_CYCLES)
        if correction_seq != lk.correction_seq and correction_seq > 0:
            lk.correction_seq = correction_seq
            lk.latencies_ms.add(correction_latency_us * 1e-3)
            lk.latency_window_ms.append(correction_latency_us * 1e-3)
        if lk.last_state_s is not None and now_s - lk.last_state_s >= self.cfg.carry_silence_s:
            lk.was_armed = False  # (silent as long as a link the chain carries: it may have powered off and on)
        lk.flags = flags
        lk.disarmed_states = 0 if flags & STATE_FLAG_ARMED else lk.disarmed_states + 1
        if flags & STATE_FLAG_ARMED:
            lk.was_armed, lk.disarm_logged = True, False
        lk.state = state
        lk.states += 1
        if lk.loss is not None:
            lk.loss.on_stamp(stamp_us)
        lk.last_state_s = now_s
        self._move_cycle_clock(now_s)
        return True

    def _move_cycle_clock(self, now_s: float) -> None:
        """The cycle clock to the second newest of the newest stamps of the links heard within
        ``carry_silence_s`` (on the companion's clock; the newest while only one is heard), if
        that is later: a link whose stamps are forged ahead, a frame at a time within the stamp
        margin or on another clock, moves it no further than the newest of the others. A link
        more than :data:`~.links.OFF_BASE_LIMIT_US` behind it (rebooted onto its boot clock)
        does not hold it back."""
        cfg, floor = self.cfg, self.fc_time_us - OFF_BASE_LIMIT_US
        heard = sorted((t for t in (usec(lk.state.time_s) for lk in self.links if lk.state is not None
                                    and not lk.quiet(now_s, cfg.carry_silence_s, cfg.clock_rate_max)) if t >= floor),
                       reverse=True)
        if heard:
            self.fc_time_us = max(self.fc_time_us, heard[min(1, len(heard) - 1)])

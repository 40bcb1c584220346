"""The firmware's report of its rotors' thrust limit (pure: times and the allocation's status are
passed in).

At the limit the allocation (:mod:`.allocation`) gives the link less than its controller asks
for: a wrench beyond the rotors is scaled onto them (``AllocationResult.scale`` below 1), the
fade (2.17) is held back, or, with ``scale_to_limit`` off, commands are clipped
(``AllocationResult.saturated``). The link then cannot follow its targets fully: it sags or
tips, and a pilot or the companion should know. ArduCopter warns "Potential Thrust Loss" after
a second with a motor at full output; PX4 logs ``control_allocator_status`` (the unallocated
thrust and torque). :class:`ThrustLimit` turns the per-tick status into episodes:

* **fault** ("Rotors at thrust limit, wrench 87%") once the link has been at the limit for
  ``warn_after_s`` without a break (a tick or two at the limit in a gust is not worth a
  message);
* **recovered** ("Rotors within limit after 1.4 s") once it has been within it for
  ``clear_after_s``.

It counts the time at the limit (every tick, reported or not), the episodes and the smallest
scale, for the vehicle's summary.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.configfile import require_positive

from .events import StatusEvent

__all__ = ["ThrustLimitConfig", "ThrustLimit"]


@dataclass(frozen=True)
class ThrustLimitConfig:
    """``warn_after_s``: at the limit this long without a break reports it; ``clear_after_s``:
    within it this long ends the episode."""

    warn_after_s: float = 0.25
    clear_after_s: float = 0.5

    def __post_init__(self) -> None:
        require_positive(self, "warn_after_s", "clear_after_s")


class ThrustLimit:
    """See the module docstring; feed it every allocation tick (:meth:`on_tick`)."""

    def __init__(self, config: ThrustLimitConfig = ThrustLimitConfig()):
        self.config = config
        self.at_limit_s = 0.0  # every tick at the limit
        self.episodes = 0  # reported ones
        self.min_scale = 1.0  # over the whole flight
        self.active = False  # an episode reported and not yet ended
        self._since_s: float | None = None  # the current run of ticks at the limit began
        self._within_since_s: float | None = None  # ... of ticks within it (while active)
        self._episode_s = 0.0  # the active episode's start
        self._episode_scale = 1.0

    @property
    def quiet(self) -> bool:
        """No episode and no run of ticks at the limit: a tick within the limit changes nothing
        (what lets the vehicle's lockstep loop leave such ticks out, :meth:`~link_firmware_sim.
        firmware.LinkFirmware.on_hil_loop`)."""
        return not self.active and self._since_s is None and self._episode_scale == 1.0

    def on_tick(self, t_s: float, dt_s: float, at_limit: bool, scale: float = 1.0) -> list[StatusEvent]:
        """One allocation at ``t_s`` (``dt_s`` since the last): ``at_limit`` (saturated) and its
        ``scale``. A tick without an allocation (disarmed) is one within the limit."""
        if not (math.isfinite(t_s) and math.isfinite(dt_s) and math.isfinite(scale)):
            raise ValueError(f"thrust limit: non-finite tick ({t_s!r}, {dt_s!r}, {scale!r})")
        cfg = self.config
        if at_limit:
            self.at_limit_s += max(dt_s, 0.0)
            self.min_scale = min(self.min_scale, scale)
            self._within_since_s = None
            if self._since_s is None:
                self._since_s = t_s
            if self.active:
                self._episode_scale = min(self._episode_scale, scale)
                return []
            self._episode_scale = min(self._episode_scale, scale)
            if t_s - self._since_s >= cfg.warn_after_s:
                self.active, self._episode_s = True, self._since_s
                self.episodes += 1
                return [StatusEvent("fault", f"Rotors at thrust limit, wrench {100.0 * self._episode_scale:.0f}%")]
            return []
        self._since_s = None
        if not self.active:
            self._episode_scale = 1.0
            return []
        if self._within_since_s is None:
            self._within_since_s = t_s
        if t_s - self._within_since_s >= cfg.clear_after_s:
            self.active = False
            length = self._within_since_s - self._episode_s
            self._within_since_s, self._episode_scale = None, 1.0
            return [StatusEvent("recovered", f"Rotors within limit after {length:.1f} s")]
        return []

    def report(self) -> dict:
        return {"at_limit_s": round(self.at_limit_s, 3), "episodes": self.episodes,
                "min_scale": round(self.min_scale, 4), "at_limit_now": self.active}

"""What the firmware's pure parts report to its shell: a :class:`StatusEvent` per transition
(GPS health, the rotors' thrust limit), sent by a vehicle as STATUSTEXT to every link and logged
in batch mode."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["StatusEvent", "EVENT_KINDS"]

#: the kinds, by severity: ``fault`` (MAV_SEVERITY_WARNING), ``reset`` (CRITICAL), ``recovered`` (INFO)
EVENT_KINDS = ("fault", "reset", "recovered")


@dataclass(frozen=True)
class StatusEvent:
    kind: str  # one of EVENT_KINDS
    text: str  # a STATUSTEXT (at most 50 characters)

    def __post_init__(self) -> None:
        if self.kind not in EVENT_KINDS:
            raise ValueError(f"event kind {self.kind!r}: one of {EVENT_KINDS}")
        if len(self.text) > 50:
            raise ValueError(f"STATUSTEXT of {len(self.text)} characters (at most 50): {self.text!r}")

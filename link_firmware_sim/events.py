"""What the firmware's pure parts report to its shell: a :class:`StatusEvent` per transition
(GPS health, the rotors' thrust limit), sent by a vehicle as STATUSTEXT to every link and logged
in batch mode."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["StatusEvent", "EVENT_KINDS", "SEVERITY", "statustext_arrays"]

#: the kinds, by severity: ``fault`` (MAV_SEVERITY_WARNING), ``reset`` (CRITICAL), ``recovered`` (INFO)
EVENT_KINDS = ("fault", "reset", "recovered")
#: each kind's STATUSTEXT severity (MAV_SEVERITY: 2 critical, 4 warning, 6 info)
SEVERITY = {"fault": 4, "reset": 2, "recovered": 6}


@dataclass(frozen=True)
class StatusEvent:
    kind: str  # one of EVENT_KINDS
    text: str  # a STATUSTEXT (at most 50 characters)

    def __post_init__(self) -> None:
        if self.kind not in EVENT_KINDS:
            raise ValueError(f"event kind {self.kind!r}: one of {EVENT_KINDS}")
        if len(self.text) > 50:
            raise ValueError(f"STATUSTEXT of {len(self.text)} characters (at most 50): {self.text!r}")


def statustext_arrays(texts) -> dict[str, np.ndarray]:
    """A run's STATUSTEXTs ``(time [s], link (from 1), MAV_SEVERITY, text)`` as a log's arrays, in
    time order: ``statustext_t``, ``statustext_link``, ``statustext_severity``, ``statustext_text``."""
    texts = sorted(texts, key=lambda x: x[0])
    return {"statustext_t": np.array([x[0] for x in texts], dtype=float),
            "statustext_link": np.array([x[1] for x in texts], dtype=np.int64),
            "statustext_severity": np.array([x[2] for x in texts], dtype=np.int64),
            "statustext_text": np.array([str(x[3]) for x in texts], dtype=np.str_)}

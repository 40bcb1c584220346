"""What the companion engine asks its caller to do: the outputs of
:meth:`~companion.engine.CompanionEngine.poll`, each for the caller to carry out (encode and
send, or hand to an in-process firmware)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from ..messages import Correction, LinkState, PoseTarget

__all__ = ["Command", "CorrectionOut", "TargetOut", "CommandOut", "Heartbeat", "HealthDue"]


class Command(Enum):
    """What a :class:`CommandOut` asks a link: arm, or stream its state at a rate."""

    ARM = "arm"
    STREAM = "stream"


@dataclass(frozen=True)
class CorrectionOut:
    """Send link ``row`` its correction (dialect mode) or its corrected estimate (standard mode:
    external vision). Both are stamped on the link's own clock."""

    row: int
    system_id: int
    correction: Correction
    corrected: LinkState


@dataclass(frozen=True)
class TargetOut:
    """Send link ``row`` its pose target for ``time_us`` on the link's own clock."""

    row: int
    system_id: int
    time_us: int
    target: PoseTarget


@dataclass(frozen=True)
class CommandOut:
    """Send link ``row`` a command: arm, or stream its state message every ``interval_us``."""

    row: int
    system_id: int
    command: Command
    interval_us: float = 0.0


@dataclass(frozen=True)
class Heartbeat:
    """The companion's 1 Hz heartbeat is due (on every link)."""


@dataclass(frozen=True)
class HealthDue:
    """The periodic health report is due (:meth:`~companion.engine.CompanionEngine.health_rows`
    over ``period_s``)."""

    period_s: float

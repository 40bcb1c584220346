"""What a group's global-step node takes in and gives out (:mod:`.leader`): the boundary of each
part of the group, how each part's cycle ended, and the actions the daemon carries out (pure
dataclasses)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.messages import GlobalShift, GroupBoundaryReport

__all__ = ["PartBoundary", "PartShift", "Resolution", "Actions"]


@dataclass(frozen=True)
class PartBoundary:
    """One part of this group after its local step: its tips, ``Lambda``, tip covariance and
    whether its ends are the group's (:class:`~companion.messages.GroupBoundaryReport`)."""

    left_tip_pv_w: np.ndarray
    right_tip_pv_w: np.ndarray
    info_pv: np.ndarray
    tip_cov_pv: np.ndarray | None = None
    joins_left: bool = True
    joins_right: bool = True


@dataclass(frozen=True)
class PartShift:
    """How one part's cycle ended: ``shift`` (6,) from the leader, or ``None`` (local-only:
    ``reason`` says why), with the shift's covariance terms (``gain`` (6, 12), ``cov`` (6, 6):
    :func:`~companion.estimation.semi.shifted_covariance`) when every entry of its run sent them."""

    shift: np.ndarray | None
    reason: str = ""
    gain: np.ndarray | None = None
    cov: np.ndarray | None = None


@dataclass(frozen=True)
class Resolution:
    """How this group's pending cycle ended: per part it published (``parts``, in chain order) its
    :class:`PartShift`; ``leader_group`` whose shift it was (``None``: none). ``shift``,
    ``reason``, ``shift_gain`` and ``shift_cov`` are the first part's (the whole group's when it
    was not split)."""

    cycle_us: int
    leader_group: int | None
    parts: tuple[PartShift, ...]

    @property
    def shift(self) -> np.ndarray | None:
        return self.parts[0].shift

    @property
    def reason(self) -> str:
        return self.parts[0].reason

    @property
    def shift_gain(self) -> np.ndarray | None:
        return self.parts[0].gain

    @property
    def shift_cov(self) -> np.ndarray | None:
        return self.parts[0].cov

    @property
    def global_applied(self) -> bool:
        """Whether any part was joined to a neighbour by the leader's shift."""
        return any(p.shift is not None for p in self.parts)


@dataclass
class Actions:
    """What the daemon must do: publish ``boundaries`` / ``shifts``, finish ``resolved`` cycles."""

    boundaries: list[GroupBoundaryReport] = field(default_factory=list)
    shifts: list[GlobalShift] = field(default_factory=list)
    resolved: list[Resolution] = field(default_factory=list)

    @property
    def boundary(self) -> GroupBoundaryReport | None:
        """The first boundary to publish (``None``: none)."""
        return self.boundaries[0] if self.boundaries else None

    def merge(self, other: Actions) -> Actions:
        self.boundaries += other.boundaries
        self.shifts += other.shifts
        self.resolved += other.resolved
        return self

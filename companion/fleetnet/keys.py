"""Zenoh key expressions of a fleet (DESIGN.md sec. 3), all under one prefix; groups are 1-based in keys."""

from __future__ import annotations

__all__ = ["boundary_key", "boundary_pattern", "passive_key", "passive_pattern", "home_key", "home_pattern",
           "shift_key", "target_key", "alive_key", "alive_pattern", "group_of_key", "neighbour_key",
           "neighbour_pattern", "load_key", "load_pattern"]


def boundary_key(prefix: str, group: int) -> str:
    """Where 0-based ``group`` publishes its boundary (:class:`~companion.messages.GroupBoundaryReport`)."""
    return f"{prefix}/group/{group + 1}/boundary"


def boundary_pattern(prefix: str) -> str:
    return f"{prefix}/group/*/boundary"


def passive_key(prefix: str, group: int) -> str:
    """Where 0-based ``group`` publishes which of its links are carried
    (:class:`~companion.messages.GroupPassiveLinks`)."""
    return f"{prefix}/group/{group + 1}/passive"


def passive_pattern(prefix: str) -> str:
    return f"{prefix}/group/*/passive"


def home_key(prefix: str, group: int) -> str:
    """Where 0-based ``group`` publishes the chain's home it holds (:class:`~companion.messages.ChainHome`)."""
    return f"{prefix}/group/{group + 1}/home"


def home_pattern(prefix: str) -> str:
    return f"{prefix}/group/*/home"


def shift_key(prefix: str) -> str:
    """Where the leader publishes :class:`~companion.messages.GlobalShift`."""
    return f"{prefix}/global/shift"


def target_key(prefix: str) -> str:
    """Where the leader publishes the CPG targets (:class:`~companion.messages.ChainTargets`)."""
    return f"{prefix}/cpg/target"


def alive_key(prefix: str, group: int) -> str:
    """Liveliness token of 0-based ``group``'s companion."""
    return f"{prefix}/group/{group + 1}/alive"


def alive_pattern(prefix: str) -> str:
    return f"{prefix}/group/*/alive"


def group_of_key(prefix: str, key: str) -> int | None:
    """0-based group of a ``<prefix>/group/<g>/...`` key, ``None`` if it is not one."""
    head = f"{prefix}/group/"
    if not key.startswith(head):
        return None
    chunk = key[len(head):].split("/", 1)[0]
    return int(chunk) - 1 if chunk.isdigit() and int(chunk) >= 1 else None


def neighbour_key(prefix: str, link: int) -> str:
    """Where the camera of 0-based chain ``link`` publishes what it sees of its neighbours
    (:class:`~companion.messages.NeighbourPose`)."""
    return f"{prefix}/link/{link + 1}/neighbour"


def neighbour_pattern(prefix: str) -> str:
    return f"{prefix}/link/*/neighbour"


def load_key(prefix: str, vehicle: int) -> str:
    """Where the cameras of 0-based carrying ``vehicle`` publish their measurements of the slung load
    (:class:`~companion.load.model.LoadObservation`)."""
    return f"{prefix}/vehicle/{vehicle + 1}/load"


def load_pattern(prefix: str) -> str:
    return f"{prefix}/vehicle/*/load"

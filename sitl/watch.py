"""Observers of the simulations a process runs: a live view attaches to each one as it starts.

:class:`~sitl.runner.BatchRunner` and :class:`~sitl.fleet.harness.FleetHarness` call
:func:`announce` with themselves at the end of their start-up, and a batch flight's cameras
(:class:`~sitl.cameras.flight.FlightCameras`) once they render; a callback registered with
:func:`watching` gets them (e.g. to add a tick hook or a frame consumer). No callback: nothing
happens.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["watching", "announce"]

_callbacks: list[Callable] = []


@contextmanager
def watching(callback: Callable) -> Iterator[None]:
    """``callback(sim)`` for every simulation started within the ``with`` block."""
    _callbacks.append(callback)
    try:
        yield
    finally:
        _callbacks.remove(callback)


def announce(sim) -> None:
    """Tell every watcher that ``sim`` (a runner or a fleet harness) has started."""
    for callback in tuple(_callbacks):
        callback(sim)

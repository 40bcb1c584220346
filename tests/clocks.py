"""A clock a test moves by hand, for code that takes its clock as an argument."""

from __future__ import annotations


class FakeClock:
    """Seconds that pass only when the test says: call it for the time, add to ``t`` to move it."""

    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t

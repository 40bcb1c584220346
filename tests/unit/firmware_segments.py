"""A firmware flight segment's inputs, shared by the fast paths' oracle tests."""

from __future__ import annotations

import numpy as np

from companion.estimation.so3 import quat_normalize
from companion.messages import Correction, PoseTarget

__all__ = ["flight_events"]


def flight_events(rng, k: int, p0, q0, *, targets_until: int, far_at: int, gps_every: int,
                   attitude_every: int) -> list:
    """The firmware calls ``(name, args)`` of tick ``k`` (time ``k * 2 ms``) of a flight segment: a
    new target every 50 ticks before ``targets_until``, one 30 m off at ``far_at`` (the rotors at
    their limit), corrections, GPS fixes and attitude references."""
    t = k * 0.002
    events = []
    if k % 50 == 1 and k < targets_until:
        target = PoseTarget(p0 + rng.normal(size=3) * 0.2, quat_normalize(q0 + rng.normal(size=4) * 0.05),
                            *(rng.normal(size=(6, 3)) * 0.3))
        events.append(("set_target", (t, target)))
    if k == far_at:
        events.append(("set_target", (t, PoseTarget.hold(p0 + np.array([30.0, -10.0, 20.0]), q0))))
    if k % 97 == 3:
        events.append(("on_correction", (t, Correction(0, t - 0.01, rng.normal(size=3) * 0.05,
                                                         rng.normal(size=3) * 0.02, rng.normal(size=3) * 0.005,
                                                         seq=k))))
    if k % gps_every == 0:
        events.append(("on_gps", (t, p0 + rng.normal(size=3) * 0.3, rng.normal(size=3) * 0.05)))
    if k % attitude_every == 0:
        events.append(("on_attitude", (t, quat_normalize(q0 + rng.normal(size=4) * 0.01))))
    return events

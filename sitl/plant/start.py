"""Where the simulated chain starts (the physical skeleton itself is :mod:`companion.skeleton.body`)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["StartPose"]


@dataclass(frozen=True)
class StartPose:
    """Where the chain starts: centre of the chain [m], heading and pitch of the straight chain."""

    center_w_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    on_ground: bool = True

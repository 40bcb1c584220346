"""The slung-load scenario's configuration: a :class:`~sitl.scenario.Scenario` with
``kind = "slung_load"``, ``trajectory.kind = "formation"`` and a ``[load]`` table
(:class:`~companion.load.config.LoadConfig`: the box, the cables, the marker's id, the filters'
tuning and the formation's circle, which the companion flies). Here: the vehicles' cameras, the
marker on the load and the clutter kept clear of the flight. No OpenCV and no MuJoCo here: the
file loads and validates on any install.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from companion.estimation.so3 import rotmat_to_quat
from companion.load.config import LoadConfig
from companion.load.model import Pose3
from sitl.scenario import Scenario, load_scenario

__all__ = ["SlungLoadScenario", "load_slung_scenario"]

#: a margin about the vehicles' nominal places that clutter keeps clear of [m]
FLIGHT_MARGIN_M = 0.7


@dataclass(frozen=True)
class SlungLoadScenario(Scenario):
    """Three (or more) unjoined vehicles of this stack carrying a box by cables (``kind =
    "slung_load"``, ``[load]``). The companion's schema checks the formation's part
    (:class:`~companion.config.CompanionSetup`: ``trajectory.kind = "formation"``, one vehicle
    per cable, ``companion.enabled = false``); here, what the simulation adds."""

    kind: Literal["slung_load"] = "slung_load"
    load: LoadConfig = field(default_factory=LoadConfig)

    def __post_init__(self) -> None:
        Scenario.__post_init__(self)  # (with a [load]: trajectory.kind "formation", n_links, companion.enabled)
        n = self.load.n
        if n < 3:
            raise ValueError("the load's pose needs three or more vehicles")
        if self.start.on_ground:
            raise ValueError("start.on_ground must be false: the flight starts hovering with the load hanging")
        marker = next((m for m in self.markers if m.id == self.load.marker_id), None)
        if marker is None or marker.body != "load":
            raise ValueError(f"load.marker_id {self.load.marker_id}: needs a [[markers]] entry with that id on "
                             "body \"load\"")
        for i, c in enumerate(self.cameras):
            if not (c.body.startswith("link") and 0 <= c.vehicle_index() < n):
                raise ValueError(f"cameras[{i}].body: a vehicle (link1..link{n}), got {c.body!r}")
        clutter = self.scene.clutter
        if clutter.active:
            reach = self.flight_reach_m()
            c = np.asarray(self.load.formation.start_w_m) - (self.load.formation.circle_radius_m, 0.0)
            if np.linalg.norm(np.asarray(clutter.center_w_m) - c) + reach > clutter.inner_radius_m:
                raise ValueError(f"scene.clutter: the ring's inside (radius {clutter.inner_radius_m:g} m about "
                                 f"{list(clutter.center_w_m)}) must hold the flight: {reach:.2f} m about the "
                                 f"formation's circle centre {c.tolist()}")

    def flight_reach_m(self) -> float:
        """How far from the formation circle's centre the vehicles fly (horizontally): the circle's
        radius, the formation's, and a margin of :data:`FLIGHT_MARGIN_M` for tracking errors
        and the rotors."""
        f = self.load.formation
        return f.circle_radius_m + f.formation_radius_m + FLIGHT_MARGIN_M

    def marker_in_load(self) -> Pose3:
        m = next(m for m in self.markers if m.id == self.load.marker_id)
        return Pose3(np.asarray(m.pos_b_m, dtype=float), rotmat_to_quat(m.R_b_m()))

    def cameras_in_body(self) -> dict[str, Pose3]:
        return {c.name: Pose3(np.asarray(c.pos_b_m, dtype=float), rotmat_to_quat(c.R_b_c())) for c in self.cameras}


def load_slung_scenario(path: str | Path, **overrides) -> SlungLoadScenario:
    """Read a slung-load scenario (:class:`~companion.configfile.ConfigError` if invalid), tuned for
    its sensors as every scenario is (:func:`~sitl.scenario.load_scenario`)."""
    return load_scenario(path, SlungLoadScenario, **overrides)

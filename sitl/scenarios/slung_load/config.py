"""The slung-load scenario's configuration: a :class:`~sitl.scenario.Scenario` with
``kind = "slung_load"`` and a ``[load]`` table. No OpenCV and no MuJoCo here: the file loads and
validates on any install.

``[load]`` (:class:`LoadConfig`): the box (mass, size, optional principal inertia), the cables
(one length per vehicle; attached on the box's top face at ``attach_radius_m`` from its centre,
towards each vehicle, and at ``vehicle_attach_b_m`` on each vehicle), the marker on the load
(``marker_id``: one of ``[[markers]]``, on body ``"load"``), the PnP method the filters use,
the filters' tuning (``[load.filter]``, :class:`~companion.load.estimate.LoadFilterConfig`)
and the formation's circle (``[load.formation]``,
:class:`~.formation.CircleFormationConfig`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from companion.config import load_setup
from companion.configfile import require_positive
from companion.estimation.so3 import rotmat_to_quat
from companion.load.estimate import LoadFilterConfig
from companion.load.model import LoadParams, Pose3
from companion.vision.config import PNP_METHOD_NAMES, CornerRefinement, PnpMethod
from sitl.scenario import Scenario, with_rate_noise

from .formation import CircleFormationConfig

__all__ = ["LoadConfig", "SlungLoadScenario", "load_slung_scenario"]

#: a margin about the vehicles' nominal places that clutter keeps clear of [m]
FLIGHT_MARGIN_M = 0.7


@dataclass(frozen=True)
class LoadConfig:
    """The slung load, its cables and the formation that carries it (module docstring)."""

    mass_kg: float = 1.0
    size_m: tuple[float, float, float] = (0.5, 0.5, 0.2)
    #: principal moments about the centre of mass [kg m^2]; ``None``: a solid box of ``size_m``
    inertia_b_kg_m2: tuple[float, float, float] | None = None
    cable_length_m: tuple[float, ...] = (1.5, 1.5, 1.5)
    attach_radius_m: float = 0.24
    vehicle_attach_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: the cable's limit constraint (MuJoCo ``solreflimit``: time constant [s], damping ratio)
    cable_solref: tuple[float, float] = (0.01, 1.0)
    cable_width_m: float = 0.004
    marker_id: int = 0
    #: the detector's corner refinement (:class:`~companion.vision.config.DetectorConfig`; what each does
    #: on this scenario's frames: ``python -m sitl.bench corners``)
    corner_refinement: CornerRefinement = "subpix"
    pnp_method: PnpMethod = "ippe_square"
    #: the PnP covariance's corner-noise floor [px] (:class:`~companion.vision.config.PipelineConfig`)
    sigma_floor_px: float = 0.3
    #: metrics leave out the first seconds (the filters' convergence from the rigging's prior)
    settle_s: float = 2.0
    #: the vehicles' samples (firmware EKF position, velocity, covariance) to the filters [Hz]
    vehicle_rate_hz: float = 50.0
    filter: LoadFilterConfig = field(default_factory=LoadFilterConfig)
    formation: CircleFormationConfig = field(default_factory=CircleFormationConfig)

    def __post_init__(self) -> None:
        require_positive(self, "mass_kg", "attach_radius_m", "cable_width_m", "vehicle_rate_hz", "sigma_floor_px")
        if min(self.size_m) <= 0:
            raise ValueError(f"size_m must be positive, got {self.size_m}")
        if self.inertia_b_kg_m2 is not None and min(self.inertia_b_kg_m2) <= 0:
            raise ValueError(f"inertia_b_kg_m2 must be positive, got {self.inertia_b_kg_m2}")
        if len(self.cable_length_m) != self.formation.n_vehicles or min(self.cable_length_m) <= 0:
            raise ValueError(f"cable_length_m: one positive length per vehicle ({self.formation.n_vehicles}), "
                             f"got {self.cable_length_m}")
        if self.attach_radius_m >= self.formation.formation_radius_m:
            raise ValueError("attach_radius_m must be smaller than formation.formation_radius_m")
        if self.pnp_method not in PNP_METHOD_NAMES:
            raise ValueError(f"pnp_method: one of {', '.join(PNP_METHOD_NAMES)}, got {self.pnp_method!r}")
        if min(self.cable_solref) <= 0:
            raise ValueError(f"cable_solref must be positive, got {self.cable_solref}")
        for L in self.cable_length_m:
            if L <= self.formation.formation_radius_m - self.attach_radius_m:
                raise ValueError(f"cable_length_m: {L} m cannot reach down from the formation's radius")

    @property
    def n(self) -> int:
        return self.formation.n_vehicles

    def attach_b_m(self) -> np.ndarray:
        """Attachment points on the load (n, 3), body frame: on the top face, towards each vehicle
        (vehicle ``i`` at angle ``2 pi i / n`` about the load's z axis)."""
        a = 2.0 * math.pi * np.arange(self.n) / self.n
        r = self.attach_radius_m
        return np.column_stack((r * np.cos(a), r * np.sin(a), np.full(self.n, 0.5 * self.size_m[2])))

    def params(self) -> LoadParams:
        """The filters' model of the load (:class:`~companion.load.model.LoadParams`)."""
        L = np.asarray(self.cable_length_m, dtype=float)
        if self.inertia_b_kg_m2 is None:
            return LoadParams.box(self.mass_kg, self.size_m, self.attach_b_m(), L)
        return LoadParams(self.mass_kg, np.asarray(self.inertia_b_kg_m2, dtype=float), self.attach_b_m(), L)

    def inertia(self) -> np.ndarray:
        return np.diag(self.params().inertia_b_kg_m2)

    def hang_drop_m(self) -> np.ndarray:
        """Per cable, the height of the vehicle's attachment over the load's (taut, nominal geometry)."""
        span = self.formation.formation_radius_m - self.attach_radius_m
        return np.sqrt(np.asarray(self.cable_length_m) ** 2 - span**2)

    def cable_dirs_f(self) -> np.ndarray:
        """Unit cable directions (load to vehicle) in the formation frame, nominal geometry (n, 3)."""
        a = 2.0 * math.pi * np.arange(self.n) / self.n
        span = self.formation.formation_radius_m - self.attach_radius_m
        L = np.asarray(self.cable_length_m)
        return np.column_stack((span * np.cos(a) / L, span * np.sin(a) / L, self.hang_drop_m() / L))

    def camera_free_pose(self, vehicle_p_w_m: np.ndarray) -> Pose3:
        """The load's pose from the vehicles' positions alone (no camera): hanging at rest
        (:meth:`nominal_pose`) below their centroid, yawed as they stand around it (the circular
        mean of each vehicle's bearing less its place in the formation, ``2 pi i / n``)."""
        p = np.asarray(vehicle_p_w_m, dtype=float)
        centre = p.mean(axis=0)
        bearing = np.arctan2(p[:, 1] - centre[1], p[:, 0] - centre[0]) - 2.0 * math.pi * np.arange(self.n) / self.n
        phi = math.atan2(float(np.mean(np.sin(bearing))), float(np.mean(np.cos(bearing))))
        return self.nominal_pose(centre, phi)

    def nominal_pose(self, center_w_m: np.ndarray, phi_rad: float) -> Pose3:
        """The load hanging at rest below a formation centred at ``center_w_m`` (vehicle height)
        yawed by ``phi_rad``: the rigging's prior (no measurement in it)."""
        a = np.asarray(self.vehicle_attach_b_m, dtype=float)
        drop = float(np.mean(self.hang_drop_m()))
        pos = np.asarray(center_w_m, dtype=float) + np.array([0.0, 0.0, a[2] - drop - 0.5 * self.size_m[2]])
        c, s = math.cos(phi_rad), math.sin(phi_rad)
        return Pose3(pos, rotmat_to_quat(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])))


@dataclass(frozen=True)
class SlungLoadScenario(Scenario):
    """Three (or more) unjoined vehicles of this stack carrying a box by cables (``kind =
    "slung_load"``, ``[load]``)."""

    kind: Literal["slung_load"] = "slung_load"
    load: LoadConfig = field(default_factory=LoadConfig)

    def __post_init__(self) -> None:
        Scenario.__post_init__(self)
        n = self.load.n
        if self.skeleton.n_links != n:
            raise ValueError(f"skeleton.n_links ({self.skeleton.n_links}) must equal load.formation.n_vehicles ({n}): "
                             "one vehicle per cable")
        if n < 3:
            raise ValueError("the load's pose needs three or more vehicles")
        if self.companion.enabled:
            raise ValueError("companion.enabled must be false: the vehicles are not joined, the chain's constraint "
                             "(SCKF) does not hold between them")
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
    """Read a slung-load scenario (:class:`~companion.configfile.ConfigError` if invalid); a
    ``[companion]`` without ``omega_std_rad_s`` gets the gyro's white noise (as
    :func:`~sitl.scenario.load_scenario`)."""
    return with_rate_noise(load_setup(SlungLoadScenario, path, **overrides))

"""The slung load's configuration (``[load]``, :class:`LoadConfig`): the box (mass, size, optional
principal inertia), the cables (one length per vehicle; attached on the box's top face at
``attach_radius_m`` from its centre, towards each vehicle, and at ``vehicle_attach_b_m`` on each
vehicle), the marker on the load (``marker_id``), the marker pipeline's settings (corner
refinement, PnP method, corner-noise floor), the filters' tuning (``[load.filter]``,
:class:`~.estimate.LoadFilterConfig`) and the formation's circle (``[load.formation]``,
:class:`~.formation.CircleFormationConfig`).

A companion config with a ``[load]`` table flies the formation carrying it
(``trajectory.kind = "formation"``, :class:`~.formation.FormationTrajectory`); a SITL slung-load
scenario adds the vehicles, the cameras and the marker (:mod:`sitl.scenarios.slung_load.config`).
No OpenCV here: the file loads and validates on any install.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_positive
from companion.estimation.so3 import rotmat_to_quat
from companion.vision.config import PNP_METHOD_NAMES, CornerRefinement, PnpMethod

from .estimate import LoadFilterConfig
from .formation import CircleFormationConfig
from .model import LoadParams, Pose3

__all__ = ["LoadConfig"]


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
    #: a companion's fixed-lag estimate, logged beside the real-time one: of the instant this long ago,
    #: once the images of that instant are in [s] (0: none; shorter than ``filter.lag_s``)
    fixed_lag_s: float = 0.0
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
        if not 0.0 <= self.fixed_lag_s < self.filter.lag_s:
            raise ValueError(f"fixed_lag_s must be in [0, filter.lag_s = {self.filter.lag_s:g}), got {self.fixed_lag_s}")

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

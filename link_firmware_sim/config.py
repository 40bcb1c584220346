"""A simulated Pixhawk's configuration file: the chain's skeleton, its rotors, the firmware, the origin.

:class:`VehicleSetup` extends the companion's :class:`~companion.config.ChainSetup` (name and
skeleton) with what one link's flight controller needs::

    [rotors]      the rotor/ESC parameters (companion.skeleton.rotors.RotorParams)
    [rotors.geometry]  optional designed rotor geometry (RotorGeometryConfig, written by
                  ``python -m link_firmware_sim.design search``); default thesis Table 2.1
    [firmware]    EKF tuning, impedance gains, allocation, failsafe times (FirmwareConfig)
    [origin]      the shared local frame's default geodetic origin (SET_GPS_GLOBAL_ORIGIN changes it)
    [signing]     MAVLink 2 signing of the onboard and GCS links (companion.mavlink.signing)
    [companion]   which state stream the companion reads (``mode``) and at what rate: the
                  vehicle's default onboard stream, as a user sets SKL_STATE_HZ / SKL_ODOM_HZ

A SITL scenario is a :class:`VehicleSetup` too; ``python -m sitl launch`` writes each vehicle's
part to ``link.toml`` in the run folder, and ``python -m link_firmware_sim`` validates it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.config import ChainSetup, CompanionConfig
from companion.skeleton.body import link_inertia
from companion.skeleton.rotors import RotorGeometry, RotorParams

from .firmware import LinkFirmware
from .firmware_config import FirmwareConfig
from .geo import GeoOrigin
from .vehicle.params import StreamRates

__all__ = ["VehicleSetup", "check_flyable"]

#: Tolerance of the structural checks of a configured geometry (null structure, principal axes).
_STRUCTURE_TOL = 1e-9


def check_flyable(geometry: RotorGeometry, link_length_m: float) -> None:
    """``ValueError`` (reported at ``rotors.geometry``) unless this firmware and model can fly ``geometry``.

    * the null structure (2.11) with ``nu = [1, -1, -1, 1]``: the allocation (Prop. 1 and the
      selective mapping, :class:`~link_firmware_sim.allocation.Allocator`) needs it;
    * ``B`` (eq. 2.8) and every single-rotor reduction of it of full row rank (full actuation;
      the selective mapping (2.17));
    * principal body axes: ``sum r_i r_i^T`` diagonal, as the link model's diagonal inertia
      (:func:`companion.skeleton.body.link_inertia`, the MuJoCo ``diaginertia``) assumes;
    * every rotor within the link: ``|r_x| < link_length_m / 2``.
    """
    if not geometry.has_null_structure(tol=_STRUCTURE_TOL):
        raise ValueError(
            "rotors.geometry does not have the null structure (2.11) with nu = [1, -1, -1, 1] (u_1 - u_2 - u_3 + u_4 = 0 "
            "and t_1 - t_2 - t_3 + t_4 = 0) that the firmware's allocation (Prop. 1) needs; a design search writes "
            "such a geometry"
        )
    B = geometry.mapping_matrix()
    if np.linalg.matrix_rank(B) < 6:
        raise ValueError("rotors.geometry: the mapping matrix B (eq. 2.8) is not of full row rank (not fully actuated)")
    for i in range(B.shape[1]):
        if np.linalg.matrix_rank(np.delete(B, i, axis=1)) < 6:
            raise ValueError(f"rotors.geometry: without rotor {i + 1} the mapping matrix loses full row rank; the "
                             "selective mapping (2.17) needs every single-rotor reduction of B to keep it")
    off = geometry.rotor_inertia_offdiag_m2()
    if off > _STRUCTURE_TOL:
        raise ValueError(
            f"rotors.geometry: sum r_i r_i^T has off-diagonal {off:.3g} m^2; the link model needs principal body axes "
            "(its inertia is diagonal)"
        )
    x_max = float(np.max(np.abs(geometry.positions_m[:, 0])))
    if x_max >= 0.5 * link_length_m:
        raise ValueError(
            f"rotors.geometry puts rotors at |x| = {x_max:.3f} m (after skeleton.rotor_x_scale), beyond the link tips "
            f"(+-{0.5 * link_length_m:.3f} m)"
        )


@dataclass(frozen=True)
class VehicleSetup(ChainSetup):
    """One link's flight controller (see the module docstring)."""

    rotors: RotorParams = field(default_factory=RotorParams)
    firmware: FirmwareConfig = field(default_factory=FirmwareConfig)
    origin: GeoOrigin = field(default_factory=GeoOrigin)
    companion: CompanionConfig = field(default_factory=CompanionConfig)

    def __post_init__(self) -> None:
        if self.rotors.thrust_max_n != self.firmware.allocation.thrust_max_n:
            raise ValueError(
                f"firmware.allocation.thrust_max_n ({self.firmware.allocation.thrust_max_n}) must equal "
                f"rotors.thrust_max_n ({self.rotors.thrust_max_n})"
            )
        if self.rotors.geometry is not None:
            check_flyable(self.geometry(), self.skeleton.link_length_m)

    def geometry(self) -> RotorGeometry:
        """The link's rotor geometry: ``[rotors.geometry]`` if given, else thesis Table 2.1
        (``sigma_1 = -1``); either with this skeleton's rotor spacing (``rotor_x_scale``)."""
        if self.rotors.geometry is not None:
            return self.rotors.geometry.to_geometry(self.rotors.drag_ratio_m, self.skeleton.rotor_x_scale)
        return RotorGeometry.odar(drag_ratio=self.rotors.drag_ratio_m, x_scale=self.skeleton.rotor_x_scale)

    def firmware_for(self, link: int) -> LinkFirmware:
        """The firmware of 0-based ``link`` (every link of the chain is the same module)."""
        geometry = self.geometry()
        return LinkFirmware(link, self.firmware, link_inertia(self.skeleton, geometry), geometry)

    def stream_rates(self) -> StreamRates:
        """Default onboard state stream: the message the companion reads, at its rate."""
        rate = self.companion.state_rate_hz
        return StreamRates(state_hz=rate, odometry_hz=0.0) if self.companion.mode == "dialect" else StreamRates(0.0, rate)

"""A simulated Pixhawk's configuration file: the chain's skeleton, its rotors, the firmware, the origin.

:class:`VehicleSetup` extends the companion's :class:`~companion.config.ChainSetup` (name and
skeleton) with what one link's flight controller needs::

    [rotors]      the rotor/ESC parameters (companion.skeleton.rotors.RotorParams)
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

from companion.config import ChainSetup, CompanionConfig
from companion.skeleton.body import link_inertia
from companion.skeleton.rotors import RotorGeometry, RotorParams

from .firmware import FirmwareConfig, LinkFirmware
from .geo import GeoOrigin
from .params import StreamRates

__all__ = ["VehicleSetup"]


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

    def geometry(self) -> RotorGeometry:
        """The link's rotor geometry (thesis Table 2.1 with this skeleton's rotor spacing)."""
        return RotorGeometry.odar(drag_ratio=self.rotors.drag_ratio_m, x_scale=self.skeleton.rotor_x_scale)

    def firmware_for(self, link: int) -> LinkFirmware:
        """The firmware of 0-based ``link`` (every link of the chain is the same module)."""
        geometry = self.geometry()
        return LinkFirmware(link, self.firmware, link_inertia(self.skeleton, geometry), geometry)

    def stream_rates(self) -> StreamRates:
        """Default onboard state stream: the message the companion reads, at its rate."""
        rate = self.companion.state_rate_hz
        return StreamRates(state_hz=rate, odometry_hz=0.0) if self.companion.mode == "dialect" else StreamRates(0.0, rate)

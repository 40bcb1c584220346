"""The configuration of one simulated Pixhawk (:class:`FirmwareConfig`, a vehicle file's
``[firmware]``): EKF tuning, the controllers' gains, allocation, failsafe times and bounds."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from companion.configfile import require_positive

from .allocation import AllocationParams
from .controllers import ImpedanceGains
from .controllers.hybrid import HybridGains, ObserverConfig
from .controllers.pspm import PspmGains
from .controllers.se3_control import Se3PidGains
from .estimators import EkfConfig, GpsHealthConfig, outdoor_ekf_config
from .thrust_limit import ThrustLimitConfig

__all__ = ["FirmwareConfig"]


@dataclass(frozen=True)
class FirmwareConfig:
    """Parameters of one simulated Pixhawk."""

    rate_hz: float = 500.0
    ekf: EkfConfig = field(default_factory=outdoor_ekf_config)
    gains: ImpedanceGains = field(default_factory=ImpedanceGains)
    allocation: AllocationParams = field(default_factory=AllocationParams)
    correction_hold_s: float = 0.1
    correction_stale_s: float = 0.5
    target_stale_s: float = 1.0
    #: largest correction accepted (SKL_CORR_MAXP / _MAXV / _MAXR); a larger one is rejected,
    #: never clamped. The SCKF's largest in the SITL scenarios: 0.78 m, 0.20 m/s, 0.006 rad.
    correction_max_dp_m: float = 2.0
    correction_max_dv_m_s: float = 1.0
    correction_max_dtheta_rad: float = 0.5
    gps: GpsHealthConfig = field(default_factory=GpsHealthConfig)
    #: when the rotors' thrust limit is reported and when the report ends (SKL_TLIM_WARN / _CLR)
    thrust_limit: ThrustLimitConfig = field(default_factory=ThrustLimitConfig)
    #: the pose controller (SKL_CTRL): eq. 1's impedance control, the SE(3) PID of thesis sec. 2.3.2
    #: (:mod:`.se3_control`) or the hybrid pose/wrench control of sec. 2.3.3 (:mod:`.hybrid`: pose
    #: control until a contact is commanded, with the momentum observer running)
    controller: Literal["impedance", "se3_pid", "hybrid"] = "impedance"
    se3_pid: Se3PidGains = field(default_factory=Se3PidGains)
    hybrid: HybridGains = field(default_factory=HybridGains)
    observer: ObserverConfig = field(default_factory=ObserverConfig)
    #: largest contact force a command may ask of the hybrid controller (SKL_CT_FMAX) [N]
    contact_max_force_n: float = 30.0
    #: PSPM teleoperation (SKL_PSPM_EN; thesis sec. 2.3.4, :mod:`.pspm`): ``"off"``; ``"on"``: every
    #: pose target is an operator set pose, modulated by PSPM (:meth:`LinkFirmware.set_target`), and
    #: the slave law of sec. 2.3.4 with ``pspm``'s gains (instead of ``controller``) tracks the
    #: modulated pose; ``"bypass"``: the same slave law on the raw set poses (the unmodulated comparison)
    pspm_mode: Literal["off", "on", "bypass"] = "off"
    #: the reservoirs start full: at rest nothing dissipates, so empty ones would never release a
    #: step (0.4 J pass 0.27 m of the 11 N/m spring at once, 0.3 J 18 deg of the 6 N m/rad one)
    pspm: PspmGains = field(default_factory=lambda: PspmGains(e_max_t_j=0.4, e_max_r_j=0.3, e0_t_j=0.4, e0_r_j=0.3))

    def __post_init__(self) -> None:
        require_positive(self, "rate_hz", "correction_max_dp_m", "correction_max_dv_m_s", "correction_max_dtheta_rad")
        require_positive(self, "contact_max_force_n")
        if not 0 <= self.correction_hold_s < self.correction_stale_s:
            raise ValueError(
                f"correction_hold_s must be in [0, correction_stale_s), got {self.correction_hold_s} "
                f"(stale {self.correction_stale_s})"
            )
        require_positive(self, "target_stale_s")

"""The firmware's pose controllers, behind one interface (:class:`~.base.Controller`).

* :mod:`.impedance`: paper eq. 1's impedance control (the default; its readable specification and
  the one dispatch to its kernel);
* :mod:`.se3_control`: the SE(3) PID of thesis sec. 2.3.2;
* :mod:`.hybrid`: the hybrid pose/wrench control of sec. 2.3.3, with its momentum observer;
* :mod:`.pspm`: PSPM teleoperation's modulator and slave law (sec. 2.3.4);
* :mod:`.common`: what they share.

:data:`CONTROLLERS` names the selectable ones (``FirmwareConfig.controller``, ``SKL_CTRL``);
:func:`make_controller` builds the one a configuration selects.
"""

from __future__ import annotations

from companion.skeleton.body import LinkInertia

from .base import Controller
from .common import limit_length, vee, weight_wrench
from .hybrid import HybridController
from .impedance import ControlIntegrals, ImpedanceController, ImpedanceGains
from .pspm import PspmModulator, PspmSlave
from .se3_control import Se3PidController

__all__ = ["Controller", "CONTROLLERS", "make_controller", "ImpedanceController", "ImpedanceGains", "ControlIntegrals",
           "Se3PidController", "HybridController", "PspmSlave", "limit_length", "vee", "weight_wrench"]

#: the selectable controllers by name (``FirmwareConfig.controller``): each built from the firmware's
#: configuration and the link's inertia
CONTROLLERS = {
    "impedance": lambda config, inertia: ImpedanceController(config.gains, inertia),
    "se3_pid": lambda config, inertia: Se3PidController(config.se3_pid, inertia),
    "hybrid": lambda config, inertia: HybridController(config.hybrid, inertia, config.observer),
}


def make_controller(config, inertia: LinkInertia, pspm: PspmModulator | None = None) -> Controller:
    """The controller a ``FirmwareConfig`` selects (``config.controller``); under PSPM
    teleoperation (``config.pspm_mode`` not ``"off"``) the slave law of sec. 2.3.4 replaces it,
    on ``pspm``'s modulated set poses (``None``: the raw ones)."""
    controller = CONTROLLERS[config.controller](config, inertia)
    if config.pspm_mode != "off":
        controller = PspmSlave(config.pspm, inertia.mass_kg, pspm)
    return controller

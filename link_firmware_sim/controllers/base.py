"""The one interface of the firmware's pose controllers (:mod:`link_firmware_sim.controllers`)."""

from __future__ import annotations

import numpy as np

from companion.messages import PoseTarget

__all__ = ["Controller"]


class Controller:
    """One link's pose controller, as the firmware runs it every control tick.

    ``controller(p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target, dt_s)`` is the body-frame wrench
    command ``U = [u; tau]`` [N, Nm] from the control estimate (world position, velocity, attitude),
    the body rate and the :class:`~companion.messages.PoseTarget`, over ``dt_s``, with whatever
    state the controller keeps (its integrals); :meth:`reset` clears that state (arming). After the
    allocation, :meth:`observe` gets the wrench the clipped commands produce (a controller with a
    momentum observer, :attr:`observer`, uses it). :attr:`tick_state` is the state array of the
    controller the firmware's fused tick runs inside its one kernel call (eq. 1's), ``None`` for
    the others.
    """

    #: the momentum observer the controller runs (the hybrid controller's), else ``None``
    observer = None
    #: the kernel state the fused tick reads and updates (eq. 1, compiled), else ``None``
    tick_state = None

    def reset(self) -> None:
        """Clear the controller's state (integrals, observer): the firmware arms."""

    def __call__(self, p_w_m, v_w_m_s, q_wxyz, omega_b_rad_s, target: PoseTarget, dt_s: float) -> np.ndarray:
        raise NotImplementedError

    def observe(self, v_w_m_s, q_wxyz, omega_b_rad_s, applied_b: np.ndarray, dt_s: float) -> None:
        """The wrench ``applied_b = [u; tau]`` (body frame) the rotors' clipped commands produce,
        after the allocation (nothing unless the controller runs an observer)."""

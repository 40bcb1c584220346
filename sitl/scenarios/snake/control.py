"""The snake's velocity control (thesis secs. 4.6, 4.7.2): once per CPG period, the desired body
velocity through the inverse model, corrected by the adaptation, to the CPG's inputs.

At every period boundary :class:`VelocityControl` measures the body's velocity over the period
that ended (:func:`~sitl.scenarios.ground.run.body_velocity`: the centre of mass's displacement
in {B}, the heading at the period's middle taken as the mean of its ends, and the heading's
change), and sets ``eta = [A, B]`` for the next period:

* ``xi_d = [v_x_m_s, 0, omega_d]``: ``omega_d`` is the command's, or with ``hold_line`` the
  line-holding law ``-k_y y - k_heading psi`` (limited to ``omega_max_rad_s``);
* ``eta``: the inverse model's ``Xi^-1(xi_d)``, and with ``[control] adapt`` eq. 4.3's correction
  (:class:`companion.motion.inverse.Adaptation`: PI in the autoencoder's hidden space, limited to
  the model's training range). As the flying chain's generator does, the adaptation runs on steady
  motion only (:class:`~companion.motion.inverse.SteadyGate`: ``settle_periods`` after a new
  command, and the period velocity changing by less than ``steady_tol``); otherwise the inputs are
  the model's plus the correction learnt so far.
"""

from __future__ import annotations

import math

import numpy as np

from companion.motion.inverse import Adaptation, InverseModel, SteadyGate

from ..ground.run import body_velocity
from .config import CpgCommand, SnakeScenario

__all__ = ["VelocityControl"]


class VelocityControl:
    """The velocity commands' ``(A, B)`` [rad] (module docstring) for ``robot``."""

    def __init__(self, sc: SnakeScenario, robot):
        cfg = sc.control
        self.cfg = cfg
        self.robot = robot
        self.period_s = 1.0 / sc.cpg.frequency_hz
        self.model = InverseModel.load(cfg.model_file)
        self.adaptation = Adaptation(self.model, cfg.k_p, cfg.k_i) if cfg.adapt else None
        self.gate = SteadyGate(cfg.settle_periods, cfg.steady_tol)
        self.eta = np.zeros(2)
        self._command = None
        self._last = None  # (com in plane, heading) at the last period boundary
        #: per update: (t, v_x, v_y, omega measured, omega_d, A, B)
        self.log: list[tuple] = []

    def desired(self, command: CpgCommand) -> np.ndarray:
        """``xi_d = [v_x, 0, omega_d]`` of ``command`` now."""
        omega = command.omega_rad_s
        if command.hold_line:
            y = float(self.robot.in_plane(self.robot.centre_of_mass())[1])
            psi = math.remainder(self.robot.heading(), 2.0 * math.pi)
            omega = -self.cfg.k_y_per_s * y - self.cfg.k_heading_per_s * psi
            omega = max(-self.cfg.omega_max_rad_s, min(self.cfg.omega_max_rad_s, omega))
        return np.array([command.v_x_m_s, 0.0, omega])

    def update(self, t_s: float, command: CpgCommand) -> np.ndarray:
        """``(A, B)`` [rad] for the period from ``t_s`` on (called at every period boundary)."""
        com = self.robot.in_plane(self.robot.centre_of_mass())
        heading = self.robot.heading()
        xi_d = self.desired(command)
        if command is not self._command:
            self._command = command
            self.gate.restart()
        measured = None
        if self._last is not None:
            (p0, h0) = self._last
            dh = math.remainder(heading - h0, 2.0 * math.pi)
            measured = np.array([float(x) for x in body_velocity(com - p0, h0 + 0.5 * dh, dh, self.period_s)])
        self._last = (com, heading)
        steady = measured is not None and self.gate.steady(measured)
        if self.adaptation is None:
            self.eta = np.clip(self.model(xi_d)[0], self.model.eta_low, self.model.eta_high)
        elif steady:
            self.eta = self.adaptation.update(xi_d, measured, self.period_s)
        else:  # the model's inputs plus the correction learnt so far
            self.eta = self.adaptation.update(xi_d, xi_d, 0.0)
        m = measured if measured is not None else np.full(3, np.nan)
        self.log.append((t_s, *m, xi_d[2], *self.eta))
        return self.eta

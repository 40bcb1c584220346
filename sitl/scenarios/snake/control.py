"""The snake's velocity control (thesis secs. 4.6, 4.7.2): once per CPG period, the desired body
velocity through the inverse model, corrected by the adaptation, to the CPG's inputs.

At every period boundary :class:`VelocityControl` measures the body's velocity over the period
that ended (:class:`~sitl.scenarios.ground.control.PeriodMeter`), and sets ``eta = [A, B]`` for
the next period:

* ``xi_d = [v_x_m_s, v_y, omega_d]``: ``omega_d`` is the command's, or with ``hold_line`` the
  line-holding law (:func:`~sitl.scenarios.ground.control.line_holding_rate`); ``v_y``, which the
  command leaves free, the one on the inverse model's feasible set at that speed and turn rate
  (:func:`~companion.motion.inverse.nearest_feasible`);
* ``eta``: the inverse model's ``Xi^-1(xi_d)``, and with ``[control] adapt`` eq. 4.3's correction
  (:class:`companion.motion.inverse.Adaptation`: PI in the autoencoder's hidden space, limited to
  the model's training range). As the flying chain's generator does, the adaptation runs on steady
  motion only (:class:`~companion.motion.inverse.SteadyGate`: ``settle_periods`` after a new
  command, and the period velocity changing by less than ``steady_tol``); otherwise the inputs are
  the model's plus the correction learnt so far.
"""

from __future__ import annotations

import numpy as np

from companion.motion.inverse import Adaptation, InverseModel, SteadyGate, nearest_feasible

from ..ground.control import PeriodMeter, line_holding_rate
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
        self.meter = PeriodMeter(robot, self.period_s)
        self.eta = np.zeros(2)
        self._command = None
        #: per update: (t, v_x, v_y, omega measured, omega_d, A, B, v_x desired)
        self.log: list[tuple] = []

    def desired(self, command: CpgCommand) -> np.ndarray:
        """``xi_d = [v_x, v_y, omega_d]`` of ``command`` now, ``v_y`` the sideways velocity the robot
        makes at that ``v_x`` and ``omega_d`` (the command leaves it free: a turning body drifts
        sideways in {B}), found on the inverse model's feasible set."""
        omega = command.omega_rad_s
        if command.hold_line:
            omega = line_holding_rate(self.robot, self.cfg.k_y_per_s, self.cfg.k_heading_per_s, self.cfg.omega_max_rad_s)
        m = self.model
        v_y = np.linspace(m.xi_mean[1] - 3.0 * m.xi_std[1], m.xi_mean[1] + 3.0 * m.xi_std[1], 201)
        best = nearest_feasible(m, lambda s: np.column_stack((np.full_like(s, command.v_x_m_s), s,
                                                              np.full_like(s, omega))), v_y)
        return np.array([command.v_x_m_s, best, omega])

    def update(self, t_s: float, command: CpgCommand) -> np.ndarray:
        """``(A, B)`` [rad] for the period from ``t_s`` on (called at every period boundary)."""
        xi_d = self.desired(command)
        if command is not self._command:
            self._command = command
            self.gate.restart()
        measured = self.meter.boundary()
        steady = measured is not None and self.gate.steady(measured)
        if self.adaptation is None:
            self.eta = np.clip(self.model(xi_d)[0], self.model.eta_low, self.model.eta_high)
        elif steady:
            self.eta = self.adaptation.update(xi_d, measured, self.period_s)
        else:  # the model's inputs plus the correction learnt so far
            self.eta = self.adaptation.update(xi_d, xi_d, 0.0)
        m = measured if measured is not None else np.full(3, np.nan)
        self.log.append((t_s, *m, xi_d[2], *self.eta, xi_d[0]))
        return self.eta

    def series(self) -> dict[str, np.ndarray]:
        """The updates as arrays: ``t``, the desired ``v_x_d`` and ``omega_d``, the inputs ``A``, ``B``
        [rad] (what the run's plot and log show)."""
        log = np.array(self.log, dtype=float).reshape(-1, 8)
        return {"t": log[:, 0], "v_x_d": log[:, 7], "omega_d": log[:, 4], "A": log[:, 5], "B": log[:, 6]}

"""The pivotboard's motion control (thesis secs. 4.5.3, 4.6, 4.7.2): once per CPG period, the
desired acceleration and angular velocity through the inverse model, corrected by the adaptation,
to the CPG's inputs.

At every period boundary :class:`MotionControl` measures the board's velocity over the period
that ended (:class:`~sitl.scenarios.ground.control.PeriodMeter`: ``v`` forward, ``omega``) and its
acceleration (the change of ``v`` from the period before, over a period), and sets the inputs for
the next period:

* the desired motion: ``v_dot_d`` the command's (``mode = "acceleration"``) or ``k_v (v_x - v)``
  (``mode = "velocity"``); ``omega_d`` the command's or, with ``hold_line``, the line-holding law
  (:func:`~sitl.scenarios.ground.control.line_holding_rate`);
* the branch: the accelerating model (the map's phase difference) unless ``v_dot_d`` is below what
  its gentlest input makes at that speed, ``d (v_s,min - v)`` (its training data's slowest
  ``v_s`` and mean ``d``); then the decelerating one (zero phase difference). The CPG's own
  ``v_dot_d`` input, whose sign picks its phase difference, is set to select that branch;
* the speed the inputs will act at: new inputs are held over the period (half of it, on
  average) and the CPG's amplitude filter (a double pole at ``k_a / 2``) follows a ramp of its
  input ``4 / k_a`` behind, so the motion is planned at ``v + v_dot_d lead``, ``lead = T / 2 +
  4 / k_a`` (planned at ``v``, the board falls short of the commanded acceleration by the
  speed it gains over that lag);
* the first step of the inverse model: the DA parameters ``xi_d = [v_s, d, c]`` of the desired
  motion on the branch model's feasible set
  (:func:`~companion.motion.decaying_acceleration.feasible_da`); the second: ``eta = [A, B]``
  from ``xi_d`` (the model, limited to its training range);
* with ``[control] adapt``, eq. 4.3 on the accelerating branch: the measured motion's DA parameters
  (the same line search on the measured ``v``, ``v_dot`` and ``omega``) against ``xi_d``, in the
  autoencoder's hidden space (:class:`~companion.motion.inverse.Adaptation`), on steady motion only
  (:class:`~companion.motion.inverse.SteadyGate` on ``[v, omega]``); otherwise the model's inputs
  plus the correction learnt so far.
"""

from __future__ import annotations

import numpy as np

from companion.motion.decaying_acceleration import feasible_da
from companion.motion.inverse import Adaptation, InverseModel, SteadyGate

from ..ground.control import PeriodMeter, line_holding_rate
from .config import BRANCHES, PivotCommand, PivotScenario, model_path

__all__ = ["MotionControl"]


class MotionControl:
    """The motion commands' CPG inputs (module docstring) for ``robot``."""

    def __init__(self, sc: PivotScenario, robot):
        cfg = sc.control
        self.cfg = cfg
        self.robot = robot
        self.period_s = 1.0 / sc.cpg.frequency_hz
        #: how long new inputs take to act: held over a period (half of it on average), and the
        #: CPG's amplitude filter (a double pole at k_a / 2) follows a ramp 4 / k_a behind
        self.lead_s = 0.5 * self.period_s + 4.0 / sc.cpg.k_a
        self.models = {b: InverseModel.load(model_path(cfg.model_folder, b)) for b in BRANCHES}
        acc = self.models["accelerating"]
        if "xi_low" not in acc.info:
            raise ValueError(f"{acc.info.get('file')}: no training range (xi_low): retrain it with "
                             "python -m sitl.scenarios.pivotboard.inverse")
        #: the accelerating branch's gentlest steady speed and its mean decay rate
        self.v_s_min, self.d_mean = float(acc.info["xi_low"][0]), float(acc.xi_mean[1])
        self.adaptation = Adaptation(acc, cfg.k_p, cfg.k_i) if cfg.adapt else None
        self.gate = SteadyGate(cfg.settle_periods, cfg.steady_tol)
        self.meter = PeriodMeter(robot, self.period_s)
        self._command = None
        self._v = None  # the last period's forward speed
        #: per update: (t, v, v_dot, omega measured, v_dot_d, omega_d, A, B, branch 1/-1, v_x desired
        #: or nan)
        self.log: list[tuple] = []

    def desired(self, command: PivotCommand, v: float) -> tuple[float, float]:
        """``(v_dot_d, omega_d)`` of ``command`` now, at the forward speed ``v``."""
        cfg = self.cfg
        v_dot = command.v_dot_d_m_s2 if command.mode == "acceleration" else cfg.k_v_per_s * (command.v_x_m_s - v)
        omega = command.omega_rad_s
        if command.hold_line:
            omega = line_holding_rate(self.robot, cfg.k_y_per_s, cfg.k_heading_per_s, cfg.omega_max_rad_s)
        return v_dot, omega

    def update(self, t_s: float, command: PivotCommand) -> tuple[float, float, float]:
        """``(A, B, v_dot_cpg)`` [rad, rad, m/s^2] for the period from ``t_s`` on (called at every
        period boundary; ``v_dot_cpg``: the CPG's branch input)."""
        if command is not self._command:
            self._command = command
            self.gate.restart()
        measured = self.meter.boundary()
        v = omega = 0.0
        v_dot = np.nan
        if measured is not None:
            v, omega = float(measured[0]), float(measured[2])
            if self._v is not None:
                v_dot = (v - self._v) / self.period_s
            self._v = v
        v_dot_d, omega_d = self.desired(command, v)
        v_ahead = v + v_dot_d * self.lead_s  # the speed when the new inputs have taken effect
        accelerating = v_dot_d >= self.d_mean * (self.v_s_min - v_ahead)
        model = self.models["accelerating" if accelerating else "decelerating"]
        xi_d = feasible_da(model, v_ahead, v_dot_d, omega_d, self.cfg.v_min_m_s)
        steady = measured is not None and bool(np.isfinite(v_dot)) and self.gate.steady(np.array([v, omega]))
        if self.adaptation is None or not accelerating:
            eta = np.clip(model(xi_d)[0], model.eta_low, model.eta_high)
        elif steady:
            xi_m = feasible_da(model, v, v_dot, omega, self.cfg.v_min_m_s)
            eta = self.adaptation.update(xi_d, xi_m, self.period_s)
        else:  # the model's inputs plus the correction learnt so far
            eta = self.adaptation.update(xi_d, xi_d, 0.0)
        v_dot_cpg = max(v_dot_d, 0.0) if accelerating else min(v_dot_d, -1e-9)
        v_x_d = command.v_x_m_s if command.mode == "velocity" else np.nan
        self.log.append((t_s, v, v_dot, omega, v_dot_d, omega_d, *eta, 1 if accelerating else -1, v_x_d))
        return float(eta[0]), float(eta[1]), v_dot_cpg

    def series(self) -> dict[str, np.ndarray]:
        """The updates as arrays: ``t``, the desired ``v_x_d`` (``nan`` for an acceleration command),
        ``v_dot_d`` and ``omega_d``, the inputs ``A``, ``B`` [rad] and the ``branch`` (1 speeding
        up, -1 slowing down) (what the run's plot and log show)."""
        log = np.array(self.log, dtype=float).reshape(-1, 10)
        return {"t": log[:, 0], "v_x_d": log[:, 9], "v_dot_d": log[:, 4], "omega_d": log[:, 5], "A": log[:, 6],
                "B": log[:, 7], "branch": log[:, 8]}

"""The leader's motion generator (thesis Fig. 4-3): desired body motion -> CPG -> expected physics -> link targets.

Each step: the CPG (sec. 4.3.1) runs with the current parameters ``eta = [A; B]``, the expected
physics (sec. 4.4) moves the body, and every link gets its target pose and twist. The desired
motion ``xi_d = [v; omega; theta]`` goes through the inverse model (sec. 4.5.1) to the raw
parameters; once per undulation period the body motion measured over that period feeds the
adaptation of eq. 4.3. Pure: time is the caller's ``dt``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cpg import CpgParams, cpg_initial_state, cpg_output, cpg_step
from .expected_physics import BodyState, WaterParams, body_step, body_wrench, link_targets
from .inverse import Adaptation, InverseModel, SteadyGate

__all__ = ["LinkTargets", "MotionGenerator"]


@dataclass(frozen=True)
class LinkTargets:
    """Every link's target: ``p_w_m``, ``v_w_m_s`` (n, 3), ``R_wl`` (n, 3, 3), ``omega_l_rad_s`` (n, 3)."""

    p_w_m: np.ndarray
    v_w_m_s: np.ndarray
    R_wl: np.ndarray
    omega_l_rad_s: np.ndarray


class MotionGenerator:
    """See the module docstring. ``adapt = False`` uses the inverse model alone. ``cpg``,
    ``water`` and ``half_length_m`` default to the physics the model was trained on (pass others
    only to simulate a model error)."""

    def __init__(self, model: InverseModel, cpg: CpgParams | None = None, water: WaterParams | None = None,
                 half_length_m: float | None = None, body: BodyState | None = None, adapt: bool = True,
                 k_p: float = 0.5, k_i: float = 0.2, settle_periods: int = 2, steady_tol: float = 0.02):
        self.model = model
        self.cpg = cpg = cpg if cpg is not None else model.steady.cpg_params
        self.water = water if water is not None else model.steady.water
        self.half = half_length_m if half_length_m is not None else model.steady.half_length_m
        self.body = body if body is not None else BodyState.at_rest()
        self.state = cpg_initial_state(cpg)
        self.adaptation = Adaptation(model, k_p, k_i) if adapt else None
        self.eta = np.zeros(4)
        self.period_s = 1.0 / cpg.frequency_hz
        self._acc_t = 0.0
        self._acc = np.zeros(6)
        self.measured: np.ndarray | None = None  # xi over the last whole period
        self._xi_d: np.ndarray | None = None
        #: the adaptation runs on steady motion only (:class:`~.inverse.SteadyGate`)
        self.gate = SteadyGate(settle_periods, steady_tol)

    def step(self, xi_desired: np.ndarray, dt_s: float, new_command: bool | None = None) -> LinkTargets:
        """Advance by ``dt_s`` towards ``xi_desired``. ``new_command``: whether the operator's
        command changed (restarts the settling before adaptation); default: any change of
        ``xi_desired`` (pass ``False`` when only a feedback loop moved it)."""
        xi_desired = np.asarray(xi_desired, dtype=float)
        changed = self._xi_d is None or not np.array_equal(xi_desired, self._xi_d)
        if changed if new_command is None else new_command:
            self.gate.restart()
        if changed:
            if self.adaptation is None or self.measured is None:
                # the raw parameters of a new command, within the model's range
                self.eta = np.clip(self.model(xi_desired)[0], self.model.eta_low, self.model.eta_high)
        self._xi_d = xi_desired
        self.state = cpg_step(self.state, self.cpg, self.eta[:2], self.eta[2:], dt_s)
        _, R_bl, om = cpg_output(self.state, self.cpg, self.eta[:2], self.eta[2:])
        f, tau = body_wrench(self.body, R_bl, om, self.half, self.water)
        self.body = body_step(self.body, f, tau, self.water, dt_s)
        self._acc += dt_s * np.concatenate([self.body.R_wb.T @ self.body.v_w_m_s, self.body.omega_b_rad_s])
        self._acc_t += dt_s
        if self._acc_t >= self.period_s - 1e-9:
            theta = np.arctan2(self.eta[1], self.eta[0])
            self.measured = np.concatenate([self._acc / self._acc_t, [theta]])
            steady = self.gate.steady(self.measured[:3])
            if self.adaptation is not None:
                if steady:
                    self.eta = self.adaptation.update(xi_desired, self.measured, self._acc_t)
                else:  # raw parameters plus the correction learnt so far
                    self.eta = self.adaptation.update(xi_desired, xi_desired, 0.0)
            self._acc[:] = 0.0
            self._acc_t = 0.0
        return self.targets()

    def targets(self) -> LinkTargets:
        """Every link's target at the current state (without stepping)."""
        _, R_bl, om = cpg_output(self.state, self.cpg, self.eta[:2], self.eta[2:])
        p, v, R, w = link_targets(self.body, R_bl, om, self.half)
        return LinkTargets(p, v, R, w)

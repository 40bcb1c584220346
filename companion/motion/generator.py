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

from companion.kernels.cpg import body_step_kernel, cpg_output_kernel, cpg_step_kernel, link_targets_kernel
from companion.kernels.jit import ENABLED as _COMPILED

from .cpg import CpgParams, CpgState, cpg_initial_state, cpg_output, cpg_step
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
    only to simulate a model error). ``compiled`` (default: when numba is installed) runs each
    step's CPG, body and targets as the kernels of :mod:`companion.kernels.cpg` instead of their
    numpy specification (the same numbers to rounding: ``tests/unit/test_companion_kernels.py``)."""

    def __init__(self, model: InverseModel, cpg: CpgParams | None = None, water: WaterParams | None = None,
                 half_length_m: float | None = None, body: BodyState | None = None, adapt: bool = True,
                 k_p: float = 0.5, k_i: float = 0.2, settle_periods: int = 2, steady_tol: float = 0.02,
                 compiled: bool | None = None):
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
        self.compiled = _COMPILED if compiled is None else compiled
        if self.compiled:  # the kernels' argument tuples (module docstring of companion.kernels.cpg)
            sa, sb, _ = cpg.shaping
            pairs = cpg.coupled_pairs
            self._shape = (np.array(sa), np.array(sb), float(cpg.frequency_hz), float(cpg.k_a), float(cpg.k_b),
                           float(cpg.k_phi))
            self._coupling = (np.array(pairs.i, dtype=np.int64), np.array(pairs.j, dtype=np.int64),
                              np.array(pairs.phi_ij, dtype=float))
            w = self.water
            self._water = (0.5 * w.density_kg_m3 * w.area_axial_m2 * w.cd_axial,
                           0.5 * w.density_kg_m3 * w.area_normal_m2 * w.cd_normal, float(w.mass_kg),
                           np.array(w.inertia_kg_m2, dtype=float))

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
        eta = self.eta
        if self.compiled:
            R_bl, om = self._step_compiled(dt_s)
        else:
            self.state = cpg_step(self.state, self.cpg, eta[:2], eta[2:], dt_s)
            _, R_bl, om = cpg_output(self.state, self.cpg, eta[:2], eta[2:])
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
        # the shape just computed, unless the adaptation has changed the parameters since
        return self._targets(R_bl, om) if self.eta is eta else self.targets()

    def targets(self) -> LinkTargets:
        """Every link's target at the current state (without stepping)."""
        if self.compiled:
            return self._targets(*self._output())
        _, R_bl, om = cpg_output(self.state, self.cpg, self.eta[:2], self.eta[2:])
        return self._targets(R_bl, om)

    def _targets(self, R_bl: np.ndarray, om: np.ndarray) -> LinkTargets:
        """Every link's target for the CPG's shape ``R_BL``, ``omega_BL_L`` and the current body."""
        if not self.compiled:
            return LinkTargets(*link_targets(self.body, R_bl, om, self.half))
        n = self.cpg.n_links
        out = (np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3)), np.empty((n, 3)))
        link_targets_kernel(self._body(), R_bl, om, float(self.half), out)
        return LinkTargets(*out)

    def _state(self) -> tuple[np.ndarray, ...]:
        st = self.state
        return tuple(np.array(x, dtype=float) for x in (st.a, st.a_dot, st.b, st.b_dot, st.phi))

    def _body(self) -> tuple[np.ndarray, ...]:
        b = self.body
        return tuple(np.array(x, dtype=float) for x in (b.p_w_m, b.v_w_m_s, b.R_wb, b.omega_b_rad_s))

    def _output(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`~.cpg.cpg_output`'s ``(R_BL, omega_BL_L)`` of the current state, compiled."""
        n = self.cpg.n_links
        out = (np.empty((n, 3, 3)), np.empty((n, 3)))
        cpg_output_kernel(self._state(), self._shape, self._coupling, self.eta[:2].copy(), self.eta[2:].copy(), out)
        return out

    def _step_compiled(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`step`'s CPG step, drag and body step, compiled; returns the new shape
        ``(R_BL, omega_BL_L)``."""
        state = self._state()
        cpg_step_kernel(state, self._shape, self._coupling, self.eta[:2].copy(), self.eta[2:].copy(), float(dt_s))
        self.state = CpgState(*state)
        R_bl, om = self._output()
        out = (np.empty(3), np.empty(3), np.empty((3, 3)), np.empty(3))
        body_step_kernel(self._body(), R_bl, om, float(self.half), self._water, float(dt_s), 4, out)
        self.body = BodyState(*out)
        return R_bl, om

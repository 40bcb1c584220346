"""Steady body motion of CPG parameters in the expected physics: the data of the inverse model.

Thesis sec. 4.5.1: with fixed CPG parameters ``eta = [A; B]`` (R^4) the body velocity in ``{B}``
converges, so ``xi(eta) = [v; omega; theta]`` (R^7) is taken as the steady state: the body-frame
linear and angular velocity averaged over whole undulation periods after settling, and the
undulating direction ``theta = atan2(A_y, A_x)`` (0: horizontal, pi/2: vertical undulation).
:func:`steady_motion` simulates a batch of parameter sets at once (the CPG and the physics take
leading batch dimensions); :func:`sample_parameters` draws them uniformly with a seeded
generator: amplitudes non-negative (a negative amplitude is the same gait half a period
later), biases of both signs (turns both ways). The thesis keeps biases non-negative and uses
the mirror symmetry; that puts "no turn" on the edge of the data, where the inverse model
extrapolates (a straight vertical undulation then asked for a spurious bias and climbed).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_nonnegative, require_positive

from .cpg import CpgParams, cpg_initial_state, cpg_output, cpg_step
from .expected_physics import BodyState, WaterParams, body_step, body_wrench

__all__ = ["SteadyConfig", "steady_motion", "sample_parameters", "XI_NAMES", "ETA_NAMES"]

ETA_NAMES = ("A_x", "A_y", "B_x", "B_y")
XI_NAMES = ("v_x", "v_y", "v_z", "omega_x", "omega_y", "omega_z", "theta")


@dataclass(frozen=True)
class SteadyConfig:
    """How a steady state is taken: ``settle_s`` of simulation from rest, then the average over
    ``periods`` undulation periods, integration step ``dt_s``."""

    n_links: int = 7
    half_length_m: float = 0.5
    dt_s: float = 0.01
    settle_s: float = 30.0
    periods: int = 4
    cpg: CpgParams | None = None
    water: WaterParams = field(default_factory=WaterParams)

    def __post_init__(self) -> None:
        require_positive(self, "half_length_m", "dt_s", "periods")
        require_nonnegative(self, "settle_s")
        if self.cpg is not None and self.cpg.n_links != self.n_links:
            raise ValueError(f"cpg.n_links ({self.cpg.n_links}) must equal n_links ({self.n_links})")

    @property
    def cpg_params(self) -> CpgParams:
        return self.cpg if self.cpg is not None else CpgParams(self.n_links)

    def check_chain(self, n_links: int, link_length_m: float) -> None:
        """``ValueError`` unless this is a chain of ``n_links`` links of ``link_length_m``."""
        if self.n_links != n_links or abs(2 * self.half_length_m - link_length_m) > 1e-9:
            raise ValueError(f"is for {self.n_links} links of {2 * self.half_length_m:g} m, "
                             f"the skeleton has {n_links} of {link_length_m:g} m")


def steady_motion(eta: np.ndarray, cfg: SteadyConfig = SteadyConfig(),
                  progress: Callable[[float], None] | None = None) -> np.ndarray:
    """(K, 7) ``xi`` of (K, 4) parameter sets ``eta``; ``progress(seconds)`` as it simulates."""
    eta = np.atleast_2d(np.asarray(eta, dtype=float))
    params = cfg.cpg_params
    A, B = eta[:, :2], eta[:, 2:]
    state = cpg_initial_state(params, batch=(len(eta),))
    body = BodyState.at_rest(batch=(len(eta),))
    period_steps = int(round(1.0 / (params.frequency_hz * cfg.dt_s)))
    settle = int(round(cfg.settle_s / cfg.dt_s))
    total = settle + cfg.periods * period_steps
    v_sum = np.zeros((len(eta), 3))
    w_sum = np.zeros((len(eta), 3))
    for k in range(total):
        state = cpg_step(state, params, A, B, cfg.dt_s)
        _, R_bl, om = cpg_output(state, params, A, B)
        f, tau = body_wrench(body, R_bl, om, cfg.half_length_m, cfg.water)
        body = body_step(body, f, tau, cfg.water, cfg.dt_s)
        if k >= settle:
            v_sum += np.einsum("kji,kj->ki", body.R_wb, body.v_w_m_s)
            w_sum += body.omega_b_rad_s
        if progress is not None and k % 100 == 99:
            progress(100 * cfg.dt_s)
    n_avg = total - settle
    theta = np.arctan2(A[:, 1], A[:, 0])
    return np.concatenate([v_sum / n_avg, w_sum / n_avg, theta[:, None]], axis=1)


def sample_parameters(k: int, rng: np.random.Generator, a_max: float = 0.6, b_max: float = 0.3) -> np.ndarray:
    """(k, 4) parameter sets: amplitudes uniform in [0, a_max], biases in [-b_max, b_max] [rad]."""
    if k < 1 or not (a_max > 0 and b_max >= 0) or not math.isfinite(a_max + b_max):
        raise ValueError(f"need k >= 1, a_max > 0, b_max >= 0; got {k}, {a_max}, {b_max}")
    return rng.uniform([0.0, 0.0, -b_max, -b_max], [a_max, a_max, b_max, b_max], size=(k, 4))

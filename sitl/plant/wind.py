"""Steady wind plus Gauss-Markov gusts, as a drag force on every link centre."""

from __future__ import annotations

import math

import numpy as np

from sitl.scenario import WindConfig

__all__ = ["Wind"]


class Wind:
    """Steady wind plus Gauss-Markov gusts, as a drag force on every link centre."""

    def __init__(self, cfg: WindConfig, n_links: int, drag_area_m2: float, drag_coefficient: float,
                 rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self.gust = np.zeros(3)
        self.k = 0.5 * cfg.air_density_kg_m3 * drag_coefficient * drag_area_m2
        self.mean = np.asarray(cfg.mean_w_m_s, dtype=float)
        self.active = self.k > 0 and (np.any(self.mean != 0) or cfg.gust_std_m_s > 0)

    def force(self, v_w: np.ndarray, dt_s: float) -> np.ndarray | None:
        """(n, 3) drag forces for link velocities ``v_w`` (``None`` when there is no wind)."""
        if not self.active:
            return None
        cfg = self.cfg
        if cfg.gust_std_m_s > 0:
            a = math.exp(-dt_s / cfg.gust_time_constant_s)
            self.gust = a * self.gust + cfg.gust_std_m_s * math.sqrt(1 - a * a) * self.rng.normal(size=3)
        rel = self.mean + self.gust - v_w
        return self.k * np.linalg.norm(rel, axis=1, keepdims=True) * rel

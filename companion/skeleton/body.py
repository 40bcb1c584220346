"""The physical skeleton: links, their mass and inertia, the cable joints, gravity.

One description of the vehicle shared by every layer: the companion's chain model
(:mod:`.dynamics`), the link firmware (eq. 1 needs mass and inertia) and the simulator (the
MuJoCo model is generated from it). Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from companion.configfile import require_nonnegative, require_positive

from .rotors import RotorGeometry

__all__ = ["GRAVITY_M_S2", "GRAVITY_W_M_S2", "LinkInertia", "SkeletonConfig", "link_inertia"]

#: Standard gravity [m/s^2]; the world frame is z-up, so gravity is ``[0, 0, -GRAVITY_M_S2]``.
GRAVITY_M_S2 = 9.80665
#: Gravity vector in the world frame (z up) [m/s^2].
GRAVITY_W_M_S2 = (0.0, 0.0, -GRAVITY_M_S2)


@dataclass(frozen=True)
class LinkInertia:
    """Mass [kg] and principal inertia [kg m^2] of a link (body frame at the centre of mass)."""

    mass_kg: float
    inertia_kgm2: tuple[float, float, float]

    def __post_init__(self) -> None:
        require_positive(self, "mass_kg")
        if len(self.inertia_kgm2) != 3 or not all(x > 0 for x in self.inertia_kgm2):
            raise ValueError(f"inertia_kgm2 must be three positive numbers, got {self.inertia_kgm2!r}")

    @cached_property
    def J(self) -> np.ndarray:
        return np.diag(self.inertia_kgm2)


@dataclass(frozen=True)
class SkeletonConfig:
    """Physical skeleton: links, mass distribution, cable joints, aerodynamics.

    The link mass is split into a central hub (battery, electronics), a uniform bar and the
    eight rotors (point masses at the rotor positions), which gives the inertia.
    """

    n_links: int = 3
    link_length_m: float = 1.0
    link_mass_kg: float = 1.8
    rotor_mass_fraction: float = 0.35
    bar_mass_fraction: float = 0.25
    rotor_x_scale: float = 1.0
    bar_radius_m: float = 0.04
    joint_stiffness_nm_rad: float = 0.3
    joint_damping_nms_rad: float = 0.1
    joint_limit_deg: float = 150.0
    drag_area_m2: float = 0.1
    drag_coefficient: float = 1.0
    ground_friction: float = 0.8

    def __post_init__(self) -> None:
        if self.n_links < 1:
            raise ValueError(f"n_links must be >= 1, got {self.n_links}")
        require_positive(self, "link_length_m", "link_mass_kg", "rotor_x_scale", "bar_radius_m")
        if not (0 <= self.rotor_mass_fraction and 0 <= self.bar_mass_fraction
                and self.rotor_mass_fraction + self.bar_mass_fraction <= 1):
            raise ValueError(
                f"rotor_mass_fraction and bar_mass_fraction must be >= 0 and sum to at most 1, "
                f"got {self.rotor_mass_fraction} + {self.bar_mass_fraction}"
            )
        require_nonnegative(self, "joint_stiffness_nm_rad", "joint_damping_nms_rad", "drag_area_m2", "drag_coefficient",
                            "ground_friction")
        if not 0 < self.joint_limit_deg <= 180:
            raise ValueError(f"joint_limit_deg must be in (0, 180], got {self.joint_limit_deg}")
        if 0.4 * self.rotor_x_scale >= 0.5 * self.link_length_m:
            raise ValueError(
                f"rotor_x_scale puts the rotors (x = +-{0.4 * self.rotor_x_scale:.2f} m) beyond the link tips "
                f"(+-{0.5 * self.link_length_m:.2f} m)"
            )

    @property
    def d_b_m(self) -> np.ndarray:
        """(n, 3) centre-to-right-tip vectors (the ``d_i`` of eq. 3)."""
        return np.tile([0.5 * self.link_length_m, 0.0, 0.0], (self.n_links, 1))


def link_inertia(cfg: SkeletonConfig, geometry: RotorGeometry) -> LinkInertia:
    """Mass and principal inertia of one link from the hub / bar / rotor split."""
    m = cfg.link_mass_kg
    m_rot = cfg.rotor_mass_fraction * m / geometry.positions_m.shape[0]
    m_bar = cfg.bar_mass_fraction * m
    r = geometry.positions_m
    I = m_rot * (np.sum(r * r) * np.eye(3) - r.T @ r)
    L, a = cfg.link_length_m, cfg.bar_radius_m
    I += np.diag([0.5 * m_bar * a * a, m_bar * (L * L / 12 + a * a / 4), m_bar * (L * L / 12 + a * a / 4)])
    # The hub is a point mass at the centre: no inertia. Table 2.1's symmetry makes I diagonal.
    return LinkInertia(mass_kg=m, inertia_kgm2=tuple(float(x) for x in np.diag(I)))

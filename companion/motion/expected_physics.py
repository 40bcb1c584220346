"""Target poses from the CPG shape through an imaginary water (thesis sec. 4.4), pure numpy.

The CPG (:mod:`.cpg`) gives the shape: every link's attitude ``R_BLi`` and body rate
``omega_BLi^Li`` in the body frame ``{B}``, whose origin is the chain's centre of mass. The
body motion comes from simulating that shape in water:

* chain kinematics in ``{B}`` (sec. 4.4, the ``p_OLi`` / ``v_OLi`` formulas written in the body
  frame): ``r_1 = -p_1,CoM``, ``r_{i+1} = r_i + (R_BLi + R_BL(i+1)) l_h``, with ``p_1,CoM`` making
  the link centres average to 0, and their rates ``r_i'`` from ``R_BLj S(omega_j) l_h``;
* resistive drag on every link (sec. 4.4, first equation), axial and normal parts with their
  own area and coefficient, *opposing* the link's velocity through the water (the thesis prints
  the magnitude without the sign);
* the wrench on the body ``f^B = sum R_BLi f_i``, ``tau^B = sum r_i x R_BLi f_i``, and the
  rigid body ``m p'' = R_OB f^B``, ``J omega' + omega x J omega = tau^B``, ``R' = R S(omega)``
  integrated with the passive midpoint rule for the free rotation (the thesis's PMI, used
  "partially, not including the external wrench"): the midpoint angular velocity solves
  ``J (w1 - w0) / dt + w_m x J w_m = tau`` by fixed-point iteration and ``R1 = R0 exp(S(dt w_m))``,
  which keeps the torque-free kinetic energy and the angular momentum's norm (its direction in
  the world to second order);
* the targets (sec. 4.4, last block): ``R_OLi = R_OB R_BLi``, ``omega_OLi^Li = R_BLi^T omega_OB^B
  + omega_BLi^Li``, ``p_OLi = p_OB + R_OB r_i``, ``v_OLi = v_OB + R_OB (omega_OB^B x r_i + r_i')``.

By construction the targets satisfy the chain constraint of eq. 3 exactly (tested with the
estimation core's residual). Every function takes leading batch dimensions (one body per CPG
parameter set), which is how a dataset of steady motions is simulated at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.configfile import require_positive
from companion.estimation.so3 import cross
from companion.skeleton.kinematics import chain_offsets

from .cpg import so3_exp

__all__ = ["WaterParams", "BodyState", "chain_shape", "link_drag", "body_wrench", "body_step", "link_targets"]


@dataclass(frozen=True)
class WaterParams:
    """The expected physics: water density, per-link drag areas and coefficients, body inertia.

    The drag is anisotropic like a slender body's (normal >> axial), which is what turns an
    undulation into thrust. ``mass_kg`` and ``inertia_kg_m2`` (diagonal, body frame) are the
    expected body's, including added mass (thesis: ``m_exp``, ``J_exp``). The steady motions
    (the inverse model's data) hardly depend on them; the transients do: the defaults (5 kg,
    lighter than the 12.6 kg flying chain) let a speed command settle in a few undulation
    periods (20 kg took over 15 s from rest to 0.25 m/s).
    """

    density_kg_m3: float = 1000.0
    area_axial_m2: float = 0.003
    area_normal_m2: float = 0.06
    cd_axial: float = 0.2
    cd_normal: float = 1.2
    mass_kg: float = 5.0
    inertia_kg_m2: tuple[float, float, float] = (0.5, 5.0, 5.0)

    def __post_init__(self) -> None:
        require_positive(self, "density_kg_m3", "area_axial_m2", "area_normal_m2", "cd_axial", "cd_normal", "mass_kg")
        if len(self.inertia_kg_m2) != 3 or not all(x > 0 for x in self.inertia_kg_m2):
            raise ValueError(f"inertia_kg_m2 must be three positive principal moments, got {self.inertia_kg_m2}")


@dataclass(frozen=True)
class BodyState:
    """Body frame ``{B}`` in the world: position, velocity (world), attitude, body rate."""

    p_w_m: np.ndarray
    v_w_m_s: np.ndarray
    R_wb: np.ndarray
    omega_b_rad_s: np.ndarray

    @classmethod
    def at_rest(cls, p_w_m=(0.0, 0.0, 0.0), yaw_rad: float = 0.0, batch: tuple[int, ...] = ()) -> BodyState:
        """At rest; ``batch``: leading dimensions for independent bodies."""
        p = np.broadcast_to(np.asarray(p_w_m, dtype=float), batch + (3,)).copy()
        R = np.broadcast_to(so3_exp(np.array([0.0, 0.0, yaw_rad])), batch + (3, 3)).copy()
        return cls(p, np.zeros(batch + (3,)), R, np.zeros(batch + (3,)))


def chain_shape(R_bl: np.ndarray, omega_bl_l: np.ndarray, half_length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Link centres ``r_i`` (..., n, 3) and their rates ``r_i'`` in ``{B}`` (centroid at 0)."""
    r, rd = chain_offsets(R_bl, omega_bl_l, np.array([half_length_m, 0.0, 0.0]))
    return r - r.mean(axis=-2, keepdims=True), rd - rd.mean(axis=-2, keepdims=True)


def link_drag(v_l: np.ndarray, water: WaterParams) -> np.ndarray:
    """(..., 3) drag force on each link in its own frame, for its velocity ``v_l`` through the water."""
    v_ax = v_l * np.array([1.0, 0.0, 0.0])
    v_n = v_l - v_ax
    k_ax = 0.5 * water.density_kg_m3 * water.area_axial_m2 * water.cd_axial
    k_n = 0.5 * water.density_kg_m3 * water.area_normal_m2 * water.cd_normal
    return -(k_ax * np.linalg.norm(v_ax, axis=-1, keepdims=True) * v_ax
             + k_n * np.linalg.norm(v_n, axis=-1, keepdims=True) * v_n)


def _link_velocities_b(body: BodyState, r: np.ndarray, rd: np.ndarray) -> np.ndarray:
    """(..., n, 3) link-centre velocities in ``{B}``."""
    v_b = np.einsum("...ji,...j->...i", body.R_wb, body.v_w_m_s)[..., None, :]
    return v_b + cross(body.omega_b_rad_s[..., None, :], r) + rd


def body_wrench(body: BodyState, R_bl: np.ndarray, omega_bl_l: np.ndarray, half_length_m: float,
                water: WaterParams) -> tuple[np.ndarray, np.ndarray]:
    """``(f^B, tau^B)``: the drag on every link summed about the centre of mass, in ``{B}``."""
    r, rd = chain_shape(R_bl, omega_bl_l, half_length_m)
    v_l = np.einsum("...ji,...j->...i", R_bl, _link_velocities_b(body, r, rd))  # R_BLi^T v
    f_b = np.einsum("...ij,...j->...i", R_bl, link_drag(v_l, water))
    return f_b.sum(axis=-2), cross(r, f_b).sum(axis=-2)


def body_step(body: BodyState, f_b: np.ndarray, tau_b: np.ndarray, water: WaterParams, dt_s: float,
              iterations: int = 4) -> BodyState:
    """One step of the body dynamics: passive midpoint rule for the rotation (see the module
    docstring), midpoint rule for the translation, the wrench held over the step."""
    J = np.asarray(water.inertia_kg_m2, dtype=float)
    w0 = body.omega_b_rad_s
    w1 = w0.copy()
    for _ in range(iterations):
        wm = 0.5 * (w0 + w1)
        w1 = w0 + dt_s * (tau_b - cross(wm, J * wm)) / J
    wm = 0.5 * (w0 + w1)
    R1 = body.R_wb @ so3_exp(dt_s * wm)
    Rm = body.R_wb @ so3_exp(0.5 * dt_s * wm)
    v1 = body.v_w_m_s + dt_s * np.einsum("...ij,...j->...i", Rm, f_b) / water.mass_kg
    p1 = body.p_w_m + 0.5 * dt_s * (body.v_w_m_s + v1)
    return BodyState(p1, v1, R1, w1)


def link_targets(body: BodyState, R_bl: np.ndarray, omega_bl_l: np.ndarray, half_length_m: float):
    """Every link's target: ``(p_w (n,3), v_w (n,3), R_wl (n,3,3), omega_l (n,3))`` (sec. 4.4)."""
    r, rd = chain_shape(R_bl, omega_bl_l, half_length_m)
    R_wb = body.R_wb[..., None, :, :]
    R_wl = R_wb @ R_bl
    omega_l = np.einsum("...ji,...j->...i", R_bl, body.omega_b_rad_s[..., None, :]) + omega_bl_l
    p_w = body.p_w_m[..., None, :] + np.einsum("...ij,...j->...i", R_wb, r)
    v_w = body.v_w_m_s[..., None, :] + np.einsum("...ij,...j->...i", R_wb, _link_velocities_b(
        BodyState(body.p_w_m, np.zeros_like(body.v_w_m_s), body.R_wb, body.omega_b_rad_s), r, rd))
    return p_w, v_w, R_wl, omega_l

"""Can a link hold a neighbour whose rotors stopped? Static thrust needs of carrying (pure).

When a link of the chain loses power in flight (a reboot, a dead battery), it hangs on its
joints and its neighbours hold its weight: a link at the end of the chain hangs from one
neighbour's tip, which then holds all of it; a link inside the chain hangs between two, each
holding about half. The carrier hovers with that load on a tip, ``L/2`` from its centre of mass,
so its rotors must give, besides its own weight, the load's force and the torque of the load
about the centre of mass. Its rotor thrusts with the least largest magnitude are the minimum
infinity-norm allocation of eq. 2.12 (Prop. 1, :func:`~link_firmware_sim.allocation.mapping.infinity_norm_allocation`)
of that wrench (eq. 2.8); the link can hold the load while that magnitude is within
``thrust_max_n``.

The carrier's pitch changes the torque arm (``L/2 cos(pitch)``): level (``pitch = 0``), as it
flies, is the worst; hanging vertical under the load needs no torque. Static only: the fall
before the joint takes the load, the swing after it and the joints' stiffness (under 0.5 N m
here) come on top, so a need near the limit is already beyond it in flight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.skeleton.rotors import RotorGeometry

from ..allocation.mapping import infinity_norm_allocation, pseudo_inverse

__all__ = ["GRAVITY_M_S2", "CarryCase", "tip_load_thrust_n", "carry_cases"]

GRAVITY_M_S2 = 9.81


def _pitch_matrix(pitch_rad: float) -> np.ndarray:
    c, s = np.cos(pitch_rad), np.sin(pitch_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def tip_load_thrust_n(geometry: RotorGeometry, mass_kg: float, length_m: float, load_n: float,
                      pitch_deg: float = 0.0) -> float:
    """The largest rotor thrust magnitude [N] with which a link of ``mass_kg`` and ``length_m``,
    pitched ``pitch_deg`` about its body y axis, hovers holding ``load_n`` hanging from its tip
    at body ``-x`` (minimum infinity-norm allocation, eq. 2.12)."""
    R = _pitch_matrix(np.radians(pitch_deg))  # body -> world
    f_w = np.array([0.0, 0.0, mass_kg * GRAVITY_M_S2 + load_n])  # the rotors' force
    tip_w = R @ np.array([-0.5 * length_m, 0.0, 0.0])
    torque_w = -np.cross(tip_w, np.array([0.0, 0.0, -load_n]))  # cancels the load's torque
    U = np.concatenate([R.T @ f_w, R.T @ torque_w])
    _, _, lam = infinity_norm_allocation(pseudo_inverse(geometry.mapping_matrix()), U)
    return float(np.max(np.abs(lam)))


@dataclass(frozen=True)
class CarryCase:
    """One case: what the carrier holds at its tip, the thrust it needs level and at its best
    pitch, and whether that is within ``thrust_max_n``."""

    case: str
    load_n: float
    level_thrust_n: float
    best_pitch_deg: float
    best_thrust_n: float
    thrust_max_n: float

    @property
    def level_ratio(self) -> float:
        """Needed over available, level: above 1 the link cannot hold the load."""
        return self.level_thrust_n / self.thrust_max_n

    def as_dict(self) -> dict:
        return {"case": self.case, "load_n": round(self.load_n, 3), "level_thrust_n": round(self.level_thrust_n, 3),
                "level_ratio": round(self.level_ratio, 3), "best_pitch_deg": self.best_pitch_deg,
                "best_thrust_n": round(self.best_thrust_n, 3), "thrust_max_n": self.thrust_max_n,
                "holds_level": self.level_ratio <= 1.0}


def carry_cases(geometry: RotorGeometry, mass_kg: float, length_m: float, thrust_max_n: float,
                pitch_step_deg: float = 5.0) -> list[CarryCase]:
    """The three cases of a chain of identical links: hovering alone, holding half a dead
    neighbour's weight (a dead link inside the chain) and all of it (a dead end link); each
    level and at the pitch (0..90 deg, ``pitch_step_deg`` apart) that needs the least."""
    weight = mass_kg * GRAVITY_M_S2
    pitches = np.arange(0.0, 90.0 + 1e-9, pitch_step_deg)
    out = []
    for case, load in (("own weight", 0.0), ("dead link inside the chain (half its weight)", 0.5 * weight),
                       ("dead end link (all its weight)", weight)):
        needs = [tip_load_thrust_n(geometry, mass_kg, length_m, load, p) for p in pitches]
        k = int(np.argmin(needs))
        out.append(CarryCase(case, load, needs[0], float(pitches[k]), needs[k], thrust_max_n))
    return out

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
flies, is the worst; hanging vertical under the load needs no torque.

The rest of the chain can help the carrier: a link pulling down on the carrier's other tip
takes some of the load's torque off it (and adds to its force), and so on along the chain.
:func:`chain_hold_thrust_n` finds the best such sharing for a level chain of ``n`` links on ball
joints with some of them dead: a linear program in every live link's eight thrusts and every
joint's force, each live link's wrench (eq. 2.8) balancing its weight and its joints' forces,
each dead link hanging from its joints (its weight theirs; held level between two, hanging
below one at the chain's end),
minimising the largest thrust magnitude. Static only: the fall before the joint takes the load,
the swing after it and the joints' stiffness (under 0.5 N m here) come on top, so a need near the
limit is already beyond it in flight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.estimation.so3 import skew
from companion.skeleton.rotors import RotorGeometry

from ..allocation.mapping import infinity_norm_allocation, pseudo_inverse

__all__ = ["GRAVITY_M_S2", "CarryCase", "tip_load_thrust_n", "chain_hold_thrust_n", "carry_cases"]

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


def chain_hold_thrust_n(geometry: RotorGeometry, n_links: int, mass_kg: float, length_m: float,
                        dead: tuple[int, ...] = ()) -> float:
    """The largest rotor thrust magnitude [N] with which a level chain of ``n_links`` links (in a
    line along x, joined tip to tip by ball joints) hovers with the 0-based links ``dead``
    powerless, every live link sharing the load as best it can (module docstring; ``inf`` if
    no thrusts balance it)."""
    from scipy.optimize import linprog  # (the design tool's; the firmware never imports this module)

    n, B, W = int(n_links), geometry.mapping_matrix(), mass_kg * GRAVITY_M_S2
    if n < 1 or any(not 0 <= d < n for d in dead) or len(set(dead)) == len(range(n)):
        raise ValueError(f"dead links {dead}: a chain of {n} links with at least one alive")
    live = [i for i in range(n) if i not in dead]
    nj = 3 * (n - 1)  # joint j's force on link j + 1 (link j gets the opposite)
    nv = 8 * len(live) + nj + 1  # ... and the bound s on |thrust|
    jf = 8 * len(live)
    tips = (np.array([-0.5 * length_m, 0.0, 0.0]), np.array([0.5 * length_m, 0.0, 0.0]))
    rows, rhs = [], []
    for i in range(n):
        force, moment = np.zeros((3, nv)), np.zeros((3, nv))
        if i > 0:  # joint i - 1 at the left tip pushes with +F
            force[:, jf + 3 * (i - 1):jf + 3 * i] += np.eye(3)
            moment[:, jf + 3 * (i - 1):jf + 3 * i] += skew(tips[0])
        if i < n - 1:  # joint i at the right tip pushes with -F
            force[:, jf + 3 * i:jf + 3 * i + 3] -= np.eye(3)
            moment[:, jf + 3 * i:jf + 3 * i + 3] -= skew(tips[1])
        if i in live:
            k = 8 * live.index(i)
            force[:, k:k + 8] += B[:3]
            moment[:, k:k + 8] += B[3:]
        rows.append(force)
        rhs.append(np.array([0.0, 0.0, W]))
        if i in live or 0 < i < n - 1:  # (a dead end link hangs below its one joint: no moment to hold)
            rows.append(moment)
            rhs.append(np.zeros(3))
    bound = np.zeros((2 * (nv - nj - 1), nv))
    for k in range(nv - nj - 1):
        bound[2 * k, k], bound[2 * k + 1, k] = 1.0, -1.0
    bound[:, -1] = -1.0
    res = linprog(np.eye(nv)[-1], A_ub=bound, b_ub=np.zeros(len(bound)), A_eq=np.vstack(rows), b_eq=np.concatenate(rhs),
                  bounds=[(None, None)] * (nv - 1) + [(0.0, None)], method="highs")
    return float(res.x[-1]) if res.success else float("inf")


@dataclass(frozen=True)
class CarryCase:
    """One case: what a neighbour holds at its tip (``load_n``), the thrust it needs for it alone,
    level and at its best pitch, the thrust the whole level chain needs with that link dead
    (``chain_thrust_n``, :func:`chain_hold_thrust_n`), against ``thrust_max_n``."""

    case: str
    load_n: float
    level_thrust_n: float
    best_pitch_deg: float
    best_thrust_n: float
    chain_thrust_n: float
    thrust_max_n: float

    @property
    def level_ratio(self) -> float:
        """Needed over available, one neighbour alone, level."""
        return self.level_thrust_n / self.thrust_max_n

    @property
    def chain_ratio(self) -> float:
        """Needed over available, the whole chain level: above 1 it cannot hold the dead link."""
        return self.chain_thrust_n / self.thrust_max_n

    def as_dict(self) -> dict:
        return {"case": self.case, "load_n": round(self.load_n, 3), "level_thrust_n": round(self.level_thrust_n, 3),
                "level_ratio": round(self.level_ratio, 3), "best_pitch_deg": self.best_pitch_deg,
                "best_thrust_n": round(self.best_thrust_n, 3), "chain_thrust_n": round(self.chain_thrust_n, 3),
                "chain_ratio": round(self.chain_ratio, 3), "thrust_max_n": self.thrust_max_n,
                "chain_holds": self.chain_ratio <= 1.0}


def carry_cases(geometry: RotorGeometry, n_links: int, mass_kg: float, length_m: float, thrust_max_n: float,
                pitch_step_deg: float = 5.0) -> list[CarryCase]:
    """The cases of a chain of ``n_links`` identical links: hovering with none dead, with a dead
    link inside the chain (the middle one; a neighbour alone holds half its weight; with three
    links or more) and with a dead end link (a neighbour alone holds all of it; with two or
    more): each neighbour alone level and at the pitch (0..90 deg, ``pitch_step_deg`` apart)
    that needs the least, and the whole chain level."""
    weight = mass_kg * GRAVITY_M_S2
    pitches = np.arange(0.0, 90.0 + 1e-9, pitch_step_deg)
    cases = [("own weight", 0.0, ())]
    if n_links >= 3:
        cases.append(("dead link inside the chain (half its weight)", 0.5 * weight, (n_links // 2,)))
    if n_links >= 2:
        cases.append(("dead end link (all its weight)", weight, (0,)))
    out = []
    for case, load, dead in cases:
        needs = [tip_load_thrust_n(geometry, mass_kg, length_m, load, p) for p in pitches]
        k = int(np.argmin(needs))
        out.append(CarryCase(case, load, needs[0], float(pitches[k]), needs[k],
                             chain_hold_thrust_n(geometry, n_links, mass_kg, length_m, dead), thrust_max_n))
    return out

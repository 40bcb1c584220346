"""A carried link bridges a neighbour without GPS to its other neighbour.

A link whose rotors are off (carried: :mod:`.carrying`) is silent, so the step leaves it out and
the chain splits there. A neighbour of it that has nothing else to join (an end link, or one whose
other side is left out too) is alone in its part and gets no correction. With its GPS healthy that
costs little; with its GPS in fault it dead-reckons with nothing to correct it, and a carrier
running near its rotors' limit drifts fast (metres in seconds).

Yet the carried link still joins it to its other neighbour: a rigid body hanging from both their
tips, which the whole-chain feed-forward holds where its target puts it. So a link that flags a
GPS fault and is left uncorrected by the step, next to a carried link whose other neighbour is
usable and healthy (:class:`Bridge`), gets a position correction through it
(:func:`bridged_position`): the healthy neighbour's tip (its corrected state when it was
corrected), the carried link's length along its target's axis, then its own tip. Its attitude and
velocity are not corrected: a carried link swings, and nothing measures how. The position's
spread is the carried link's attitude off its target, :data:`BRIDGE_ATT_STD_RAD` (about 0.35 m at
the tip of a 1 m link); the link fuses it as any correction while its GPS is in fault
(``link_firmware_sim.estimators.correction_aid``), where alone it would drift without bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..estimation.chain import ERR_P
from ..estimation.constraints import tip_offsets
from ..messages import Correction, LinkState

__all__ = ["BRIDGE_ATT_STD_RAD", "Bridge", "bridged_position", "bridge_correction"]

#: How far a carried link's attitude may be from its target's [rad] (per axis): it sags and swings
#: between its carriers
BRIDGE_ATT_STD_RAD = math.radians(20.0)


@dataclass(frozen=True)
class Bridge:
    """Rows of one engine: a ``carried`` link, its neighbour ``faulty`` (GPS fault) and its other
    neighbour ``healthy``."""

    carried: int
    faulty: int
    healthy: int


def bridged_position(p_healthy, q_healthy, d_healthy, q_carried, d_carried, q_faulty, d_faulty,
                     faulty_right: bool) -> np.ndarray:
    """The faulty link's centre [m] through the carried link: from the healthy link's tip on the
    carried link's side, along the carried link (tip to tip, ``2 R d``) at its attitude
    ``q_carried``, to the faulty link's centre. ``d_*``: each link's right-tip vector (body);
    ``faulty_right``: the faulty link is on the carried link's right (higher index)."""
    a, _ = tip_offsets(np.array([q_healthy, q_carried, q_faulty], dtype=float), np.zeros((3, 3)),
                       np.array([d_healthy, d_carried, d_faulty], dtype=float))
    s = 1.0 if faulty_right else -1.0
    return np.asarray(p_healthy, dtype=float) + s * (a[0] + 2.0 * a[1] + a[2])


def bridge_correction(faulty: LinkState, healthy: LinkState, q_carried, d: np.ndarray, faulty_right: bool,
                      seq: int) -> tuple[Correction, LinkState]:
    """The faulty link's correction (position only) and corrected state through the carried link,
    ``healthy`` aligned to the faulty link's stamp; ``d``: the right-tip vectors of the healthy, the
    carried and the faulty link. The corrected position's covariance: the healthy link's plus the
    carried link's attitude spread at its length."""
    dt = faulty.time_s - healthy.time_s
    p_healthy = healthy.p_w_m + healthy.v_w_m_s * dt
    p = bridged_position(p_healthy, healthy.q_wxyz, d[0], q_carried, d[1], faulty.q_wxyz, d[2], faulty_right)
    dp = p - faulty.p_w_m
    P = np.array(faulty.P, dtype=float)
    spread = (2.0 * float(np.linalg.norm(d[1])) * BRIDGE_ATT_STD_RAD) ** 2
    P[ERR_P, ERR_P] = healthy.P[ERR_P, ERR_P] + spread * np.eye(3)
    correction = Correction(faulty.link, faulty.time_s, dp, np.zeros(3), np.zeros(3), seq)
    corrected = LinkState(faulty.link, faulty.time_s, p, faulty.v_w_m_s, faulty.q_wxyz, faulty.omega_b_rad_s, P)
    return correction, corrected

"""A link left out of the step still joins its neighbours: it bridges one without GPS to the other.

A link the step leaves out (silent: its rotors off and carried, :mod:`.carrying`, or its MAVLink
link failed; or excluded for its state) splits the chain there. A neighbour of it that has nothing
else to join (an end link, or one whose other side is left out too) is alone in its part and gets no
correction. With its GPS healthy that costs little; with its GPS in fault it dead-reckons with
nothing to correct it, and a carrier running near its rotors' limit drifts fast (metres in
seconds).

Yet the link left out is still there: a rigid body between its neighbours' tips, which are
therefore exactly its length apart, whatever it does. That much is known; which way it points is
not (a carried link swings between its carriers, and nothing measures it: its target says where it
should be, not where the faulty neighbour's drift has turned it). So a link that flags a GPS fault
and is left uncorrected by the step, next to a link left out whose other neighbour is usable and
healthy (:class:`Bridge`), gets a position correction along the line between the two tips, to the
length of the link between them (:func:`bridged_position`), and none across it; its attitude and
velocity are not corrected. The link fuses it as any correction while its GPS is in fault
(``link_firmware_sim.estimators.correction_aid``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..corrections import align_states
from ..estimation.chain import ERR_P
from ..estimation.constraints import tip_offsets
from ..messages import Correction, LinkState

__all__ = ["Bridge", "bridged_position", "bridge_correction"]


@dataclass(frozen=True)
class Bridge:
    """Rows of one engine: a link left ``out`` of the step, its neighbour ``faulty`` (GPS fault) and
    its other neighbour ``healthy``."""

    out: int
    faulty: int
    healthy: int


def bridged_position(p_healthy, q_healthy, d_healthy, d_out, p_faulty, q_faulty, d_faulty,
                     faulty_right: bool) -> tuple[np.ndarray, np.ndarray]:
    """The faulty link's centre [m] moved along the line from the healthy link's tip to its own
    (the two tips the link left out joins) until they are that link's length, ``2 |d_out|``, apart;
    and that line's unit vector (zero, and the centre unmoved, if the tips coincide). ``d_*``: each
    link's right-tip vector (body); ``faulty_right``: the faulty link is on the right (higher
    index) of the link left out."""
    a, _ = tip_offsets(np.array([q_healthy, q_faulty], dtype=float), np.zeros((2, 3)),
                       np.array([d_healthy, d_faulty], dtype=float))
    s = 1.0 if faulty_right else -1.0
    p_faulty = np.asarray(p_faulty, dtype=float)
    r = (p_faulty - s * a[1]) - (np.asarray(p_healthy, dtype=float) + s * a[0])
    dist = float(np.linalg.norm(r))
    if dist < 1e-9:
        return p_faulty.copy(), np.zeros(3)
    u = r / dist
    return p_faulty + (2.0 * float(np.linalg.norm(d_out)) - dist) * u, u


def bridge_correction(faulty: LinkState, healthy: LinkState, d: np.ndarray, faulty_right: bool,
                      seq: int) -> tuple[Correction, LinkState]:
    """The faulty link's correction (position, along the tips' line only) and corrected state
    through the link left out, ``healthy`` propagated to the faulty link's stamp
    (:func:`~companion.corrections.align_states`); ``d``: the right-tip vectors of the healthy
    link, the link left out and the faulty link. The corrected position's covariance: the faulty
    link's across the line, the healthy link's along it."""
    _, p_healthy, _, q_healthy = align_states([healthy], faulty.time_s)
    p, u = bridged_position(p_healthy[0], q_healthy[0], d[0], d[1], faulty.p_w_m, faulty.q_wxyz, d[2], faulty_right)
    P = np.array(faulty.P, dtype=float)
    across = np.eye(3) - np.outer(u, u)
    P[ERR_P, ERR_P] = across @ P[ERR_P, ERR_P] @ across + float(u @ healthy.P[ERR_P, ERR_P] @ u) * np.outer(u, u)
    correction = Correction(faulty.link, faulty.time_s, p - faulty.p_w_m, np.zeros(3), np.zeros(3), seq)
    corrected = LinkState(faulty.link, faulty.time_s, p, faulty.v_w_m_s, faulty.q_wxyz, faulty.omega_b_rad_s, P)
    return correction, corrected

"""Each link's state word: what a SITL run logs as ``link_state`` (log ticks x links, ``uint8``),
its MCAP's ``/link{i}/state`` and the 3D view's colours.

The low four bits are the link's own report (the dialect's SKELETON_STATE_FLAGS,
:data:`companion.messages.STATE_FLAG_EKF_OK` and the others); the companion and the simulator add
what only they know: the link is carried (its rotors taken to be off, the neighbours take its
weight), it was left out of the companion's last step, or its vehicle has no power (killed,
rebooting, its process gone). :func:`condition` names the one that matters most to a person
watching the chain.
"""

from __future__ import annotations

import numpy as np

from .messages import STATE_FLAG_ARMED, STATE_FLAG_EKF_OK, STATE_FLAG_GPS_FAULT

__all__ = ["CARRIED", "EXCLUDED", "DOWN", "CONDITIONS", "word", "condition", "conditions"]

#: the companion takes the link's rotors to be off (its neighbours carry it)
CARRIED = 16
#: the link took no part in the companion's last step (stale, gated, out of its segment)
EXCLUDED = 32
#: the link's vehicle has no power or no process (killed, not restarted yet)
DOWN = 64

#: a link's conditions, most important first (what :func:`condition` picks from)
CONDITIONS = ("down", "no_ekf", "gps_fault", "excluded", "carried", "disarmed", "flying")


def word(flags, *, carried=False, excluded=False, down=False):
    """A link's state word from its reported ``flags`` and what the companion and simulator know:
    an ``int`` for scalars, a ``uint8`` array (broadcast) for arrays of them."""
    if all(np.ndim(x) == 0 for x in (flags, carried, excluded, down)):
        return (int(flags) & 0x0F) | (CARRIED if carried else 0) | (EXCLUDED if excluded else 0) | (DOWN if down else 0)
    out = (np.asarray(flags, dtype=np.int64) & 0x0F) | np.where(carried, CARRIED, 0) | np.where(excluded, EXCLUDED, 0)
    return (out | np.where(down, DOWN, 0)).astype(np.uint8)


def condition(w: int) -> str:
    """The condition of state word ``w`` that matters most (one of :data:`CONDITIONS`)."""
    w = int(w)
    if w & DOWN:
        return "down"
    if not w & STATE_FLAG_EKF_OK:
        return "no_ekf"
    if w & STATE_FLAG_GPS_FAULT:
        return "gps_fault"
    if w & EXCLUDED:
        return "excluded"
    if w & CARRIED:
        return "carried"
    return "flying" if w & STATE_FLAG_ARMED else "disarmed"


def conditions(words: np.ndarray) -> list[str]:
    """:func:`condition` of every word of ``words``."""
    return [condition(w) for w in np.asarray(words).ravel().tolist()]

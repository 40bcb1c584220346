"""Every compiled kernel a simulation runs (the firmware's, the companion's, the rotors', the
IMU's) compiled, or loaded from numba's on-disk cache, before a flight needs it."""

from __future__ import annotations

import logging
import threading
import time

from companion.kernels import warm as _companion_kernels
from link_firmware_sim.kernels import warm as _firmware_kernels

from .plant.rotor import warm_up as warm_up_rotors
from .plant.sensors import warm_up as warm_up_sensors

__all__ = ["COMPILING_NOTE_S", "warm_up_kernels"]

log = logging.getLogger(__name__)

#: a warm-up still running after this long [s] is compiling, and says so (a load takes well under it)
COMPILING_NOTE_S = 3.0


def warm_up_kernels(*, batch_only: bool = False, cpg: bool = True) -> float:
    """The compiled kernels of a simulation (the firmware's, the companion's, the rotors', the IMU's)
    compiled, or loaded from numba's on-disk cache, now; returns the seconds it took (next to none
    without numba). ``batch_only``: those a batch flight runs (not the fleet's lockstep); ``cpg``: the
    CPG motion generator's too. A warm-up that outlasts :data:`COMPILING_NOTE_S` says why it may be
    long (a machine's first run compiles)."""
    t0 = time.perf_counter()
    note = threading.Timer(COMPILING_NOTE_S, log.warning, ("loading the simulator's compiled kernels; a first run on "
                                                           "this machine compiles them (a minute or two, once), later "
                                                           "runs load them from numba's cache",))
    note.daemon = True
    note.start()
    try:
        _firmware_kernels.warm_up(lockstep=not batch_only)
        _companion_kernels.warm_up(cpg=cpg)
        warm_up_rotors()
        warm_up_sensors()
    finally:
        note.cancel()
    seconds = time.perf_counter() - t0
    if seconds > COMPILING_NOTE_S:
        log.warning("kernels ready in %.0f s", seconds)
    return seconds

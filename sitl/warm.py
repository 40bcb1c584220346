"""The compiled kernels a simulation runs (the firmware's, the companion's, the rotors', the
IMU's) compiled, or loaded from numba's on-disk cache, before a flight needs them."""

from __future__ import annotations

import logging
import time
from typing import Literal

from companion.kernels import warm as _companion_kernels
from link_firmware_sim.kernels import warm as _firmware_kernels

from .plant.rotor import warm_up as warm_up_rotors
from .plant.sensors import warm_up as warm_up_sensors

__all__ = ["warm_up_kernels"]

log = logging.getLogger(__name__)


def warm_up_kernels(mode: Literal["all", "batch", "fleet"] = "all", *, cpg: bool = True,
                    companion: bool = True) -> float:
    """The compiled kernels of a simulation compiled, or loaded from numba's on-disk cache, now;
    returns the seconds it took (next to none without numba). ``mode``: those a batch flight runs
    (the firmware's tick and batch tick, the companion's, the rotors', the IMU's), those a fleet's
    launcher warms for its vehicles, its companions and itself (the firmware's tick and lockstep,
    the companion's, the rotors', the IMU's), or all of them; ``companion``: with the companion's
    (a fleet whose companions run the numpy path, or that starts none, passes false); ``cpg``:
    with the companion's, the CPG motion generator's. A long warm-up says why
    (:func:`~companion.kernels.warm.compile_notice`)."""
    if mode not in ("all", "batch", "fleet"):
        raise ValueError(f"warm-up mode {mode!r}: one of 'all', 'batch', 'fleet'")
    t0 = time.perf_counter()
    with _companion_kernels.compile_notice("the simulator's compiled kernels", log):
        _firmware_kernels.warm_up(lockstep=mode != "batch", batch=mode != "fleet")
        if companion:
            _companion_kernels.warm_up(cpg=cpg)
        warm_up_rotors()
        warm_up_sensors()
    return time.perf_counter() - t0

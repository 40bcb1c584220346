"""Compile (first run) or load from numba's cache (later runs) every firmware kernel, for the
argument types the firmware, the vehicle and the simulator's link reader pass, before the first
tick needs them; the fleet launcher calls it before it starts the vehicle processes, so that n
vehicles load one cache instead of compiling n times.

It imports the kernels it warms, never their callers: each is compiled for the signature of example
arguments built as its callers build theirs (C-contiguous writeable arrays, tuples of them, a
record received as read-only bytes, Python floats, ints and bools), without running it.
``tests/unit/test_fast_paths.py`` checks that the firmware then finds every signature it uses.
"""

from __future__ import annotations

import time

import numpy as np

from companion.kernels.jit import ENABLED
from companion.kernels.warm import load

from .allocation import ALLOC_META, allocate_kernel
from .batch_tick import BANK_SIZE, links_tick_kernel
from .ekf import attitude_update_kernel, ekf_predict_kernel, update_block_kernel, update_rows_kernel
from .hil_records import HIL_ACTUATOR_RECORD, HIL_SENSOR_RECORD, sensor_record_at, sensor_records
from .impedance import impedance_kernel
from .layouts import ALLOC_SIZE, CTL_SIZE, EKF_SIZE, IN_SIZE, IO_SIZE, OUT_SIZE, TGT_SIZE
from .lockstep import hil_loop_kernel
from .mavlink_frames import FRAME_BYTES, FRAMING_SIZE, frames_to_records, records_to_frames
from .tick import attitude_tick_kernel, hil_tick_kernel, tick_kernel

__all__ = ["ENABLED", "warm_up"]


def warm_up(*, lockstep: bool = True, batch: bool = True) -> float:
    """The firmware's kernels compiled or loaded; returns the seconds it took (0 without the
    compiled kernels). The tick's kernels always; ``lockstep``: the fleet's (the vehicle's lockstep
    loop and the simulator link's records, on both sides), ``batch``: the batch mode's every-link
    tick. A process warms only what it runs: compiling a kernel takes seconds, on a first run."""
    if not ENABLED:
        return 0.0
    t0 = time.perf_counter()
    v3, v6 = np.zeros(3), np.zeros(6)
    ekf_par, cmd, ctl, io = np.zeros(EKF_SIZE), np.zeros(IN_SIZE), np.zeros(CTL_SIZE), np.zeros(IO_SIZE)
    alloc = (np.zeros((8, 6)), np.zeros((2, 4, 4, 6)), np.zeros(ALLOC_SIZE))
    x, P = np.zeros(16), np.zeros((15, 15))  # (with the barometer's offset: the same types)
    load(ekf_predict_kernel, x, P, v3, v3, 0.002, ekf_par)
    load(update_block_kernel, x, P, v3, 0, np.zeros((3, 3)), 5.0)
    load(update_rows_kernel, x, P, np.zeros(1), np.zeros((1, 15)), np.zeros((1, 1)), 5.0)
    load(attitude_update_kernel, x, P, np.zeros(4), ekf_par)
    load(impedance_kernel, v3, v3, np.zeros(4), v3, np.zeros(TGT_SIZE), ctl, 0.002, v6)
    load(allocate_kernel, v6, v6, alloc, np.zeros((5, 8)), np.zeros(ALLOC_META))
    load(tick_kernel, x, P, True, (v3, v3), 0.002, ekf_par, cmd, ctl, alloc, np.zeros(OUT_SIZE))
    load(attitude_tick_kernel, x, P, np.zeros(4), (v3, v3), 0.002, ekf_par, cmd, ctl, alloc, np.zeros(OUT_SIZE))
    if lockstep:
        _warm_lockstep(x, P, ekf_par, cmd, ctl, alloc, io)
    if batch:
        n = 2  # (any number of links: the same types)
        load(links_tick_kernel, np.zeros((n, BANK_SIZE)), np.zeros((n, 3)), np.zeros((n, 3)), 0.002, np.zeros((n, 8)),
             np.zeros((0, 4)))
    return time.perf_counter() - t0


def _warm_lockstep(x, P, ekf_par, cmd, ctl, alloc, io) -> None:
    received = np.frombuffer(bytes(HIL_SENSOR_RECORD["size"]), dtype=np.uint8)  # (read-only, as received)
    answer = np.zeros(HIL_ACTUATOR_RECORD["size"], dtype=np.uint8)
    load(hil_tick_kernel, received, answer, x, P, 0.002, ekf_par, cmd, ctl, alloc, io)
    load(sensor_record_at, received, len(received))
    buf = np.zeros(1025, dtype=np.uint8)
    bufs = (buf, buf.copy(), np.zeros(FRAME_BYTES, dtype=np.uint8), answer)
    framing = np.zeros(FRAMING_SIZE, dtype=np.int64)
    load(hil_loop_kernel, np.zeros(6, dtype=np.int32), bufs, framing, x, P, ekf_par, cmd, ctl, alloc, io)
    load(frames_to_records, buf, 1, buf, framing)
    records = np.zeros((2, HIL_SENSOR_RECORD["size"]), dtype=np.uint8)  # (the harness's writer)
    load(sensor_records, 1, np.zeros((2, HIL_SENSOR_RECORD["floats"])), 1, records)
    load(records_to_frames, records[0], 1, buf, framing)

"""A quiet tick: one whose bookkeeping outside the kernels changes nothing, so that a kernel may run a
run of them and leave the bookkeeping to the newest.

The vehicle's lockstep loop (:mod:`.lockstep`) and the batch simulator's tick of all links
(:mod:`.batch_tick`) decide it the same way, from a link's ``io`` (``IO_*`` of :mod:`.layouts`)
that the firmware fills (``LinkFirmware._quiet_io``):

- before the tick (:func:`quiet_step`): the target still fresh, no GPS timeout due; the
  correction's weight and the step since the previous tick, as the firmware computes them;
- after it (:func:`quiet_result`): the wrench finite, the allocation not saturated, no take-off to
  detect (the control estimate's height at most ``io[IO_TAKEOFF]`` above ``io[IO_ARM_HEIGHT]``,
  infinite once airborne).
"""

from __future__ import annotations

import math

from companion.kernels.jit import jit

from .layouts import (IN_WEIGHT, IO_ARM_HEIGHT, IO_CORR_HOLD, IO_CORR_STALE, IO_CORR_TIME, IO_DT_DEFAULT,
                      IO_GPS_FIX, IO_GPS_TIMEOUT, IO_T_PREV, IO_TAKEOFF, IO_TARGET_STALE, IO_TARGET_TIME, OUT_FINITE,
                      OUT_P_CTRL, OUT_SATURATED)

__all__ = ["correction_weight", "quiet_step", "quiet_result"]


@jit
def correction_weight(t_s, io):
    """``LinkFirmware.correction_weight`` at ``t_s`` from ``io``'s correction time (NaN: none), hold and staleness."""
    corr_time_s, corr_hold_s, corr_stale_s = io[IO_CORR_TIME], io[IO_CORR_HOLD], io[IO_CORR_STALE]
    if math.isnan(corr_time_s):
        return 0.0
    age = t_s - corr_time_s
    if age <= corr_hold_s:
        return 1.0
    if age >= corr_stale_s:
        return 0.0
    return (corr_stale_s - age) / (corr_stale_s - corr_hold_s)


@jit
def quiet_step(t_s, io, cmd):
    """A quiet tick at ``t_s`` about to run: its step since ``io[IO_T_PREV]`` (the nominal
    ``io[IO_DT_DEFAULT]`` when not positive, as ``LinkFirmware._tick_dt``), with the correction's
    weight written to ``cmd[IN_WEIGHT]``; -1.0 (nothing written) when the tick is not quiet: the
    target stale or a GPS timeout due (the firmware's path reports them)."""
    if not (t_s - io[IO_TARGET_TIME] <= io[IO_TARGET_STALE]) or not (t_s - io[IO_GPS_FIX] < io[IO_GPS_TIMEOUT]):
        return -1.0
    cmd[IN_WEIGHT] = correction_weight(t_s, io)
    dt = t_s - io[IO_T_PREV]
    return io[IO_DT_DEFAULT] if dt <= 0.0 else dt


@jit
def quiet_result(out, io):
    """The tick's results ``out`` (``OUT_*``) leave the bookkeeping nothing to do: a finite wrench,
    an allocation within the limit, no take-off."""
    return (out[OUT_FINITE] != 0.0 and out[OUT_SATURATED] == 0.0
            and not out[OUT_P_CTRL + 2] - io[IO_ARM_HEIGHT] > io[IO_TAKEOFF])

"""Every link's fast-loop tick in one kernel call, for a simulator that steps all links in one
process (the batch mode).

The links' firmware state is grouped into one array, ``bank`` (n, :data:`BANK_SIZE`), row ``i``
link ``i``'s (:class:`~link_firmware_sim.batch.LinkBatch` gathers it from the firmware and gives it
back), one call's arguments fewer than a kernel's dispatch costs per array. A row holds, at the
``BANK_*`` offsets: the EKF's state size ``nx``, its ``x`` (``nx``) and ``P`` ((nx - 1)^2, row by
row) and parameters (``EKF_*``), the tick's inputs (``IN_*``), eq. 1's controller (``CTL_*``), the
allocator's ``B_pinv`` (8 x 6), ``reduced_by_side`` (2 x 4 x 4 x 6) and state (``ALLOC_*``), and the
link's ``io`` (``IO_*``, the vehicle's lockstep layout: its quiet tick's inputs, :mod:`.quiet`, the
newest tick's results at ``[:OUT_SIZE]`` and report). A link's tick is :func:`.tick.tick_kernel`
with the propagation, or :func:`.tick.attitude_tick_kernel` on a tick that brings an attitude
reference, on the same numbers as the firmware's own fused tick;
``tests/unit/test_batch_tick.py`` checks it against that kernel link by link, and
``tests/integration/test_batch_tick.py`` flies the batch simulator both ways, bit for bit.
"""

from __future__ import annotations

from companion.kernels.jit import jit

from .layouts import (ALLOC_SIZE, CTL_SIZE, EKF_SIZE, IN_SIZE, IO_ACCEL, IO_AHRS_ACCEPTED, IO_AHRS_REJECTED, IO_DT,
                      IO_GYRO, IO_SIZE, IO_STATUS, IO_T_PREV, IO_TICKS, OUT_COMMAND, OUT_SIZE)
from .quiet import quiet_result, quiet_step
from .tick import attitude_tick_kernel, tick_kernel

__all__ = ["BATCH_OFF", "BATCH_QUIET", "BATCH_TICKED", "BATCH_NOT_TAKEN", "BANK_NX_MAX", "BANK_NX", "BANK_X",
           "BANK_P", "BANK_PAR", "BANK_CMD", "BANK_CTL", "BANK_BP", "BANK_RBS", "BANK_AST", "BANK_IO", "BANK_SIZE",
           "links_tick_kernel"]

#: the link is not in the batch (its firmware ticks it; the kernel leaves its row alone)
BATCH_OFF = 0
#: the link's tick ran and was quiet: its bookkeeping can wait
BATCH_QUIET = 1
#: the link's tick ran and needs the firmware's bookkeeping now (a non-finite wrench, the
#: allocation at the limit, a take-off): its commands are the bookkeeping's
BATCH_TICKED = 2
#: the link's tick was not run (its target stale, a GPS timeout due, an attitude reference that is
#: not a quaternion): the firmware ticks it
BATCH_NOT_TAKEN = 3

#: the largest EKF state a row holds (with the barometer's offset)
BANK_NX_MAX = 17
BANK_NX = 0
BANK_X = 1
BANK_P = BANK_X + BANK_NX_MAX
BANK_PAR = BANK_P + (BANK_NX_MAX - 1) ** 2
BANK_CMD = BANK_PAR + EKF_SIZE
BANK_CTL = BANK_CMD + IN_SIZE
BANK_BP = BANK_CTL + CTL_SIZE
BANK_RBS = BANK_BP + 8 * 6
BANK_AST = BANK_RBS + 2 * 4 * 4 * 6
BANK_IO = BANK_AST + ALLOC_SIZE
BANK_SIZE = BANK_IO + IO_SIZE


@jit
def links_tick_kernel(bank, gyro, accel, t_s, commands, att):
    """One tick at ``t_s`` of every link whose row's ``io[IO_STATUS]`` is :data:`BATCH_QUIET` on
    entry, from its body rate ``gyro[i]`` and specific force ``accel[i]`` (n, 3 each) and, when
    ``att`` has rows ((n, 4), else (0, 4)), the attitude reference ``att[i]`` the tick fuses first:
    the tick runs when :func:`.quiet.quiet_step` finds it quiet, with the row's ``x``, ``P``,
    controller and allocator state updated in place, the results in its ``io[:OUT_SIZE]``, the
    samples in ``io[IO_GYRO]``, ``io[IO_ACCEL]``, the time and step in ``io[IO_T_PREV]``,
    ``io[IO_DT]``, ``io[IO_TICKS]`` and the references fused in ``io[IO_AHRS_ACCEPTED]``,
    ``io[IO_AHRS_REJECTED]`` counted, and the thrust commands in ``commands[i]``; the status
    becomes :data:`BATCH_TICKED` when :func:`.quiet.quiet_result` finds work for the bookkeeping or
    the gate rejected the reference (the rejections in a row decide the next reference's path),
    :data:`BATCH_NOT_TAKEN` (nothing changed) when the tick is not quiet or the reference not a
    quaternion. Rows in any other status are left alone. Returns how many links left
    :data:`BATCH_QUIET`."""
    left = 0
    with_att = att.shape[0] > 0
    for i in range(bank.shape[0]):
        row = bank[i]
        io = row[BANK_IO:BANK_IO + IO_SIZE]
        if io[IO_STATUS] != BATCH_QUIET:
            continue
        cmd = row[BANK_CMD:BANK_CMD + IN_SIZE]
        dt = quiet_step(t_s, io, cmd)
        if dt < 0.0:
            io[IO_STATUS] = BATCH_NOT_TAKEN
            left += 1
            continue
        nx = int(row[BANK_NX])
        ne = nx - 1
        x = row[BANK_X:BANK_X + nx]
        P = row[BANK_P:BANK_P + ne * ne].reshape((ne, ne))
        alloc = (row[BANK_BP:BANK_BP + 48].reshape((8, 6)), row[BANK_RBS:BANK_RBS + 192].reshape((2, 4, 4, 6)),
                 row[BANK_AST:BANK_AST + ALLOC_SIZE])
        out = io[:OUT_SIZE]
        ctl, par = row[BANK_CTL:BANK_CTL + CTL_SIZE], row[BANK_PAR:BANK_PAR + EKF_SIZE]
        status = -1
        if with_att:
            xn, Pn, status = attitude_tick_kernel(x, P, att[i], (gyro[i], accel[i]), dt, par, cmd, ctl, alloc, out)
            if status < 0:
                io[IO_STATUS] = BATCH_NOT_TAKEN
                left += 1
                continue
            if status == 1:
                io[IO_AHRS_ACCEPTED] += 1.0
            else:
                io[IO_AHRS_REJECTED] += 1.0
        else:
            xn, Pn = tick_kernel(x, P, True, (gyro[i], accel[i]), dt, par, cmd, ctl, alloc, out)
        x[:] = xn
        P[:, :] = Pn
        for k in range(3):
            io[IO_GYRO + k] = gyro[i, k]
            io[IO_ACCEL + k] = accel[i, k]
        for k in range(8):
            commands[i, k] = out[OUT_COMMAND + k]
        io[IO_T_PREV] = t_s
        io[IO_DT] = dt
        io[IO_TICKS] += 1.0
        if status == 0 or not quiet_result(out, io):
            io[IO_STATUS] = BATCH_TICKED
            left += 1
    return left

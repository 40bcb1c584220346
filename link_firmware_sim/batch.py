"""Every link's quiet ticks in one kernel call, for a simulator that runs all links' firmware in one
process (the batch mode).

Between two of the simulator's touches of the firmware (a GPS fix, a barometer or magnetometer
sample fed, a companion output, a log row), most ticks of most links are quiet
(:mod:`.kernels.quiet`): their bookkeeping outside the kernels changes nothing but the newest values
(a tick may bring an attitude reference: the kernel fuses it as the firmware's fused tick does, and
counts it). :class:`LinkBatch` takes those links' kernel state
into stacked arrays at the first such tick (:meth:`LinkBatch.tick` gathers it), runs each tick of
all of them as one call of :func:`~.kernels.batch_tick.links_tick_kernel`, and gives the state
back, with the newest tick's bookkeeping, when the simulator is about to touch the firmware again
(:meth:`LinkBatch.sync`) or when a link's tick is not quiet. The firmware's own path ticks the
rest, so each link's numbers are those of its fused tick
(:meth:`~.fused.FusedTicks._tick_fused`), bit for bit.
"""

from __future__ import annotations

import numpy as np

from companion.kernels.jit import ENABLED

from .kernels.batch_tick import (BANK_AST, BANK_BP, BANK_CMD, BANK_CTL, BANK_IO, BANK_NX, BANK_NX_MAX, BANK_P,
                                 BANK_PAR, BANK_RBS, BANK_SIZE, BANK_X, BATCH_OFF, BATCH_QUIET, BATCH_TICKED,
                                 links_tick_kernel)
from .kernels.layouts import (ALLOC_SIZE, CTL_SIZE, EKF_SIZE, IN_SIZE, IO_AHRS_ACCEPTED, IO_AHRS_REJECTED, IO_SIZE,
                              IO_STATUS, IO_TICKS)

__all__ = ["ENABLED", "LinkBatch"]

_IO = slice(BANK_IO, BANK_IO + IO_SIZE)
_PAR, _BP, _RBS = slice(BANK_PAR, BANK_PAR + EKF_SIZE), slice(BANK_BP, BANK_BP + 48), slice(BANK_RBS, BANK_RBS + 192)
_CMD, _CTL, _AST = slice(BANK_CMD, BANK_CMD + IN_SIZE), slice(BANK_CTL, BANK_CTL + CTL_SIZE), slice(
    BANK_AST, BANK_AST + ALLOC_SIZE)


class LinkBatch:
    """The quiet ticks of the links of ``firmware`` (a list of
    :class:`~link_firmware_sim.firmware.LinkFirmware`, read at every gather: a link's restarted
    firmware is seen) in one kernel call per tick. The caller calls :meth:`sync` before anything
    else reads or changes the firmware (a measurement, a companion output, a log row, a fault),
    and after its last tick."""

    def __init__(self, firmware: list):
        if not ENABLED:
            raise RuntimeError("LinkBatch needs the compiled kernels (numba)")
        self.firmware = firmware
        n = len(firmware)
        #: the links' kernel state, row by row (``BANK_*`` of :mod:`.kernels.batch_tick`)
        self.bank = np.zeros((n, BANK_SIZE))
        self._io = [row[_IO] for row in self.bank]  # (each link's io, a view)
        self._consts: list = [None] * n  # the parameter arrays each row holds copies of
        self._held: dict = {}  # link -> its firmware, of the links in the batch while gathered
        self._own: list[int] = []  # the links the caller ticks itself until the next gather
        self._open = False  # gathered since the last sync
        self._no_att = np.zeros((0, 4))
        #: kernel calls, gathers (how often the caller's touches interrupt a run of quiet ticks), and
        #: the links' ticks here that needed their bookkeeping at once or were left to the firmware
        self.counts = {"ticks": 0, "gathers": 0, "ticked": 0, "not_taken": 0}

    def tick(self, t_s: float, gyro: np.ndarray, accel: np.ndarray, commands: np.ndarray,
             skip=frozenset(), att: np.ndarray | None = None) -> list[int]:
        """One tick at ``t_s`` of every link, from its body rate ``gyro[i]`` and specific force
        ``accel[i]`` (n, 3 each, body frame) and, when given, the attitude reference ``att[i]`` (n,
        4) fused first: the quiet ones here, their thrust commands written to ``commands[i]`` (n,
        8). Returns the links the caller ticks itself this time (its firmware's ``on_imu``, after
        its ``on_attitude`` when ``att`` is given), in order: those in ``skip`` (links the caller
        treats apart, e.g. without power), those not in the quiet case, those whose tick here was
        not quiet. A link whose tick here needed its bookkeeping has had it, events included
        (``firmware[i].events``)."""
        if not self._open:
            self._gather(skip)
        if not self._held:
            return self._own
        left = links_tick_kernel(self.bank, gyro, accel, t_s, commands, self._no_att if att is None else att)
        counts = self.counts
        counts["ticks"] += 1
        own = self._own
        if left:
            ticked, not_taken = [], []
            for i in list(self._held):
                status = self._io[i][IO_STATUS]
                if status == BATCH_QUIET:
                    continue
                command = self._release(i)
                if status == BATCH_TICKED:
                    commands[i] = command
                    ticked.append(i)
                else:  # (not taken: not run; the firmware ticks it)
                    not_taken.append(i)
            counts["ticked"] += len(ticked)
            counts["not_taken"] += len(not_taken)
            own = sorted(own + not_taken)
            self._own = sorted(own + ticked)  # (the firmware ticks them all until the next gather)
        return own

    def sync(self) -> None:
        """Every held link's state and newest tick's bookkeeping given back to its firmware; the
        next :meth:`tick` gathers afresh."""
        for i in list(self._held):
            self._release(i)
        self._open = False

    def _gather(self, skip) -> None:
        """The links in the quiet case (and not in ``skip``) taken into the bank."""
        self.counts["gathers"] += 1
        bank, consts = self.bank, self._consts
        held, own = {}, []
        for i, fw in enumerate(self.firmware):
            io = self._io[i]
            io[IO_STATUS] = BATCH_OFF
            if i in skip or not fw._quiet_case():
                own.append(i)
                continue
            ekf = fw.ekf
            x, P, par = ekf.x, ekf.P, ekf.par
            nx = x.shape[0]
            if nx > BANK_NX_MAX or P.shape != (nx - 1, nx - 1) or par.shape != (EKF_SIZE,):
                own.append(i)
                continue
            row = bank[i]
            B_pinv, reduced_by_side, state = fw.allocator.tick_state
            c = consts[i]
            if c is None or c[0] is not par or c[1] is not B_pinv or c[2] is not reduced_by_side:
                row[_PAR], row[_BP], row[_RBS] = par, B_pinv.reshape(-1), reduced_by_side.reshape(-1)
                consts[i] = (par, B_pinv, reduced_by_side)
            row[BANK_NX] = nx
            row[BANK_X:BANK_X + nx] = x
            row[BANK_P:BANK_P + (nx - 1) ** 2] = P.reshape(-1)
            row[_CTL] = fw._controller.tick_state
            row[_AST] = state
            row[_CMD] = fw._quiet_io(io)
            io[IO_TICKS] = 0.0
            io[IO_STATUS] = BATCH_QUIET
            held[i] = fw
        self._held, self._own, self._open = held, own, True

    def _release(self, i: int) -> np.ndarray | None:
        """Link ``i``'s state given back to the firmware it was taken from, with its newest tick's
        bookkeeping (none if it never ticked here); returns that tick's thrust commands."""
        fw = self._held.pop(i, None)
        if fw is None:
            return None
        io = self._io[i]
        io[IO_STATUS] = BATCH_OFF
        accepted, rejected = int(io[IO_AHRS_ACCEPTED]), int(io[IO_AHRS_REJECTED])
        if accepted or rejected:  # (a rejection ends the link's run here: it comes last)
            io[IO_AHRS_ACCEPTED] = io[IO_AHRS_REJECTED] = 0.0
            fw.ekf.count_attitude(accepted, rejected)
        if io[IO_TICKS] == 0.0:
            return None
        row = self.bank[i]
        nx = int(row[BANK_NX])
        fw._controller.tick_state[:] = row[_CTL]
        fw.allocator.tick_state[2][:] = row[_AST]
        return fw._quiet_done(io, row[BANK_X:BANK_X + nx].copy(),
                              row[BANK_P:BANK_P + (nx - 1) ** 2].reshape(nx - 1, nx - 1).copy())

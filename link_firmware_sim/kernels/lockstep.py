"""The vehicle's lockstep loop over its quiet ticks, the waits and the socket calls in it.

:func:`hil_loop_kernel` hands back to Python at the first tick whose bookkeeping changes anything;
``tests/integration/test_lockstep.py`` flies it against the record tick, bit for bit. Over PX4's TCP link the same
loop reads and writes the ticks' MAVLink 2 frames (:mod:`.mavlink_frames`: whole, unsigned frames
from the simulator, numbered without a gap, checksums checked; anything else goes to pymavlink's
parser), flown against the decoding path bit for bit, counters included.
"""

from __future__ import annotations

import numpy as np

from companion.kernels.jit import jit

from .hil_records import HIL_ACTUATOR_RECORD, record_time_us, sensor_record_at
from .layouts import (IO_AHRS_REJECTED, IO_DT, IO_DUE_US, IO_MAX_TICKS, IO_N_FDS, IO_PACKET, IO_SENT, IO_STATUS,
                      IO_T_PREV, IO_T_US, IO_TAKEN_BYTES, IO_TICKS, IO_TIMEOUT_MS, OUT_FINITE)
from .libc import MSG_NOSIGNAL, POLLIN, c_poll, c_recv, c_send
from .mavlink_frames import FRAMING, frames_to_records, record_to_frame
from .quiet import quiet_result, quiet_step
from .tick import hil_tick_kernel

__all__ = ["LOOP_IDLE", "LOOP_PACKET", "LOOP_TICKED", "hil_loop_kernel"]

#: nothing received is left over: the wait timed out or was interrupted, another descriptor (a
#: MAVLink port) is readable, the simulator's socket reported an error or hang-up, or the most ticks
LOOP_IDLE = 0
#: a packet of ``io[IO_PACKET]`` bytes is in the receive buffer, received but not taken (another
#: kind or size, baro/mag bits, a stale target, a GPS timeout due, ...): the caller decodes it
LOOP_PACKET = 1
#: the newest tick (``io[IO_TICKS]`` >= 1) needs the caller's bookkeeping (the monitors, a stream or
#: log row due, ...), its answer already sent if ``io[IO_SENT]`` counts it (else not: a non-finite
#: wrench, or a send that did not go through whole)
LOOP_TICKED = 2

_ACT_SIZE = HIL_ACTUATOR_RECORD["size"]
_F_ON, _F_SEQ_IN, _F_SENT, _F_LENGTH, _F_SEQ_READ = (FRAMING[k] for k in ("on", "seq_in", "sent", "length",
                                                                         "seq_read"))


@jit
def _left_over(io, n):
    """A packet of ``n`` bytes received and left to the caller."""
    io[IO_STATUS] = LOOP_PACKET
    io[IO_PACKET] = n


@jit
def hil_loop_kernel(fds, bufs, framing, x, P, ekf_par, cmd, ctl, alloc, io):
    """The vehicle's lockstep over its quiet ticks in one call. ``fds``: the ``poll`` pairs
    (int32 ``fd, events | revents << 16``), the simulator's socket first (non-blocking), the
    vehicle's MAVLink ports after it (``io[IO_N_FDS]`` in all); ``bufs = (buf, rec, frame,
    answer)`` (uint8): the receive buffer, the records read from frames, the answer's frame and the
    answer record; ``framing`` (:data:`.mavlink_frames.FRAMING`); ``x, P, ekf_par, cmd, ctl,
    alloc`` the firmware's state, as :func:`.tick.hil_tick_kernel` takes it; ``io`` the vehicle's
    side (``IO_*``: the loop's inputs, its report). Each turn waits for the simulator (at most
    ``io[IO_TIMEOUT_MS]``), receives one packet into ``buf`` and, when
    :func:`.tick.hil_tick_kernel` takes it, sends its answer at once.

    The simulator's link is the same-host link (``SOCK_SEQPACKET``: a packet of records), or with
    ``framing["on"]`` PX4's TCP link: what one receive brings is taken when it is exactly the
    MAVLink 2 frames of such a packet (:func:`.mavlink_frames.frames_to_records`, into ``rec``: the
    whole frames the simulator writes at once; anything else, e.g. a read that cuts a frame, is
    handed over as a packet, for pymavlink's parser), and the answer goes out as its MAVLink 2
    frame (:func:`.mavlink_frames.record_to_frame`, in ``frame``; a send that takes only part of it
    is the caller's to finish, ``framing["sent"]``); the sequence numbers both ways are kept in
    ``framing``.

    A tick is quiet (:mod:`.quiet`) when what the firmware and the vehicle do after the kernel
    changes nothing, so that leaving it out is exact: :func:`.quiet.quiet_step` before it (the target
    fresh, no GPS timeout due; the correction's weight and ``dt`` as the firmware computes them,
    ``io[IO_T_PREV]`` advanced tick by tick), :func:`.quiet.quiet_result` after it, and no stream or
    log row due (``t_us < io[IO_DUE_US]``). It returns at the first tick that is not quiet
    (:data:`LOOP_TICKED`: the caller does that tick's bookkeeping, which also stands for the quiet
    ticks' before it, as those change nothing it would not set again), after a tick whose attitude
    reference the gate rejected (:data:`LOOP_TICKED`: the rejections in a row decide whether the
    next reference resets the attitude, so the caller counts each, the last of the call), at a
    packet it does not take (:data:`LOOP_PACKET`), and when there is nothing to do
    (:data:`LOOP_IDLE`: timeout, a MAVLink port readable, the simulator's socket in error,
    ``io[IO_MAX_TICKS]`` quiet ticks). Returns
    ``(x, P)``; ``ctl``'s integrals and ``alloc``'s modulation state are updated in place, ``io``
    holds the newest tick's results and the loop's report."""
    buf, rec, frame, answer = bufs
    io[IO_STATUS] = LOOP_IDLE
    io[IO_TICKS] = 0.0
    io[IO_SENT] = 0.0
    io[IO_PACKET] = 0.0
    io[IO_TAKEN_BYTES] = 0.0
    n_fds, timeout_ms = np.int64(io[IO_N_FDS]), np.int32(io[IO_TIMEOUT_MS])
    while io[IO_TICKS] < io[IO_MAX_TICKS]:
        for k in range(n_fds):
            fds[2 * k + 1] = POLLIN
        r = c_poll(fds, n_fds, timeout_ms)
        if r <= 0:
            return x, P  # timeout, or interrupted (a signal: the caller's handler runs)
        for k in range(1, n_fds):
            if fds[2 * k + 1] >> 16 != 0:
                return x, P  # a MAVLink port has something: the caller reads it
        if (fds[1] >> 16) != POLLIN:
            return x, P  # nothing from the simulator yet, or an error / hang-up: the caller's recv sees it
        n = c_recv(fds[0], buf, buf.shape[0], 0)
        if n <= 0:
            return x, P  # EAGAIN, or the peer closed: the caller's recv sees it again
        if framing[_F_ON] != 0:
            m = frames_to_records(buf, n, rec, framing)
            if m < 0:
                _left_over(io, n)
                return x, P
            pkt = rec[:m]
        else:
            m = n
            pkt = buf[:n]
        s0 = sensor_record_at(pkt, m)
        if s0 < 0:
            _left_over(io, n)
            return x, P
        t_us = record_time_us(pkt, s0)
        t_s = t_us * 1e-6  # (hil.seconds)
        dt = quiet_step(t_s, io, cmd)
        if dt < 0.0:
            _left_over(io, n)
            return x, P
        rejected = io[IO_AHRS_REJECTED]
        xn, Pn, taken = hil_tick_kernel(pkt, answer, x, P, dt, ekf_par, cmd, ctl, alloc, io)
        if not taken:
            _left_over(io, n)
            return x, P
        x, P = xn, Pn
        if framing[_F_ON] != 0:
            framing[_F_SEQ_IN] = framing[_F_SEQ_READ]  # the frames taken: their sender's numbers seen
        io[IO_TICKS] += 1.0
        io[IO_TAKEN_BYTES] += n
        io[IO_T_US] = t_us
        io[IO_DT] = dt
        io[IO_T_PREV] = t_s
        sent = False
        if io[OUT_FINITE] != 0.0:  # a finite wrench: the answer goes out
            if framing[_F_ON] != 0:
                length = record_to_frame(answer, frame, framing)
                framing[_F_LENGTH] = length
                framing[_F_SENT] = c_send(fds[0], frame, length, MSG_NOSIGNAL)
                sent = framing[_F_SENT] == length
            else:
                sent = c_send(fds[0], answer, _ACT_SIZE, MSG_NOSIGNAL) == _ACT_SIZE
        if sent:
            io[IO_SENT] += 1.0
        else:
            io[IO_STATUS] = LOOP_TICKED  # not sent (whole): the caller's send (or its error) takes over
            return x, P
        if not quiet_result(io, io) or t_us >= io[IO_DUE_US] or io[IO_AHRS_REJECTED] != rejected:
            io[IO_STATUS] = LOOP_TICKED
            return x, P
    return x, P

"""MAVLink 2 frames of the simulator link's common tick (PX4's TCP link) to and from its records.

The same messages as the same-host link's records (:mod:`.hil_records`) in MAVLink 2 frames: the
ids, CRC extras and payload sizes (:mod:`link_firmware_sim.vehicle.simlink` checks them against the dialect
when it is imported), MAVLink's checksum, and the conversions the lockstep loop and the simulator's
reader use (:func:`frames_to_records`, :func:`record_to_frame`), with their framing state
(:data:`FRAMING`).
"""

from __future__ import annotations

import numpy as np

from companion.kernels.jit import jit

from .hil_records import HIL_ACTUATOR_RECORD, HIL_AHRS_RECORD, HIL_SENSOR_RECORD

__all__ = ["MAV2_STX", "MAV2_HEADER", "MAV_HIL_SENSOR", "MAV_HIL_AHRS", "MAV_HIL_ACTUATOR", "FRAME_BYTES", "FRAMING",
           "FRAMING_SIZE", "FRAMES_TO_VEHICLE", "FRAMES_TO_SIMULATOR", "crc_mcrf4xx", "frames_to_records",
           "record_to_frame", "records_to_frames"]

_SENSOR_KIND = HIL_SENSOR_RECORD["kind"]
_AHRS_KIND = HIL_AHRS_RECORD["kind"]
_ACT_KIND = HIL_ACTUATOR_RECORD["kind"]

#: PX4's TCP simulator link carries the same messages in MAVLink 2 frames: the start byte, the
#: header's length (start byte to message id) and the checksum's (CRC-16/MCRF4XX over the frame
#: after the start byte, then the message's CRC extra)
MAV2_STX = 0xFD
MAV2_HEADER = 10
#: the messages of the common tick over TCP as :func:`.lockstep.hil_loop_kernel` reads (HIL_SENSOR,
#: SKELETON_AHRS_REFERENCE) and writes (HIL_ACTUATOR_CONTROLS) them: message id, CRC extra and the
#: payload's size (its record's less the kind byte). Literals for the same reason as the records'
#: offsets; :mod:`link_firmware_sim.vehicle.simlink` checks them against the dialect when it is imported.
MAV_HIL_SENSOR = {"msgid": 107, "crc_extra": 108, "size": 65}
MAV_HIL_AHRS = {"msgid": 57002, "crc_extra": 112, "size": 24}
MAV_HIL_ACTUATOR = {"msgid": 93, "crc_extra": 47, "size": 81}
_MS_ID, _MS_EXTRA, _MS_SIZE = MAV_HIL_SENSOR.values()
_MA_ID, _MA_EXTRA, _MA_SIZE = MAV_HIL_AHRS.values()
_MO_ID, _MO_EXTRA, _MO_SIZE = MAV_HIL_ACTUATOR.values()
#: the longest answer's frame (an unsigned MAVLink 2 HIL_ACTUATOR_CONTROLS, no trailing zero)
FRAME_BYTES = MAV2_HEADER + _MO_SIZE + 2
#: ``framing`` of :func:`.lockstep.hil_loop_kernel` and :func:`frames_to_records` (int64): ``on`` 0 for the
#: same-host link's records, else MAVLink 2 frames on a TCP stream, read by the vehicle
#: (:data:`FRAMES_TO_VEHICLE`: HIL_SENSOR, SKELETON_AHRS_REFERENCE) or by the simulator
#: (:data:`FRAMES_TO_SIMULATOR`: HIL_ACTUATOR_CONTROLS); the peer's system and component (the one
#: sender whose frames are taken) and its last sequence number, kept up to date; this end's
#: system, component and next sequence number, kept up to date; the bytes of the newest answer's
#: frame that its send took (-1: none) and the frame's length (the rest is the caller's to send);
#: the sequence number of the newest frame read (for the caller to keep once it takes them)
FRAMING = {"on": 0, "src_sys": 1, "src_comp": 2, "seq_in": 3, "sys": 4, "comp": 5, "seq_out": 6, "sent": 7,
           "length": 8, "seq_read": 9}
FRAMING_SIZE = 10
_F_ON, _F_SRC_SYS, _F_SRC_COMP, _F_SEQ_IN, _F_SYS, _F_COMP, _F_SEQ_OUT, _F_SENT, _F_LENGTH, _F_SEQ_READ = FRAMING.values()
FRAMES_TO_VEHICLE = 1
FRAMES_TO_SIMULATOR = 2


@jit
def _crc_step(crc, byte):
    """MAVLink's checksum (CRC-16/MCRF4XX) ``crc`` continued by one byte."""
    tmp = (byte ^ (crc & 0xFF)) & 0xFF
    tmp = (tmp ^ (tmp << 4)) & 0xFF
    return ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF


@jit
def crc_mcrf4xx(data, start, end, crc):
    """MAVLink's checksum (CRC-16/MCRF4XX, pymavlink's ``x25crc``) of ``data[start:end]`` (uint8)
    continued from ``crc`` (0xFFFF to start one)."""
    for i in range(start, end):
        crc = _crc_step(crc, np.int64(data[i]))
    return crc


@jit
def frames_to_records(buf, n, rec, framing):
    """The same-host link's packet (into ``rec``; its length returned) that the first ``n`` bytes
    of ``buf`` carry as MAVLink 2 frames, or -1 unless those bytes are exactly a run of whole,
    unsigned frames (no incompatibility or compatibility flag), each of the kinds of ``framing``'s
    side (:data:`FRAMES_TO_VEHICLE`: HIL_SENSOR or SKELETON_AHRS_REFERENCE;
    :data:`FRAMES_TO_SIMULATOR`: HIL_ACTUATOR_CONTROLS) with a payload of 1 to its size bytes
    (MAVLink 2 cuts a payload's trailing zeros: they are put back), a good checksum, from
    ``framing``'s sender and numbered on from its last sequence number without a gap. Anything
    else (another message, a frame cut at either end, a duplicate or a lost frame, another sender,
    a bad checksum) is left to pymavlink's parser, which counts what it must. The newest frame's sequence number goes to
    ``framing["seq_read"]``, for the caller to keep once it takes the packet."""
    i = 0
    m = 0
    seq = framing[_F_SEQ_IN]
    while i < n:
        if n - i < MAV2_HEADER + 2 or buf[i] != MAV2_STX or buf[i + 2] != 0 or buf[i + 3] != 0:
            return -1
        length = np.int64(buf[i + 1])
        end = i + MAV2_HEADER + length
        if end + 2 > n or length == 0:
            return -1
        if (np.int64(buf[i + 4]) != (seq + 1) & 0xFF or buf[i + 5] != framing[_F_SRC_SYS]
                or buf[i + 6] != framing[_F_SRC_COMP]):
            return -1
        msgid = np.int64(buf[i + 7]) | (np.int64(buf[i + 8]) << 8) | (np.int64(buf[i + 9]) << 16)
        if framing[_F_ON] == FRAMES_TO_SIMULATOR:
            if msgid != _MO_ID:
                return -1
            kind, size, extra = _ACT_KIND, _MO_SIZE, _MO_EXTRA
        elif msgid == _MS_ID:
            kind, size, extra = _SENSOR_KIND, _MS_SIZE, _MS_EXTRA
        elif msgid == _MA_ID:
            kind, size, extra = _AHRS_KIND, _MA_SIZE, _MA_EXTRA
        else:
            return -1
        if length > size or m + 1 + size > rec.shape[0]:
            return -1
        crc = _crc_step(crc_mcrf4xx(buf, i + 1, end, 0xFFFF), extra)
        if np.int64(buf[end]) != (crc & 0xFF) or np.int64(buf[end + 1]) != crc >> 8:
            return -1
        rec[m] = kind
        rec[m + 1:m + 1 + length] = buf[i + MAV2_HEADER:end]
        rec[m + 1 + length:m + 1 + size] = 0
        m += 1 + size
        seq = np.int64(buf[i + 4])
        i = end + 2
    framing[_F_SEQ_READ] = seq
    return m


@jit
def _put_frame(rec, r0, msgid, extra, size, frame, f0, framing):
    """The record at ``rec[r0]`` (its kind byte, then a payload of ``size`` bytes) as the MAVLink 2
    frame of message ``msgid`` (CRC extra ``extra``) that pymavlink packs (unsigned, from
    ``framing``'s system and component, with its next sequence number, which moves on; the
    payload's trailing zeros cut, one byte kept), written at ``frame[f0]``; returns its length."""
    plen = size
    while plen > 1 and rec[r0 + plen] == 0:  # (the payload's byte j is the record's j + 1)
        plen -= 1
    frame[f0] = MAV2_STX
    frame[f0 + 1] = plen
    frame[f0 + 2] = 0
    frame[f0 + 3] = 0
    frame[f0 + 4] = framing[_F_SEQ_OUT] & 0xFF
    frame[f0 + 5] = framing[_F_SYS]
    frame[f0 + 6] = framing[_F_COMP]
    frame[f0 + 7] = msgid & 0xFF
    frame[f0 + 8] = (msgid >> 8) & 0xFF
    frame[f0 + 9] = msgid >> 16
    frame[f0 + MAV2_HEADER:f0 + MAV2_HEADER + plen] = rec[r0 + 1:r0 + 1 + plen]
    end = f0 + MAV2_HEADER + plen
    crc = _crc_step(crc_mcrf4xx(frame, f0 + 1, end, 0xFFFF), extra)
    frame[end] = crc & 0xFF
    frame[end + 1] = crc >> 8
    framing[_F_SEQ_OUT] = (framing[_F_SEQ_OUT] + 1) & 0xFF
    return end + 2 - f0


@jit
def record_to_frame(answer, frame, framing):
    """The HIL_ACTUATOR_CONTROLS record ``answer`` as the MAVLink 2 frame pymavlink packs (unsigned,
    from ``framing``'s system and component, with its next sequence number, which moves on; the
    payload's trailing zeros cut, one byte kept) into ``frame``; returns the frame's length."""
    return _put_frame(answer, 0, _MO_ID, _MO_EXTRA, _MO_SIZE, frame, 0, framing)


@jit
def _kind_frame(kind):
    """The message id, CRC extra and payload size of a record kind's frame; (-1, 0, 0) for a kind
    without one here."""
    if kind == _SENSOR_KIND:
        return _MS_ID, _MS_EXTRA, _MS_SIZE
    if kind == _AHRS_KIND:
        return _MA_ID, _MA_EXTRA, _MA_SIZE
    if kind == _ACT_KIND:
        return _MO_ID, _MO_EXTRA, _MO_SIZE
    return -1, 0, 0


@jit
def records_to_frames(rec, m, frames, framing):
    """The same-host link's packet of ``m`` bytes in ``rec`` (HIL_SENSOR, SKELETON_AHRS_REFERENCE
    and HIL_ACTUATOR_CONTROLS records) as the MAVLink 2 frames pymavlink packs, one per record in
    order, numbered on from ``framing``'s next sequence number (:func:`record_to_frame`'s frames),
    into ``frames``; returns their length, or -1 (nothing written, no number used) for a packet
    that is not whole records of those kinds or whose frames do not fit."""
    i = 0
    f = 0
    while i < m:
        msgid, _, size = _kind_frame(rec[i])
        if msgid < 0 or i + 1 + size > m:
            return -1
        f += MAV2_HEADER + size + 2
        i += 1 + size
    if f > frames.shape[0]:
        return -1
    i = 0
    f = 0
    while i < m:
        msgid, extra, size = _kind_frame(rec[i])
        f += _put_frame(rec, i, msgid, extra, size, frames, f, framing)
        i += 1 + size
    return f

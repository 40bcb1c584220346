"""MAVLink FTP (mavlink.io "File Transfer Protocol") without a file system: session resets are
acknowledged, everything else is answered at once with a NAK (opening a file: FileNotFound, so a
ground station that tries ``@PARAM/param.pck`` first falls back to PARAM_REQUEST_LIST without
waiting)."""

from __future__ import annotations

import struct

from companion.mavlink.codec import MessageError
from companion.mavlink.dialect import load_dialect

from .links import Endpoint

__all__ = ["on_ftp"]

D = load_dialect()
# opcodes and errors this vehicle answers
_FTP_TERMINATE, _FTP_RESET, _FTP_ACK, _FTP_NAK = 1, 2, 128, 129
_FTP_ERR_UNKNOWN_COMMAND, _FTP_ERR_FILE_NOT_FOUND = 9, 10
_FTP_OPEN_FILE_RO, _FTP_LIST_DIRECTORY = 4, 3
_PAYLOAD_BYTES = 251


def on_ftp(v, ep: Endpoint, msg) -> None:
    """FILE_TRANSFER_PROTOCOL ``msg`` to vehicle ``v`` from link ``ep``; :class:`MessageError` for a
    payload shorter than its header."""
    if msg.target_system not in (0, v.system_id):
        return
    payload = bytes(msg.payload)
    if len(payload) < 12:
        raise MessageError("FILE_TRANSFER_PROTOCOL payload shorter than its header")
    seq, session, opcode = struct.unpack_from("<HBB", payload)
    if opcode in (_FTP_ACK, _FTP_NAK):
        return
    if opcode in (_FTP_TERMINATE, _FTP_RESET):
        reply, data = _FTP_ACK, b""
    elif opcode in (_FTP_OPEN_FILE_RO, _FTP_LIST_DIRECTORY):
        reply, data = _FTP_NAK, bytes([_FTP_ERR_FILE_NOT_FOUND])
    else:
        reply, data = _FTP_NAK, bytes([_FTP_ERR_UNKNOWN_COMMAND])
    header = struct.pack("<HBBBBBBI", (seq + 1) & 0xFFFF, session, reply, len(data), opcode, 0, 0, 0)
    body = (header + data).ljust(_PAYLOAD_BYTES, b"\0")
    ep.port.send(D.MAVLink_file_transfer_protocol_message(0, msg.get_srcSystem(), msg.get_srcComponent(),
                                                          list(body)))

"""SETUP_SIGNING: a new MAVLink 2 signing key for every link of the vehicle, accepted only on a
trusted link (``[signing] trusted``; PX4: USB only). An all-zero key with timestamp 0 turns
signing off (MAVLink semantics). The key is written to the configured key file (hex), so it
survives a restart."""

from __future__ import annotations

import logging

from companion.mavlink.codec import MessageError
from companion.mavlink.dialect import load_dialect
from companion.mavlink.signing import KEY_LEN, write_key_file

from .links import Endpoint, statustext

__all__ = ["on_setup_signing"]

log = logging.getLogger(__name__)
D = load_dialect()
#: the largest signing timestamp (48 bits on the wire; a larger one could not be sent)
TIMESTAMP_MAX = 2**48 - 1


def on_setup_signing(v, ep: Endpoint, msg) -> None:
    """SETUP_SIGNING ``msg`` to vehicle ``v`` from link ``ep``: refused (counted in
    ``errors["setup_signing_refused"]``, answered with a STATUSTEXT) on an untrusted link;
    :class:`MessageError` for a key of the wrong length or a timestamp beyond 48 bits (nothing
    changed)."""
    if msg.target_system not in (0, v.system_id):
        return
    if not ep.trusted:
        v.errors["setup_signing_refused"] += 1
        log.warning("link %d: SETUP_SIGNING on the untrusted %s link refused", v.system_id, ep.name)
        statustext(ep, D.MAV_SEVERITY_WARNING, "Signing setup refused: untrusted link")
        return
    key = bytes(msg.secret_key)
    if len(key) != KEY_LEN:
        raise MessageError(f"SETUP_SIGNING key of {len(key)} bytes")
    if msg.initial_timestamp > TIMESTAMP_MAX:
        raise MessageError(f"SETUP_SIGNING initial_timestamp {msg.initial_timestamp} does not fit the 48-bit timestamp")
    disable = not any(key) and msg.initial_timestamp == 0
    for other in v.endpoints:
        mode = "off" if disable else (v.signing.link_mode(other.name) if v.signing.active else "required")
        other.port.set_signing(mode, None if disable else key)
        if not disable:
            other.port.mav.signing.timestamp = max(other.port.mav.signing.timestamp, int(msg.initial_timestamp))
    if v.key_path is not None and not disable:
        write_key_file(v.key_path, key.hex(), overwrite=True)
    log.warning("link %d: signing %s over the %s link", v.system_id, "disabled" if disable else "key replaced",
                ep.name)
    v.status_all(D.MAV_SEVERITY_NOTICE, "Signing disabled" if disable else "Signing key updated")

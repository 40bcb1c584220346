"""MAVLink 2 message signing: keys, key files, the per-link policy and signature checks (pure).

The MAVLink 2 signing protocol (mavlink.io, "Message Signing"; what PX4 and ArduPilot implement):
a signed frame carries 13 more bytes, ``link_id`` (1), ``timestamp`` (6, little-endian, units
of 10 us since 2015-01-01 00:00 UTC) and ``signature`` (6): the first 48 bits of
``SHA-256(secret_key + header + payload + CRC + link_id + timestamp)``. A receiver accepts a
signed frame when the signature matches its 32-byte key and the timestamp is newer than the
last one of the same stream ``(link_id, system id, component id)`` (replay protection); a
stream it has not seen must not be more than one minute behind its own timestamp.

Outgoing frames are signed by pymavlink (``MAVLink.signing``); incoming frames are checked here,
not by pymavlink's parser: pymavlink records a stream's timestamp before it compares the
signature, so one forged frame with a large timestamp would lock a legitimate sender out
(the C library and PX4 check the signature first, as :meth:`SignatureChecker.check` does).

Per link, a :data:`SigningMode`:

* ``off``: nothing signed, signatures not checked (a signed frame is read like an unsigned one);
* ``permissive``: outgoing frames signed; a signed incoming frame must verify (a bad signature
  or a replay is rejected), an unsigned one is accepted and counted (for migrating a fleet);
* ``required``: outgoing frames signed; unsigned frames are rejected, except the messages PX4
  accepts unsigned from a radio (:data:`UNSIGNED_ALLOWED`: RADIO_STATUS) and, on a link the
  configuration trusts, SETUP_SIGNING (PX4 accepts a key only over USB).

Key files hold one line: a passphrase (the key is its SHA-256, as MAVProxy's ``signing``
module and QGroundControl derive theirs, so ``signing key PASSPHRASE`` typed at MAVProxy's prompt
signs with the same key) or 64 hexadecimal digits (the raw key, e.g. one received by SETUP_SIGNING). A
key file readable by group or others is refused, as ssh refuses such private keys.
"""

from __future__ import annotations

import hashlib
import secrets
import time
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Literal

from ..keyfiles import read_private_text, write_private_text

__all__ = [
    "SigningMode",
    "SigningConfig",
    "Verdict",
    "SignatureChecker",
    "UNSIGNED_ALLOWED",
    "KEY_LEN",
    "SIGNATURE_BLOCK_LEN",
    "signing_timestamp",
    "key_from_text",
    "load_key",
    "key_passphrase",
    "new_key_file",
    "write_key_file",
    "frame_is_signed",
]

SigningMode = Literal["off", "permissive", "required"]
KEY_LEN = 32
SIGNATURE_BLOCK_LEN = 13
_MAGIC_V2 = 0xFD
_IFLAG_SIGNED = 0x01
_EPOCH_2015_S = 1420070400
_NEW_STREAM_WINDOW = 60 * 100_000  # one minute in signing units (10 us)
#: Messages accepted unsigned even when signing is required (PX4's list: a radio's own status).
UNSIGNED_ALLOWED = frozenset({"RADIO_STATUS"})


def signing_timestamp(unix_s: float | None = None) -> int:
    """The signing clock: 10 us units since 2015-01-01 00:00 UTC."""
    now = time.time() if unix_s is None else unix_s
    return max(int((now - _EPOCH_2015_S) * 100_000), 0)


@dataclass(frozen=True)
class SigningConfig:
    """The ``[signing]`` section (every config that speaks MAVLink: companion, vehicle, scenario).

    ``mode``: the default for every MAVLink link (``off``, ``permissive``, ``required``);
    ``onboard`` / ``gcs``: per-link overrides (the companion <-> vehicle links; the vehicle's
    ground-station link), empty for ``mode``. ``key_file``: the key (see the module docstring),
    relative to the config file's folder; never a key inline. A SITL launch makes a throwaway
    key in its run folder when none is given. ``trusted``: links over which SETUP_SIGNING may
    replace the key (``onboard``, ``gcs``; none by default: PX4 accepts it on USB only).
    """

    mode: SigningMode = "off"
    onboard: Literal["", "off", "permissive", "required"] = ""
    gcs: Literal["", "off", "permissive", "required"] = ""
    key_file: str = ""
    trusted: tuple[Literal["onboard", "gcs"], ...] = ()

    def __post_init__(self) -> None:
        if len(set(self.trusted)) != len(self.trusted):
            raise ValueError(f"trusted lists a link twice: {list(self.trusted)}")

    def link_mode(self, link: Literal["onboard", "gcs"]) -> SigningMode:
        """The mode of the ``onboard`` or ``gcs`` link."""
        return getattr(self, link) or self.mode

    @property
    def active(self) -> bool:
        """Whether any link signs (a key is then needed)."""
        return any(self.link_mode(k) != "off" for k in ("onboard", "gcs"))

    def key(self) -> bytes | None:
        """The key from ``key_file`` when a link signs, else ``None``; ``ValueError`` with the reason."""
        if not self.active:
            return None
        if not self.key_file:
            raise ValueError("signing.key_file is needed when a link signs (create one: python -m companion keys new FILE)")
        try:
            return load_key(self.key_file)
        except ValueError as exc:
            raise ValueError(f"signing.key_file: {exc} (create one: python -m companion keys new "
                             f"{self.key_file}; every computer of the fleet and every Pixhawk share it)") from None


class Verdict(Enum):
    """What :meth:`SignatureChecker.check` made of a frame."""

    SIGNED = "signed"  # signature and timestamp good
    UNSIGNED = "unsigned"  # accepted unsigned (permissive, or an allowed message)
    NOT_CHECKED = "not_checked"  # signing off on this link
    REJECTED_UNSIGNED = "rejected_unsigned"
    REJECTED_SIGNATURE = "rejected_signature"  # wrong key or altered frame
    REJECTED_REPLAY = "rejected_replay"  # timestamp not newer than the stream's last, or too old

    @property
    def accepted(self) -> bool:
        return self in (Verdict.SIGNED, Verdict.UNSIGNED, Verdict.NOT_CHECKED)


class SignatureChecker:
    """Signature and replay checks of one link's incoming frames (no I/O; the time is passed in).

    Args:
        mode: the link's :data:`SigningMode`.
        key: the 32-byte secret key (``None`` only with ``mode = "off"``).
        unsigned_allowed: message names accepted unsigned under ``required``.
        max_streams: most streams remembered (only frames with a valid signature add one).
    """

    def __init__(self, mode: SigningMode, key: bytes | None, unsigned_allowed=UNSIGNED_ALLOWED,
                 max_streams: int = 1024):
        if mode not in ("off", "permissive", "required"):
            raise ValueError(f"signing mode must be off, permissive or required, got {mode!r}")
        if mode != "off" and (key is None or len(key) != KEY_LEN):
            raise ValueError(f"signing mode {mode!r} needs a {KEY_LEN}-byte key")
        self.mode = mode
        self.key = key
        self.unsigned_allowed = frozenset(unsigned_allowed)
        self.max_streams = max_streams
        #: (link_id, system id, component id) -> last accepted timestamp
        self.streams: dict[tuple[int, int, int], int] = {}
        #: the newest timestamp seen in a good frame (new streams may be at most a minute older)
        self.timestamp = 0

    def set_key(self, mode: SigningMode, key: bytes | None) -> None:
        """A new key or mode (SETUP_SIGNING): the replay state starts again."""
        self.__init__(mode, key, self.unsigned_allowed, self.max_streams)

    def check(self, frame: bytes, msg_name: str, now_timestamp: int) -> Verdict:
        """The verdict on one complete frame (``frame`` as received; ``msg_name`` its type)."""
        if self.mode == "off":
            return Verdict.NOT_CHECKED
        if not frame_is_signed(frame):
            if self.mode == "permissive" or msg_name in self.unsigned_allowed:
                return Verdict.UNSIGNED
            return Verdict.REJECTED_UNSIGNED
        block = frame[-SIGNATURE_BLOCK_LEN:]
        digest = hashlib.sha256(self.key + frame[:-6]).digest()[:6]
        if not secrets.compare_digest(digest, bytes(block[7:13])):
            return Verdict.REJECTED_SIGNATURE
        link_id = block[0]
        stamp = int.from_bytes(block[1:7], "little")
        stream = (link_id, frame[5], frame[6])
        last = self.streams.get(stream)
        reference = max(self.timestamp, now_timestamp)
        if last is not None:
            if stamp <= last:
                return Verdict.REJECTED_REPLAY
        elif stamp + _NEW_STREAM_WINDOW < reference:
            return Verdict.REJECTED_REPLAY
        if last is None and len(self.streams) >= self.max_streams:
            self.streams.pop(next(iter(self.streams)))
        self.streams[stream] = stamp
        self.timestamp = max(self.timestamp, stamp)
        return Verdict.SIGNED


def key_from_text(text: str) -> bytes:
    """The 32-byte key of a key file's text: 64 hex digits as they are, else SHA-256 of the passphrase."""
    line = text.strip()
    if not line or "\n" in line:
        raise ValueError("a key file holds one non-empty line (a passphrase or 64 hex digits)")
    if len(line) == 2 * KEY_LEN and all(c in "0123456789abcdefABCDEF" for c in line):
        return bytes.fromhex(line)
    if not line.isascii() or any(c.isspace() for c in line):
        raise ValueError("a passphrase must be ASCII without spaces (MAVProxy and QGroundControl take one word)")
    if len(line) < 16:
        raise ValueError(f"a passphrase needs at least 16 characters, got {len(line)}")
    return hashlib.sha256(line.encode("ascii")).digest()


def load_key(path: str | Path) -> bytes:
    """The key in the key file ``path``; ``ValueError`` naming the file and the reason."""
    text = read_private_text(path, "signing key")
    try:
        return key_from_text(text)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def key_passphrase(path: str | Path) -> str | None:
    """The passphrase in the key file ``path`` (what a ground station's ``signing key`` takes), or
    ``None`` when the file holds a raw key; ``ValueError`` naming the file and the reason."""
    text = read_private_text(path, "signing key").strip()
    try:
        key_from_text(text)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    return None if len(text) == 2 * KEY_LEN and all(c in "0123456789abcdefABCDEF" for c in text) else text


def write_key_file(path: str | Path, text: str, overwrite: bool = False) -> Path:
    """Write ``text`` (a passphrase or hex key) to ``path`` with mode 600, atomically."""
    key_from_text(text)
    try:
        return write_private_text(path, text, overwrite)
    except ValueError as exc:
        raise ValueError(str(exc).replace("a secret", "a key")) from None


def new_key_file(path: str | Path, overwrite: bool = False) -> str:
    """A new random passphrase (256 bits, URL-safe base64) in ``path``; returns it."""
    passphrase = secrets.token_urlsafe(KEY_LEN)
    write_key_file(path, passphrase, overwrite)
    return passphrase


def frame_is_signed(frame: bytes) -> bool:
    """Whether a MAVLink frame carries a signature block."""
    return len(frame) > SIGNATURE_BLOCK_LEN and frame[0] == _MAGIC_V2 and bool(frame[2] & _IFLAG_SIGNED)


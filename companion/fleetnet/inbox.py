"""The vision consumer's messages, taken off Zenoh by a companion.

Two kinds arrive (:data:`KINDS`), each on keys of its own:

* ``"neighbour"``: a chain camera's view of its neighbour's marker
  (:class:`~companion.messages.NeighbourPose`) on ``<prefix>/link/<i>/neighbour``, ``i`` the
  1-based link that carries the camera;
* ``"load"``: a carrying vehicle's camera measurement of the slung load
  (:class:`~companion.load.model.LoadObservation`) on ``<prefix>/vehicle/<i>/load``.

A :class:`MessageInbox` subscribes to one kind on a session it is given: a distributed
companion's fleet session, or a centralised companion's session on group 1's endpoint
(:func:`open_vision_session`, ``[zenoh] vision_session``: presenting group 1's credentials, so
only a session the fleet admits can deliver one). The Zenoh callback only queues a payload
(:class:`~.payload_queue.PayloadQueue`); :meth:`MessageInbox.drain` decodes them in the daemon's
thread. A payload that does not decode, a message of another kind, or one published on another
link's or vehicle's key, is counted by reason and dropped.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from companion.load.model import LoadObservation
from companion.messages import MessageError, NeighbourPose

from . import codec
from .config import ZenohConfig
from .keys import load_key, load_pattern, neighbour_key, neighbour_pattern
from .payload_queue import PayloadQueue

__all__ = ["InboxKind", "KINDS", "MessageInbox", "open_vision_session"]

log = logging.getLogger(__name__)

#: Payloads queued between two drains at most (a flood beyond it is counted and dropped).
MAX_QUEUED = 256


@dataclass(frozen=True)
class InboxKind:
    """A kind of message an inbox takes: its type, the pattern it subscribes to, and the one key a
    message of it belongs on (``key(prefix, msg)``)."""

    name: str
    type: type
    pattern: Callable[[str], str]
    key: Callable[[str, object], str]


KINDS = {k.name: k for k in (
    InboxKind("neighbour pose", NeighbourPose, neighbour_pattern, lambda prefix, m: neighbour_key(prefix, m.observer)),
    InboxKind("load observation", LoadObservation, load_pattern, lambda prefix, m: load_key(prefix, m.vehicle)),
)}


def open_vision_session(cfg: ZenohConfig, file: str = "<config>"):
    """A centralised companion's session for the vision consumer's messages: group 1 of one group
    (listening on its endpoint, with its credentials)."""
    from .bus import open_group_session

    session = open_group_session(cfg, 0, 1, file)
    log.info("vision consumer's messages: listening on %s", cfg.group_endpoint(0))
    return session


class MessageInbox:
    """Messages of ``kind`` (a name of :data:`KINDS`) from ``session`` under ``prefix`` (module
    docstring); the session stays the caller's."""

    def __init__(self, session, prefix: str, kind: str):
        self.prefix = prefix
        self.kind = KINDS[kind]
        self._payloads = PayloadQueue(MAX_QUEUED)
        self.counts = {"received": 0, "delivered": 0, "rejected": 0}
        self.reasons: dict[str, int] = {}
        self._sub = session.declare_subscriber(self.kind.pattern(prefix), self._payloads.on_sample)

    def _reject(self, reason: str, key: str) -> None:
        self.counts["rejected"] += 1
        kind = reason.split(":", 1)[0][:60]
        n = self.reasons[kind] = self.reasons.get(kind, 0) + 1
        if n <= 5 or n % 100 == 0:
            log.warning("%s on %s dropped (#%d): %s", self.kind.name, key, n, reason)

    def drain(self) -> list:
        """The messages that arrived since the last drain, checked (the others counted)."""
        out = []
        for payload, key in self._payloads.take():
            self.counts["received"] += 1
            try:
                msg = codec.decode(payload)
            except MessageError as exc:
                self._reject(str(exc), key)
                continue
            if not isinstance(msg, self.kind.type) or key != self.kind.key(self.prefix, msg):
                self._reject(f"{type(msg).__name__} does not belong on this key", key)
                continue
            self.counts["delivered"] += 1
            out.append(msg)
        return out

    def summary(self) -> dict:
        """Counts: received, delivered, rejected (with ``reasons``), overflow (queue full)."""
        return {**self.counts, "overflow": self._payloads.overflow, "reasons": dict(self.reasons)}

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:  # noqa: BLE001 - the session may be closed already
            pass

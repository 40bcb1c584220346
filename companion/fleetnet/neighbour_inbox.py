"""The vision consumer's neighbour poses, taken off Zenoh by a companion.

A chain camera's view of its neighbour's marker (:class:`~companion.messages.NeighbourPose`)
arrives on ``<prefix>/link/<i>/neighbour``, ``i`` the 1-based link that carries the camera.
:class:`NeighbourInbox` subscribes on a session it is given (a distributed companion's fleet
session) or opens itself (:meth:`NeighbourInbox.open`: a centralised companion with ``[zenoh]
neighbour_poses``, listening on group 1's endpoint and presenting group 1's credentials, so only
a session the fleet admits can deliver one). The Zenoh callback only queues a payload
(:class:`~.payload_queue.PayloadQueue`); :meth:`NeighbourInbox.drain` decodes them in the
daemon's thread. A payload that does not
decode, or a pose published on another link's key, is counted by reason and dropped.
"""

from __future__ import annotations

import logging

from companion.messages import MessageError, NeighbourPose

from . import codec
from .config import ZenohConfig
from .keys import neighbour_key, neighbour_pattern
from .payload_queue import PayloadQueue

__all__ = ["NeighbourInbox"]

log = logging.getLogger(__name__)

#: Payloads queued between two drains at most (a flood beyond it is counted and dropped).
MAX_QUEUED = 256


class NeighbourInbox:
    """Neighbour poses from ``session`` under ``prefix`` (module docstring); ``own_session``:
    close the session with the inbox."""

    def __init__(self, session, prefix: str, own_session: bool = False):
        self.prefix = prefix
        self.session = session
        self._own = own_session
        self._payloads = PayloadQueue(MAX_QUEUED)
        self.counts = {"received": 0, "delivered": 0, "rejected": 0}
        self.reasons: dict[str, int] = {}
        self._sub = session.declare_subscriber(neighbour_pattern(prefix), self._payloads.on_sample)

    @classmethod
    def open(cls, cfg: ZenohConfig, prefix: str, file: str = "<config>") -> NeighbourInbox:
        """A centralised companion's inbox on a session of its own (group 1 of one group)."""
        from .bus import open_group_session

        session = open_group_session(cfg, 0, 1, file)
        try:
            inbox = cls(session, prefix, own_session=True)
        except BaseException:
            session.close()
            raise
        log.info("neighbour poses: listening on %s for %s", cfg.group_endpoint(0), neighbour_pattern(prefix))
        return inbox

    def _reject(self, reason: str, key: str) -> None:
        self.counts["rejected"] += 1
        kind = reason.split(":", 1)[0][:60]
        n = self.reasons[kind] = self.reasons.get(kind, 0) + 1
        if n <= 5 or n % 100 == 0:
            log.warning("neighbour pose on %s dropped (#%d): %s", key, n, reason)

    def drain(self) -> list[NeighbourPose]:
        """The poses that arrived since the last drain, checked (the others counted)."""
        out = []
        for payload, key in self._payloads.take():
            self.counts["received"] += 1
            try:
                msg = codec.decode(payload)
            except MessageError as exc:
                self._reject(str(exc), key)
                continue
            if not isinstance(msg, NeighbourPose) or key != neighbour_key(self.prefix, msg.observer):
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
        if self._own:
            self.session.close()

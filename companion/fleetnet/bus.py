"""The Zenoh session of one group companion, and the Zenoh configurations of a group's sessions.

:func:`zenoh_config` configures group ``g``'s companion (its endpoints, the fleet's settings and
the group's credentials, :mod:`.credentials`); :func:`peer_config` another session of the same
computer (its camera stream, a vision consumer) with the same credentials.

:class:`FleetBus` opens a session from a :class:`~companion.fleetnet.config.ZenohConfig`,
declares this group's liveliness token, subscribes to the other groups' boundaries, carried
links and homes, the leader's shifts and CPG targets and the liveliness of every group, and
publishes this group's boundary, its carried links, the chain's home it holds and (when it leads)
the shifts and targets. Zenoh calls back on its own threads; the callbacks only stamp the
arrival time and queue, and wake the daemon's ``select`` through a pipe (:meth:`fileno`);
:meth:`drain` decodes in the daemon's thread, where all the estimation state lives. A payload
that fails :func:`~companion.fleetnet.codec.decode` becomes an error event: the daemon counts
it per key and logs it; nothing else happens.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import time
from collections.abc import Sequence
from typing import Any

import zenoh

from companion.configfile import ConfigError
from companion.messages import (ChainHome, ChainTargets, GlobalShift, GroupBoundaryReport, GroupPassiveLinks,
                                MessageError)

from . import codec
from .config import ZenohConfig
from .credentials import ZenohSetting, group_credentials
from .hub import KINDS, BusEvent
from .keys import (alive_key, alive_pattern, boundary_key, boundary_pattern, group_of_key, home_key, home_pattern,
                   passive_key, passive_pattern, shift_key, target_key)

__all__ = ["BusEvent", "FleetBus", "open_group_session", "peer_config", "zenoh_config", "close_session"]

log = logging.getLogger(__name__)


#: How a session retries a peer endpoint it could not reach: after 0.1 s, backing off to 1 s
#: (Zenoh's default starts at 1 s and backs off to 4 s, so companions started together could
#: lead alone for seconds before they meet).
CONNECT_RETRY = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}


def close_session(session, what: str = "Zenoh session") -> None:
    """Close ``session``; a close that Zenoh gives up on (``zenoh.ZError``: it timed out, a peer
    stalled) is logged, not raised: the caller is stopping, and what it still has to write (its
    summary, its logs) must not be lost to it. The process's exit releases what is left."""
    try:
        session.close()
    except zenoh.ZError as exc:
        log.warning("%s: close failed (%s); left to the process's exit", what, exc)


def _insert(zc: zenoh.Config, settings: list[ZenohSetting]) -> zenoh.Config:
    for s in settings:
        try:
            zc.insert_json5(s.key, s.json5)
        except Exception as exc:  # zenoh raises ZError with the parser's message
            raise ConfigError(s.file, s.where, f"Zenoh rejected {s.key}: {exc}") from None
    return zc


def zenoh_config(cfg: ZenohConfig, group: int, n_groups: int, file: str = "<config>") -> zenoh.Config:
    """The Zenoh configuration of 0-based ``group``'s companion (errors name the config key)."""

    def setting(key: str, value: Any, where: str) -> ZenohSetting:
        return ZenohSetting(key, json.dumps(value), file, where)

    settings = [setting("mode", cfg.mode, "zenoh.mode"),
                setting("scouting/multicast/enabled", cfg.multicast_scouting, "zenoh.multicast_scouting"),
                setting("transport/link/tx/lease", int(cfg.lease_ms), "zenoh.lease_ms")]
    others = [cfg.group_endpoint(g) for g in range(n_groups) if g != group]
    if cfg.mode == "peer":
        settings += [setting("listen/endpoints", [cfg.group_endpoint(group)], "zenoh.endpoints"),
                     setting("connect/endpoints", others + list(cfg.connect), "zenoh.connect")]
    else:
        settings.append(setting("connect/endpoints", list(cfg.connect), "zenoh.connect"))
    settings.append(setting("connect/retry", CONNECT_RETRY, "zenoh.connect"))
    zc = _insert(zenoh.Config(), settings)
    return _insert(zc, group_credentials(cfg, group, n_groups, file))


def peer_config(listen: Sequence[str], connect: Sequence[str], credentials: Sequence[ZenohSetting] = (),
                multicast_scouting: bool = False, file: str = "<config>") -> zenoh.Config:
    """A peer session that listens on ``listen`` and connects to ``connect`` only (multicast
    scouting off unless asked), with ``credentials``: a session beside a group's companion on its
    computer (its camera stream, a vision consumer) takes the group's
    (:func:`~.credentials.group_credentials`), so it presents what the companion presents and
    admits only what the companion admits. Errors name ``file``'s ``zenoh.listen`` or
    ``zenoh.connect``, or the credentials' own file and key."""
    settings = [ZenohSetting("mode", '"peer"', file, "zenoh"),
                ZenohSetting("scouting/multicast/enabled", json.dumps(multicast_scouting), file,
                             "zenoh.multicast_scouting"),
                ZenohSetting("listen/endpoints", json.dumps(list(listen)), file, "zenoh.listen"),
                ZenohSetting("connect/endpoints", json.dumps(list(connect)), file, "zenoh.connect"),
                ZenohSetting("connect/retry", json.dumps(CONNECT_RETRY), file, "zenoh.connect")]
    return _insert(zenoh.Config(), settings + list(credentials))


#: how often a session whose listen address is not up yet is tried again [s]
ADDRESS_RETRY_S = 1.0
#: the error of a listen address no interface holds (yet): EADDRNOTAVAIL
_NOT_UP = "Cannot assign requested address"


def open_group_session(cfg: ZenohConfig, group: int, n_groups: int, file: str = "<config>",
                       wait_s: float | None = None, clock=time.monotonic, sleep=time.sleep):
    """0-based ``group``'s companion session (:func:`zenoh_config`), the process's Zenoh runtime
    sized by ``cfg.runtime_threads`` first; :class:`~companion.configfile.ConfigError` if Zenoh
    refuses to open it. A listen address no interface holds yet (a computer whose network is
    still coming up) is tried again every :data:`ADDRESS_RETRY_S`, saying so, for ``wait_s``
    (``None``: until it is up, as a serial link waits for its device; Ctrl-C stops it)."""
    zc = zenoh_config(cfg, group, n_groups, file)
    runtime = cfg.runtime_env()
    if runtime is not None:
        # read when Zenoh starts its runtime, at the first session of the process
        os.environ.setdefault("ZENOH_RUNTIME", runtime)
    listen = cfg.group_endpoint(group) if cfg.mode == "peer" else "(zenoh.endpoints)"
    start, said = clock(), -float("inf")
    while True:
        try:
            return zenoh.open(zc)
        except Exception as exc:
            waited = clock() - start
            if _NOT_UP not in str(exc) or (wait_s is not None and waited >= wait_s):
                raise ConfigError(file, "zenoh.listen" if _NOT_UP in str(exc) else "zenoh",
                                  f"cannot open the Zenoh session: {exc}") from None
            if waited - said >= 10.0:
                said = waited
                log.warning("the Zenoh listen address %s is not up on this computer yet (%.0f s): trying again "
                            "every %.0f s", listen, waited, ADDRESS_RETRY_S)
            sleep(ADDRESS_RETRY_S)


class FleetBus:
    """Zenoh wires of one group companion; see the module docstring."""

    def __init__(self, cfg: ZenohConfig, prefix: str, group: int, n_groups: int, file: str = "<config>",
                 clock=time.monotonic, wait_s: float | None = None):
        self.prefix = prefix
        self._clock = clock  # stamps each event on arrival (monotonic seconds, the daemon's clock)
        self.group = group
        self._events: queue.SimpleQueue[BusEvent] = queue.SimpleQueue()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        try:
            self.session = open_group_session(cfg, group, n_groups, file, wait_s)
        except Exception:
            self._close_pipe()
            raise
        s = self.session
        self._token = s.liveliness().declare_token(alive_key(prefix, group))
        self._subs = [
            s.liveliness().declare_subscriber(alive_pattern(prefix), self._on_liveliness, history=True),
            # this session's own publications are handled in-process, not echoed back
            s.declare_subscriber(boundary_pattern(prefix), self._on_data, allowed_origin=zenoh.Locality.REMOTE),
            s.declare_subscriber(shift_key(prefix), self._on_data, allowed_origin=zenoh.Locality.REMOTE),
            s.declare_subscriber(target_key(prefix), self._on_data, allowed_origin=zenoh.Locality.REMOTE),
            s.declare_subscriber(passive_pattern(prefix), self._on_data, allowed_origin=zenoh.Locality.REMOTE),
            s.declare_subscriber(home_pattern(prefix), self._on_data, allowed_origin=zenoh.Locality.REMOTE),
        ]
        opts = dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.INTERACTIVE_HIGH,
                    express=True)
        self._boundary_pub = s.declare_publisher(boundary_key(prefix, group), **opts)
        self._shift_pub = s.declare_publisher(shift_key(prefix), **opts)
        self._target_pub = s.declare_publisher(target_key(prefix), **opts)
        self._passive_pub = s.declare_publisher(passive_key(prefix, group), **opts)
        self._home_pub = s.declare_publisher(home_key(prefix, group), **opts)
        self.closed = False
        log.info("zenoh %s session %s: group %d, listening %s", cfg.mode, s.zid(), group + 1,
                 cfg.group_endpoint(group) if cfg.mode == "peer" else "-")

    # -- callbacks (Zenoh threads) --------------------------------------------------------------------
    def _push(self, event: BusEvent) -> None:
        self._events.put(event)
        try:
            os.write(self._wake_w, b"\0")
        except (BlockingIOError, OSError):
            pass  # the pipe is full (the daemon will drain everything) or closed

    def _on_data(self, sample) -> None:
        # stamp and queue only: decoding happens in the daemon's thread (:meth:`drain`), so the
        # callback holds the GIL for microseconds and the next sample is not held up behind it
        self._push(BusEvent("payload", sample.payload.to_bytes(), self._clock(), str(sample.key_expr)))

    def _decoded(self, ev: BusEvent) -> BusEvent:
        try:
            msg = codec.decode(ev.value)
        except MessageError as exc:
            return BusEvent("error", str(exc), ev.time_s, ev.key)
        kind = KINDS.get(type(msg))
        # a group's own messages on its own key (the key carries the group), the leader's on theirs
        expected = {"boundary": boundary_key(self.prefix, getattr(msg, "group", -1)),
                    "passive": passive_key(self.prefix, getattr(msg, "group", -1)),
                    "home": home_key(self.prefix, getattr(msg, "group", -1)),
                    "shift": shift_key(self.prefix), "targets": target_key(self.prefix)}
        misplaced = kind is None or ev.key != expected[kind]
        if misplaced:
            return BusEvent("error", f"{type(msg).__name__} does not belong on this key", ev.time_s, ev.key)
        return BusEvent(kind, msg, ev.time_s, ev.key)

    def _on_liveliness(self, sample) -> None:
        now = self._clock()
        key = str(sample.key_expr)
        g = group_of_key(self.prefix, key)
        if g is None:
            self._push(BusEvent("error", "liveliness token outside the group keys", now, key))
            return
        self._push(BusEvent("alive" if sample.kind == zenoh.SampleKind.PUT else "gone", g, now, key))

    # -- daemon side ----------------------------------------------------------------------------------
    def fileno(self) -> int:
        return self._wake_r

    def pending(self) -> bool:
        """Whether events wait to be drained (Zenoh's threads may add one right after)."""
        return not self._events.empty()

    def drain(self) -> list[BusEvent]:
        try:
            while os.read(self._wake_r, 4096):
                pass
        except (BlockingIOError, OSError):
            pass
        out = []
        while True:
            try:
                ev = self._events.get_nowait()
            except queue.Empty:
                return out
            out.append(self._decoded(ev) if ev.kind == "payload" else ev)

    def publish_boundary(self, report: GroupBoundaryReport) -> None:
        self._boundary_pub.put(codec.encode(report))

    def publish_shift(self, shift: GlobalShift) -> None:
        self._shift_pub.put(codec.encode(shift))

    def publish_targets(self, targets: ChainTargets) -> None:
        self._target_pub.put(codec.encode(targets))

    def publish_passive(self, passive: GroupPassiveLinks) -> None:
        self._passive_pub.put(codec.encode(passive))

    def publish_home(self, home: ChainHome) -> None:
        self._home_pub.put(codec.encode(home))

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            close_session(self.session, f"group {self.group + 1}'s session")  # drops the liveliness token
        finally:
            self._close_pipe()

    def _close_pipe(self) -> None:
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

"""The Zenoh session of one group companion (the only module of the stack that imports ``zenoh``).

:class:`FleetBus` opens a session from a :class:`~companion.fleetnet.config.ZenohConfig`,
declares this group's liveliness token, subscribes to the other groups' boundaries and carried
links, the leader's shifts and CPG targets and the liveliness of every group, and publishes this
group's boundary, its carried links and (when it leads) the shifts and targets. Zenoh calls back on its own threads; the callbacks only stamp the
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
from pathlib import Path
from typing import Any

import zenoh

from companion.configfile import ConfigError
from companion.keyfiles import read_private_text
from companion.messages import ChainTargets, GlobalShift, GroupBoundaryReport, GroupPassiveLinks, MessageError

from . import codec
from .config import ZenohConfig, group_user, read_users_file
from .hub import KINDS, BusEvent
from .keys import (alive_key, alive_pattern, boundary_key, boundary_pattern, group_of_key, passive_key, passive_pattern,
                   shift_key, target_key)

__all__ = ["BusEvent", "FleetBus", "zenoh_config"]

log = logging.getLogger(__name__)


def zenoh_config(cfg: ZenohConfig, group: int, n_groups: int, file: str = "<config>") -> zenoh.Config:
    """The Zenoh configuration of 0-based ``group``'s companion (errors name the config key)."""
    zc = zenoh.Config()

    def put(key: str, value: Any, where: str, json5_text: bool = False) -> None:
        try:
            zc.insert_json5(key, value if json5_text else json.dumps(value))
        except Exception as exc:  # zenoh raises ZError with the parser's message
            raise ConfigError(file, where, f"Zenoh rejected {key}: {exc}") from None

    put("mode", cfg.mode, "zenoh.mode")
    put("scouting/multicast/enabled", cfg.multicast_scouting, "zenoh.multicast_scouting")
    put("transport/link/tx/lease", int(cfg.lease_ms), "zenoh.lease_ms")
    others = [cfg.group_endpoint(g) for g in range(n_groups) if g != group]
    if cfg.mode == "peer":
        put("listen/endpoints", [cfg.group_endpoint(group)], "zenoh.endpoints")
        put("connect/endpoints", others + list(cfg.connect), "zenoh.connect")
    else:
        put("connect/endpoints", list(cfg.connect), "zenoh.connect")
    tls = cfg.tls
    if tls.certs_dir:
        _check_certs_dir(cfg, group, n_groups, file)
    for name, path in tls.files(group).items():
        where = "zenoh.tls.certs_dir" if tls.certs_dir else f"zenoh.tls.{name}"
        if not Path(path).is_file():
            raise ConfigError(file, where, f"no such file: {path}")
        put(f"transport/link/tls/{name}", path, where)
    if tls.configured:
        put("transport/link/tls/enable_mtls", tls.mtls, "zenoh.tls.enable_mtls")
    if cfg.users_file:
        try:
            users = read_users_file(cfg.users_file)
        except ValueError as exc:
            raise ConfigError(file, "zenoh.users_file", str(exc)) from None
        user = group_user(group)
        if user not in users:
            raise ConfigError(file, "zenoh.users_file", f"{cfg.users_file} has no user {user} (group {group + 1})")
        put("transport/auth/usrpwd/user", user, "zenoh.users_file")
        put("transport/auth/usrpwd/password", users[user], "zenoh.users_file")
        put("transport/auth/usrpwd/dictionary_file", str(Path(cfg.users_file).resolve()), "zenoh.users_file")
    if cfg.access_control:
        try:
            text = Path(cfg.access_control).read_text()
        except OSError as exc:
            raise ConfigError(file, "zenoh.access_control", f"cannot read {cfg.access_control}: {exc.strerror}") from None
        put("access_control", text, "zenoh.access_control", json5_text=True)
    return zc


def _check_certs_dir(cfg: ZenohConfig, group: int, n_groups: int, file: str) -> None:
    """``ConfigError`` at ``zenoh.tls.certs_dir`` unless 0-based ``group``'s files are there, its key
    is private, and its certificate is the fleet CA's, valid now, for the host of its endpoint."""
    from .certs import check_group_certificate  # cryptography: only companions that use certs_dir

    files = cfg.tls.files(group)
    make = (f"create them with `python -m companion certs DIR --groups {n_groups} --hosts HOST1 ...` and copy "
            f"ca.pem, {group_user(group)}.pem and {group_user(group)}.key to this computer")
    for name, what in (("root_ca_certificate", "the fleet CA certificate"),
                       ("listen_certificate", f"group {group + 1}'s certificate"),
                       ("listen_private_key", f"group {group + 1}'s private key")):
        if not Path(files[name]).is_file():
            raise ConfigError(file, "zenoh.tls.certs_dir", f"no such file: {files[name]} ({what}); {make}")
    try:
        read_private_text(files["listen_private_key"], "TLS private key")
        host = None
        if cfg.mode == "peer":
            host = cfg.group_endpoint(group).split("/", 1)[1].rsplit(":", 1)[0]
        check_group_certificate(files["listen_certificate"], files["root_ca_certificate"], host)
    except ValueError as exc:
        raise ConfigError(file, "zenoh.tls.certs_dir", str(exc)) from None


class FleetBus:
    """Zenoh wires of one group companion; see the module docstring."""

    def __init__(self, cfg: ZenohConfig, prefix: str, group: int, n_groups: int, file: str = "<config>",
                 clock=time.monotonic):
        self.prefix = prefix
        self._clock = clock  # stamps each event on arrival (monotonic seconds, the daemon's clock)
        self.group = group
        self._events: queue.SimpleQueue[BusEvent] = queue.SimpleQueue()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        zc = zenoh_config(cfg, group, n_groups, file)
        runtime = cfg.runtime_env()
        if runtime is not None:
            # read when Zenoh starts its runtime, at the first session of the process
            os.environ.setdefault("ZENOH_RUNTIME", runtime)
        try:
            self.session = zenoh.open(zc)
        except Exception as exc:
            self._close_pipe()
            raise ConfigError(file, "zenoh", f"cannot open the Zenoh session: {exc}") from None
        s = self.session
        self._token = s.liveliness().declare_token(alive_key(prefix, group))
        self._subs = [
            s.liveliness().declare_subscriber(alive_pattern(prefix), self._on_liveliness, history=True),
            # this session's own publications are handled in-process, not echoed back
            s.declare_subscriber(boundary_pattern(prefix), self._on_data, allowed_origin=zenoh.Locality.REMOTE),
            s.declare_subscriber(shift_key(prefix), self._on_data, allowed_origin=zenoh.Locality.REMOTE),
            s.declare_subscriber(target_key(prefix), self._on_data, allowed_origin=zenoh.Locality.REMOTE),
            s.declare_subscriber(passive_pattern(prefix), self._on_data, allowed_origin=zenoh.Locality.REMOTE),
        ]
        opts = dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.INTERACTIVE_HIGH,
                    express=True)
        self._boundary_pub = s.declare_publisher(boundary_key(prefix, group), **opts)
        self._shift_pub = s.declare_publisher(shift_key(prefix), **opts)
        self._target_pub = s.declare_publisher(target_key(prefix), **opts)
        self._passive_pub = s.declare_publisher(passive_key(prefix, group), **opts)
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

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.session.close()  # drops the liveliness token: the others see this group leave
        finally:
            self._close_pipe()

    def _close_pipe(self) -> None:
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

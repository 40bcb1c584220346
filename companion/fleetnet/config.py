"""The ``[zenoh]`` section of a scenario: how group companions reach each other (pure, validated).

One file serves every companion of a chain: group ``g`` (1-based) listens on ``endpoints[g-1]``
and connects to the other groups' endpoints (a full mesh, peer mode: the thesis's three
Raspberry Pis on one bridged network). Empty ``endpoints`` are the SITL defaults,
``tcp/127.0.0.1:<base_port + g - 1>``. Multicast scouting is off unless enabled, so nothing
leaves the configured endpoints. ``lease_ms`` is the Zenoh transport lease: a companion whose
link goes silent (cable pulled, process frozen) is declared gone after it, which bounds the
leader failover time; a process that exits or is killed closes its TCP links and is gone at once.

Authentication (``users_file``): a file of ``user:password`` lines (Zenoh's user-password
dictionary, mode 600) naming every companion of the fleet, ``companion-g<G>`` for group ``G``.
Each companion authenticates as its group's user and admits only sessions that present a user
and password of the file: a session without them (a process on the same host, a laptop on the
network) cannot open a transport to the fleet, so it can neither publish nor subscribe under the
fleet's prefix. ``python -m companion keys zenoh FILE --groups N`` writes one; a SITL launch of a
distributed scenario without one makes a throwaway file in its run folder. User-password
authentication is checked by the listening side only and does not encrypt the traffic: on
hardware use mutual TLS as well.

Mutual TLS (``[zenoh.tls]``, hardware): every link between companions is TLS, and both ends
present a certificate signed by the fleet CA, so a session without one (or with another CA's)
cannot even complete the handshake, and each side knows the other is a fleet computer. Make the
files once with ``python -m companion certs DIR --groups N --hosts H1 .. HN``
(:mod:`.certs`: ``ca.pem``, ``ca.key`` and per group ``companion-g<G>.pem`` / ``.key``, each
certificate naming its group's endpoint host, which Zenoh checks when it connects) and set
``certs_dir = DIR`` (relative to the config file's folder): the one config file then serves every
group, and group ``G`` uses ``ca.pem`` as root CA and ``companion-g<G>.pem`` / ``.key`` as both
listen (server) and connect (client) certificate, with ``enable_mtls`` on. A group's computer
needs only ``ca.pem`` and its own pair; ``ca.key`` stays on the computer that made them.
Before the session opens, the companion checks its files: present, its key private (mode 600), its
certificate signed by that CA, valid now and made for its endpoint's host (errors at
``zenoh.tls.certs_dir`` name the file). The endpoints must then be ``tls/`` (or ``quic/``).
Instead of ``certs_dir``, the explicit keys ``root_ca_certificate``,
``listen_certificate``/``listen_private_key``, ``connect_certificate``/``connect_private_key``
and ``enable_mtls`` name one computer's files (used as given, checked to exist when the session
opens); the two ways do not mix.

Access control (``access_control``: a JSON5 file holding Zenoh's ``access_control`` object) is
read when the session opens.
"""

from __future__ import annotations

import re
import secrets
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from companion.configfile import build, load_toml, require_positive
from companion.keyfiles import read_private_text, write_private_text

__all__ = ["CA_CERT", "ZenohTls", "ZenohConfig", "PREFIX_RE", "group_user", "load_zenoh_table", "new_users_file",
           "read_users_file"]

#: A fleet prefix: one or more key chunks of letters, digits, ``_`` and ``-``, joined by ``/``.
PREFIX_RE = re.compile(r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$")
_ENDPOINT_RE = re.compile(r"^(tcp|tls|udp|quic)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")
#: The fleet CA's certificate in a ``certs_dir`` (group ``G``'s files are ``companion-g<G>.pem`` / ``.key``).
CA_CERT = "ca.pem"
_TLS_FILES = ("root_ca_certificate", "listen_certificate", "listen_private_key", "connect_certificate",
              "connect_private_key")


@dataclass(frozen=True)
class ZenohTls:
    """Zenoh TLS files (PEM). ``enable_mtls`` also authenticates the connecting side.

    ``certs_dir``: a folder written by ``python -m companion certs`` (relative paths are resolved
    against the config file's folder): group ``G`` uses ``ca.pem`` as root CA and
    ``companion-g<G>.pem`` / ``.key`` as listen and connect certificate, with mutual TLS. It
    replaces the five file keys, which name the same files for one computer.
    """

    root_ca_certificate: str = ""
    listen_certificate: str = ""
    listen_private_key: str = ""
    connect_certificate: str = ""
    connect_private_key: str = ""
    enable_mtls: bool | None = None
    certs_dir: str = ""

    def __post_init__(self) -> None:
        if self.certs_dir:
            explicit = [name for name in _TLS_FILES if getattr(self, name)]
            if explicit:
                raise ValueError(f"certs_dir names every TLS file by the group: drop {', '.join(explicit)} "
                                 "(or drop certs_dir and name the files of one computer)")
            if self.enable_mtls is False:
                raise ValueError("enable_mtls: certs_dir always uses mutual TLS (every companion has its certificate)")
        if bool(self.listen_certificate) != bool(self.listen_private_key):
            raise ValueError("listen_certificate and listen_private_key go together")
        if bool(self.connect_certificate) != bool(self.connect_private_key):
            raise ValueError("connect_certificate and connect_private_key go together")
        if self.enable_mtls and not (self.connect_certificate or self.certs_dir):
            raise ValueError("enable_mtls needs connect_certificate and connect_private_key")

    @property
    def configured(self) -> bool:
        return bool(self.root_ca_certificate or self.listen_certificate or self.certs_dir)

    @property
    def mtls(self) -> bool:
        """Whether both sides of every link present a certificate."""
        return bool(self.certs_dir) if self.enable_mtls is None else self.enable_mtls

    def files(self, group: int) -> dict[str, str]:
        """Zenoh's ``transport/link/tls`` file keys for 0-based ``group``'s companion, the set ones only."""
        if self.certs_dir:
            base = Path(self.certs_dir)
            cert, key = str(base / f"{group_user(group)}.pem"), str(base / f"{group_user(group)}.key")
            return {"root_ca_certificate": str(base / CA_CERT), "listen_certificate": cert,
                    "listen_private_key": key, "connect_certificate": cert, "connect_private_key": key}
        return {name: getattr(self, name) for name in _TLS_FILES if getattr(self, name)}


@dataclass(frozen=True)
class ZenohConfig:
    """See the module docstring.

    ``prefix``: key-expression prefix of this fleet (default: the scenario name).
    ``mode``: ``peer`` (default; companions connect to each other) or ``client`` (through the
    routers in ``connect``). ``leader_order``: groups (1-based) in order of preference for the
    leader; default: the middle group first, then outwards (thesis sec. 5.1: the central
    computer leads). ``shift_deadline_ms``: how long a group waits for the leader's shift
    before it sends its local-only corrections. ``leader_wait_ms``: how long the leader waits
    for missing boundaries after the first one of a cycle before it solves without them.
    ``handover_cycles``: cycles of notice a leader gives a returning preferred group.
    ``runtime_threads``: worker threads per Zenoh runtime pool in a companion (sets
    ``ZENOH_RUNTIME`` unless it is set already; 0 keeps Zenoh's defaults). A companion sends a
    few small messages per cycle; on the 2-core development VM one thread per pool cut the
    loopback round trip's p99 from 4-6 ms to 2.5 ms.
    ``vision_session``: a centralised companion (one group) opens a Zenoh session on group 1's
    endpoint, with group 1's credentials, for the vision consumer's messages (neighbour poses on
    ``<prefix>/link/<i>/neighbour``, load observations on ``<prefix>/vehicle/<i>/load``);
    distributed companions take them on their fleet session.
    """

    prefix: str = ""
    mode: Literal["peer", "client"] = "peer"
    endpoints: tuple[str, ...] = ()
    base_port: int = 7460
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    lease_ms: int = 1000
    tls: ZenohTls = field(default_factory=ZenohTls)
    access_control: str = ""
    users_file: str = ""
    leader_order: tuple[int, ...] = ()
    shift_deadline_ms: float = 35.0
    leader_wait_ms: float = 25.0
    handover_cycles: int = 3
    runtime_threads: int = 1
    vision_session: bool = False

    def __post_init__(self) -> None:
        if self.prefix and not PREFIX_RE.match(self.prefix):
            raise ValueError(f"prefix {self.prefix!r}: use letters, digits, '_' and '-' in '/'-separated chunks "
                             "(no wildcards '*', '$', no leading or trailing '/')")
        for key in ("endpoints", "connect"):
            for ep in getattr(self, key):
                m = _ENDPOINT_RE.match(ep)
                if not m or not 0 < int(m.group(3)) <= 65535:
                    raise ValueError(f"{key}: {ep!r} is not a Zenoh endpoint like tcp/10.0.0.2:7447 "
                                     "(tcp, tls, udp or quic; port 1..65535)")
                if self.tls.configured != ep.startswith(("tls/", "quic/")):
                    raise ValueError(f"{key}: {ep!r}: " + ("[zenoh.tls] is set, use tls/ or quic/ endpoints"
                                                           if self.tls.configured else "tls/ and quic/ need [zenoh.tls]"))
        if len(set(self.endpoints)) != len(self.endpoints):
            raise ValueError(f"endpoints: every group needs its own endpoint, got {list(self.endpoints)}")
        if not 1 <= self.base_port <= 65535:
            raise ValueError(f"base_port must be in 1..65535, got {self.base_port}")
        if self.mode == "client" and not self.connect:
            raise ValueError("connect: client mode needs at least one router here")
        if self.tls.configured and not self.endpoints:
            raise ValueError("endpoints: [zenoh.tls] needs explicit tls/ endpoints (the SITL defaults are plain tcp "
                             "on loopback)")
        require_positive(self, "lease_ms", "shift_deadline_ms", "leader_wait_ms", "handover_cycles")
        if not 0 <= self.runtime_threads <= 64:
            raise ValueError(f"runtime_threads must be in 0..64, got {self.runtime_threads}")

    @property
    def secured(self) -> bool:
        """Whether sessions of this fleet present credentials (TLS, user and password) or follow access rules."""
        return bool(self.tls.configured or self.users_file or self.access_control)

    def resolved(self, folder: str | Path) -> ZenohConfig:
        """This config with a relative ``users_file`` and ``tls.certs_dir`` taken from ``folder``
        (the config file's)."""
        cfg, folder = self, Path(folder)
        if cfg.users_file:
            cfg = replace(cfg, users_file=str(folder / Path(cfg.users_file).expanduser()))
        if cfg.tls.certs_dir:
            cfg = replace(cfg, tls=replace(cfg.tls, certs_dir=str(folder / Path(cfg.tls.certs_dir).expanduser())))
        return cfg

    def runtime_env(self) -> str | None:
        """The ``ZENOH_RUNTIME`` value for ``runtime_threads`` (``None``: Zenoh's defaults)."""
        if not self.runtime_threads:
            return None
        pools = ", ".join(f"{p}: (worker_threads: {self.runtime_threads})" for p in ("app", "acc", "tx", "rx", "net"))
        return f"({pools})"

    def check_groups(self, n_groups: int, period_ms: float) -> None:
        """``ValueError`` if ``endpoints`` or ``leader_order`` do not fit ``n_groups`` groups, or
        the deadlines do not fit one step period."""
        if not self.leader_wait_ms < self.shift_deadline_ms < period_ms:
            raise ValueError(f"leader_wait_ms ({self.leader_wait_ms:g}) < shift_deadline_ms ({self.shift_deadline_ms:g}) "
                             f"< the step period ({period_ms:g} ms) must hold")
        if self.endpoints and len(self.endpoints) != n_groups:
            raise ValueError(f"endpoints lists {len(self.endpoints)} endpoints for {n_groups} groups (one per group)")
        if self.leader_order and sorted(self.leader_order) != list(range(1, n_groups + 1)):
            raise ValueError(f"leader_order {list(self.leader_order)} must list each of the groups 1..{n_groups} once")

    def group_endpoint(self, group: int) -> str:
        """Listen endpoint of 0-based ``group``."""
        return self.endpoints[group] if self.endpoints else f"tcp/127.0.0.1:{self.base_port + group}"

    def order(self, n_groups: int) -> tuple[int, ...]:
        """0-based groups in leader preference order."""
        if self.leader_order:
            return tuple(g - 1 for g in self.leader_order)
        mid = (n_groups - 1) / 2
        return tuple(sorted(range(n_groups), key=lambda g: (abs(g - mid), g)))


def load_zenoh_table(path: str | Path) -> ZenohConfig:
    """The ``[zenoh]`` table of a config file (a companion's or a scenario), its ``users_file`` and
    ``tls.certs_dir`` relative to the file's folder; :class:`~companion.configfile.ConfigError`
    names the file and key."""
    table = load_toml(path).get("zenoh", {})
    return build(ZenohConfig, table, file=str(path), prefix="zenoh").resolved(Path(path).resolve().parent)


def group_user(group: int) -> str:
    """The Zenoh user of 0-based ``group``'s companion."""
    return f"companion-g{group + 1}"


def read_users_file(path: str) -> dict[str, str]:
    """``{user: password}`` of a Zenoh user-password file; ``ValueError`` naming the problem (missing,
    readable by group or others, a line that is not ``user:password``)."""
    users: dict[str, str] = {}
    for k, line in enumerate(read_private_text(path, "Zenoh user-password file").splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        if not sep or not re.fullmatch(r"[A-Za-z0-9_.-]+", user) or len(password) < 16 or ":" in password:
            raise ValueError(f"{path}:{k}: not user:password (a password of 16 characters or more, no ':')")
        users[user] = password
    if not users:
        raise ValueError(f"{path}: no users")
    return users


def new_users_file(path, n_groups: int, overwrite: bool = False) -> None:
    """Write a user-password file for ``n_groups`` companions (random 256-bit passwords, mode 600)."""
    text = "\n".join(f"{group_user(g)}:{secrets.token_urlsafe(32)}" for g in range(n_groups))
    write_private_text(path, text, overwrite)


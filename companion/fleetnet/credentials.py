"""What a session on one group's computer presents to the fleet's Zenoh and demands of it (no
``zenoh`` import: the checks run where a config is loaded, without the ``distributed`` extra).

:func:`group_credentials` turns a :class:`~.config.ZenohConfig` into the Zenoh settings of
0-based ``group``: the ``[zenoh.tls]`` files (with ``certs_dir``: the fleet CA and the group's
certificate and key, checked first: present, key private, certificate the CA's, valid now, made
for the host of the group's endpoint) and ``enable_mtls``; the group's user and password from
``users_file``, with the file as the dictionary the session checks connecting sessions against;
and the ``access_control`` rules. The group's companion (:func:`~.bus.zenoh_config`) and the other
sessions of its computer (its camera stream, a vision consumer: :func:`~.bus.peer_config`) take
the same settings, so the fleet admits and refuses them alike. Errors are
:class:`~companion.configfile.ConfigError` naming the config file and its ``zenoh.*`` key.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

from companion.configfile import ConfigError
from companion.keyfiles import read_private_text

from .config import ZenohConfig, group_user, read_users_file

__all__ = ["ZenohSetting", "group_credentials"]


class ZenohSetting(NamedTuple):
    """One Zenoh configuration entry: its key path, its value as JSON5 text, and the config file
    and key it comes from (for the error when Zenoh rejects it)."""

    key: str
    json5: str
    file: str
    where: str


def group_credentials(cfg: ZenohConfig, group: int, n_groups: int, file: str = "<config>") -> list[ZenohSetting]:
    """The TLS, user-password and access-control settings of 0-based ``group`` (module docstring);
    empty when ``cfg`` has none of them. ``n_groups`` only serves the advice in the errors."""
    out: list[ZenohSetting] = []
    tls = cfg.tls
    if tls.certs_dir:
        _check_certs_dir(cfg, group, n_groups, file)
    for name, path in tls.files(group).items():
        where = "zenoh.tls.certs_dir" if tls.certs_dir else f"zenoh.tls.{name}"
        if not Path(path).is_file():
            raise ConfigError(file, where, f"no such file: {path}")
        out.append(ZenohSetting(f"transport/link/tls/{name}", json.dumps(path), file, where))
    if tls.configured:
        out.append(ZenohSetting("transport/link/tls/enable_mtls", json.dumps(tls.mtls), file, "zenoh.tls.enable_mtls"))
    if cfg.users_file:
        try:
            users = read_users_file(cfg.users_file)
        except ValueError as exc:
            raise ConfigError(file, "zenoh.users_file", str(exc)) from None
        user = group_user(group)
        if user not in users:
            raise ConfigError(file, "zenoh.users_file", f"{cfg.users_file} has no user {user} (group {group + 1})")
        for key, value in (("user", user), ("password", users[user]),
                           ("dictionary_file", str(Path(cfg.users_file).resolve()))):
            out.append(ZenohSetting(f"transport/auth/usrpwd/{key}", json.dumps(value), file, "zenoh.users_file"))
    if cfg.access_control:
        try:
            text = Path(cfg.access_control).read_text()
        except OSError as exc:
            raise ConfigError(file, "zenoh.access_control",
                              f"cannot read {cfg.access_control}: {exc.strerror}") from None
        out.append(ZenohSetting("access_control", text, file, "zenoh.access_control"))
    return out


def _check_certs_dir(cfg: ZenohConfig, group: int, n_groups: int, file: str) -> None:
    """``ConfigError`` at ``zenoh.tls.certs_dir`` unless 0-based ``group``'s files are there, its key
    is private, and its certificate is the fleet CA's, valid now, for the host of its endpoint."""
    from .certs import check_group_certificate  # cryptography: only where certs_dir is used

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

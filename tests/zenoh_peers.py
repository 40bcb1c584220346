"""Bare Zenoh sessions on loopback for the tests: a harness, an outsider, a rogue."""

from __future__ import annotations

import json


def peer_session(listen: tuple[str, ...] | None = None, connect: tuple[str, ...] | None = None, **settings):
    """A Zenoh peer with multicast scouting off, listening on ``listen`` and connecting to
    ``connect`` (endpoints such as ``tcp/127.0.0.1:7447``; ``None``: Zenoh's default);
    ``settings``: more of Zenoh's configuration, a key path with ``__`` for ``/``
    (``transport__link__tls__root_ca_certificate="ca.pem"``) to its value."""
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    if listen is not None:
        c.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect is not None:
        c.insert_json5("connect/endpoints", json.dumps(list(connect)))
    for key, value in settings.items():
        c.insert_json5(key.replace("__", "/"), json.dumps(value))
    return zenoh.open(c)

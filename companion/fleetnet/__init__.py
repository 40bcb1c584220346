"""Companion-to-companion network over Eclipse Zenoh (semi-distributed estimation, docs/architecture.md).

* :mod:`.config` -- the ``[zenoh]`` section of a scenario (pure, validated);
* :mod:`.codec` -- typed, versioned binary payloads of :mod:`companion.messages` (pure);
* :mod:`.keys` -- the key expressions under the fleet prefix (pure);
* :mod:`.leader` -- leader election and the global-step collector (pure, no clocks or I/O);
* :mod:`.outcomes` -- what the collector takes in and gives out per part of a group (pure);
* :mod:`.solve` -- eq. 6 over the groups' reported boundaries, and each group's covariance terms (pure);
* :mod:`.group` -- the node on a bus, with its operational record (clock and bus passed in);
* :mod:`.hub` -- bus events and an in-process bus (batch mode; pure);
* :mod:`.certs` -- the fleet CA and each group's TLS certificate (``python -m companion certs``);
* :mod:`.credentials` -- what a group's sessions present and demand: TLS, user and password, access control;
* :mod:`.bus` -- the Zenoh session wrapper and the Zenoh configurations of a group's sessions.
* :mod:`.payload_queue` -- a subscriber's payloads, queued on Zenoh's thread, taken in the caller's;
* :mod:`.inbox` -- the vision consumer's neighbour poses and load observations, taken by a companion.
"""

"""Companion-to-companion network over Eclipse Zenoh (semi-distributed estimation, DESIGN.md sec. 3).

* :mod:`.config` -- the ``[zenoh]`` section of a scenario (pure, validated);
* :mod:`.codec` -- typed, versioned binary payloads of :mod:`companion.messages` (pure);
* :mod:`.keys` -- the key expressions under the fleet prefix (pure);
* :mod:`.leader` -- leader election and the global-step collector (pure, no clocks or I/O);
* :mod:`.bus` -- the Zenoh session wrapper (the only module that imports ``zenoh``).
"""

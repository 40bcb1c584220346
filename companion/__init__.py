"""The companion computer of an aerial skeleton, and the pure core every layer builds on.

Layers run one way: ``companion`` <- ``link_firmware_sim`` <- ``sitl`` (docs/architecture.md);
this package imports neither of the other two, and its base install (``pip install .``) is what
an onboard computer needs.

Pure core (no sockets, clocks or threads):

* :mod:`.estimation` -- SO(3), the chain constraint (eq. 3-4), constraint application (Alg. 1),
  the semi-distributed step (Alg. 2, eq. 6);
* :mod:`.messages` -- the typed messages of every wire (one schema);
* :mod:`.skeleton` -- the vehicle model: links, rotors (Table 2.1), gravity, the chain's
  kinematics and its pinocchio multibody model;
* :mod:`.config`, :mod:`.configfile` -- the companion's config schema and the TOML loader;
* :mod:`.corrections`, :mod:`.engine` -- the 20 Hz step and the companion engine (everything the
  daemon decides);
* :mod:`.trajectory`, :mod:`.motion` -- the target sources (take-off, bending, CPG, thesis ch. 4);
* :mod:`.mavlink` (codec, frames, standard messages, dialect) and :mod:`.fleetnet` (Zenoh
  codec, leader election) -- the wire codecs.

Shells: :mod:`.daemon` (``python -m companion``), :mod:`.mavlink.port` and its transports
(:mod:`.mavlink.transport`, :mod:`.mavlink.sockets`, :mod:`.mavlink.serialport`), :mod:`.fleetnet.bus`
(Zenoh, distributed mode only), :mod:`.replay`, :mod:`.cli`.
"""

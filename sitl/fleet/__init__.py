"""Fleet mode: the MuJoCo harness in lockstep with one firmware process per link, plus the companion.

``python -m sitl launch --config FILE`` starts, for an n-link scenario:

* n vehicle processes (``python -m link_firmware_sim``): link ``i`` is MAVLink system ``i + 1``,
  simulator TCP 4560+i, onboard UDP 14540+i (from 14580+i), GCS UDP 14550 (from 18570+i; another
  port with ``--gcs-port``);
* the companion daemon (``python -m companion``), listening on UDP 14540+i; with
  ``companion.distributed`` one per group (``--group G``, run folder ``companion-gG``), joined
  over Zenoh on loopback (``tcp/127.0.0.1:7460+G-1``, clear of a local zenohd on 7447); ``[faults]`` can SIGKILL one of them
  mid-flight and start a new one later (folder ``companion-gG-restart``);
* with ``--sim-link unix`` the vehicles' simulator links are the same-host link
  (:mod:`link_firmware_sim.vehicle.simlink`: the same HIL messages as binary records over UNIX sockets in
  a private temporary folder) instead of PX4's TCP 4560+i, which stays the default;
* with ``--instance-offset K`` every one of these ports moves by K (link ``i`` is PX4 SITL
  instance K+i; the system ids stay), so that two fleets can fly side by side;
* the harness (this process, :mod:`.harness`): the same :class:`~sitl.plant.plant.Plant` as batch
  mode, talking to each vehicle over its simulator link. Lockstep: at every firmware tick the
  harness sends HIL_GPS / SKELETON_AHRS_REFERENCE (when due) and HIL_SENSOR to every vehicle,
  waits until every vehicle has answered with HIL_ACTUATOR_CONTROLS for that time, then advances
  the physics. ``--speed F`` paces the simulation at F times real time (0: as fast as possible).

At the end (or on Ctrl-C) every process is stopped (SIGTERM, then SIGKILL after a grace period;
children also die with the launcher through PR_SET_PDEATHSIG), their logs are merged and the run
folder gets the same ``metrics.json``, ``log.npz`` and plots as batch mode, plus a .tlog per link.

A scenario with ``[[cameras]]`` adds the vision consumer (``python -m companion.vision``, folder
``vision``): the harness renders the cameras on the simulation clock and publishes their frames
on ``<prefix>/camera/<vehicle>/image`` from a Zenoh session per camera-carrying group on a free
loopback port, with that group's credentials in a secured fleet (:mod:`sitl.cameras.stream`); the
consumer runs the marker pipeline on them, and ``metrics.json["vision"]`` scores its poses against
the truth (``vision.npz``).

The modules: :mod:`.launcher` (:func:`~.launcher.launch`, the run as a :class:`~.launcher.Fleet`),
:mod:`.layout` (ports, checks, the endpoint table, :class:`~.layout.FleetError`), :mod:`.harness`
(the lockstep), :mod:`.processes` (process control, scheduling, /proc port probes), :mod:`.logs`
(the logs merged, counters, fault reports), :mod:`.faults` (the harness faults, scripted or asked
for at run time through :mod:`.fault_socket` and ``python -m sitl fault``, :mod:`.fault_cli`),
:mod:`.inject` (failure injection by MAVLink command), :mod:`.wire` (the impaired wire's proxy,
``python -m sitl.fleet.wire``) and :mod:`.sim_time` (the lockstep's time, shared with the wire). The package imports none of them itself: the wire's process loads
no simulator.
"""

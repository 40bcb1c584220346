"""The vehicle's I/O: one link's firmware as a MAVLink 2 vehicle process (``python -m
link_firmware_sim``), one module per job (PX4's mavlink module is the model):

* :mod:`.core`: :class:`~.core.Vehicle`, the process: its ports, the main loop, the dispatch of
  what arrives, the counters written at the end;
* :mod:`.links`: the ports a vehicle opens (:class:`~.links.VehiclePorts`, PX4 SITL's by default)
  and each MAVLink link's state; STATUSTEXT;
* :mod:`.lockstep`: the simulator link's side in Python, the decoders' path and the compiled ones
  (the record tick, the lockstep loop);
* :mod:`.streams`: the telemetry streams, one module per family of messages, and their schedule;
* :mod:`.commands`: COMMAND_LONG / COMMAND_INT (arm and disarm, SET_MESSAGE_INTERVAL,
  REQUEST_MESSAGE, the contact command, INJECT_FAILURE, DO_SET_HOME); :mod:`.failures`: the
  injected failures and the samples they change; :mod:`.home`: the home position;
* :mod:`.targets`: the pose target from the companion's target messages;
* :mod:`.params`: the parameter table (names, ranges, persistence, the firmware config it gives);
  :mod:`.param_protocol`: the PARAM_* protocol over it; :mod:`.origin`: SET_GPS_GLOBAL_ORIGIN;
* :mod:`.signing_setup`: SETUP_SIGNING; :mod:`.ftp`: MAVLink FTP without a file system;
* :mod:`.recorder`: the flight log;
* :mod:`.hil`: the HIL messages' encoders and decoders (units, frames, checks), used by the
  simulator too; :mod:`.simlink`: the same-host simulator link (UNIX sockets) and the simulator's
  end of PX4's TCP link.

Nothing is imported here: the firmware's configuration reads :mod:`.params` without the rest.
"""

"""The physical side of a SITL run, shared by batch mode (:mod:`sitl.runner`) and fleet mode
(:mod:`sitl.fleet`); nothing here knows about firmware or companions.

* :mod:`.plant`: :class:`~.plant.Plant`, one physics tick as kinematics and truth, then rotor
  dynamics, wind and integration; the take-off and crash checks;
* :mod:`.model`: the MuJoCo model generated from the scenario (links, joints, rotors, sensors);
* :mod:`.rotor`: the rotor and reversible-ESC model (its compiled kernels: :mod:`sitl.kernels.rotor`);
* :mod:`.sensors`: IMU, GNSS, attitude reference, barometer and magnetometer models;
* :mod:`.wind`: steady wind and gusts as drag on the links;
* :mod:`.schedule`: every rate as a whole number of physics ticks;
* :mod:`.start`: where the chain starts.

The package imports nothing itself: :mod:`.sensors`, :mod:`.schedule` and :mod:`.start` load
without MuJoCo.
"""

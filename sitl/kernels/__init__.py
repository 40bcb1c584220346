"""The simulator's compiled kernels (numba), leaves like :mod:`companion.kernels`: each imports
the standard library, numpy, numba and other kernel modules only, and computes what a readable
numpy specification in its caller computes (its oracle in the tests).

* :mod:`.rotor`: the rotor and reversible-ESC model (:class:`sitl.plant.rotor.RotorBank`);
* :mod:`.sensors`: the IMU's noise and bias walks (:meth:`sitl.plant.sensors.LinkSensors.imu`).
"""

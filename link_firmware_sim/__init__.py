"""The simulated Pixhawk of one link (builds on :mod:`companion`'s pure modules, never on ``sitl``).

Pure firmware, folders by role: :mod:`.estimators` (the SE(3) error-state EKF, its tunings, GPS
health), :mod:`.controllers` (eq. 1's impedance control, the SE(3) PID, hybrid, PSPM),
:mod:`.allocation` (ODAR allocation, Prop. 1, selective mapping 2.15-2.17), :mod:`.firmware`
(:class:`~.firmware.LinkFirmware`: all of it on one clock), :mod:`.kernels` (the per-tick path
compiled). Shell: :mod:`.vehicle` (a MAVLink 2 vehicle process, ``python -m link_firmware_sim``:
its streams, commands, parameters, the simulator link) and the geodesy of the simulated GPS
:mod:`.geo`; its configuration is :mod:`.config`.
"""

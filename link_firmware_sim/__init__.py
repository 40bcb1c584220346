"""The simulated Pixhawk of one link (builds on :mod:`companion`'s pure modules, never on ``sitl``).

Pure firmware: :mod:`.ekf` (SE(3) error-state EKF), :mod:`.control` (impedance control, eq. 1),
:mod:`.allocation` (ODAR allocation, Prop. 1, selective mapping 2.15-2.17), :mod:`.firmware`
(:class:`~.firmware.LinkFirmware`: all of it on one clock), :mod:`.params` (the parameter table).
Shell: :mod:`.vehicle` (a MAVLink 2 vehicle process, ``python -m link_firmware_sim``) with the
simulator link :mod:`.hil` and the geodesy of the simulated GPS :mod:`.geo`; its configuration
is :mod:`.config`.
"""

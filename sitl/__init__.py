"""The MuJoCo SITL harness (builds on :mod:`companion` and :mod:`link_firmware_sim`).

* ``python -m sitl fly`` -- batch mode (:mod:`.runner`, :mod:`.fly`): physics, every link's firmware
  and the companion engine in one process on one clock, deterministic;
* ``python -m sitl launch`` -- fleet mode (:mod:`.fleet`): one vehicle process per link, the
  companion daemon(s), the harness in lockstep over PX4-style simulator links;
* the plant: :mod:`.model` (MuJoCo model generated from the config), :mod:`.rotor` (rotor/ESC
  dynamics), :mod:`.sensors`; the scenario schema :mod:`.scenario`; :mod:`.metrics`,
  :mod:`.steplog`, :mod:`.plots`; :mod:`.rendering` (MuJoCo's headless OpenGL, only for runs that render);
* :mod:`.synthetic` -- constraint-consistent chain motion without physics (the paper's sec. IV);
* :mod:`.bench` -- benchmarks that print figures.
"""

import os as _os

# MuJoCo takes its OpenGL backend from MUJOCO_GL at its first import. Nothing here renders unless a
# run asks for it (cameras, a video), so by default none is loaded: the command lines choose a
# headless one before MuJoCo is imported when the run renders (sitl.rendering.choose_backend), and
# so can a program that renders (call it before importing mujoco).
_os.environ.setdefault("MUJOCO_GL", "disable")

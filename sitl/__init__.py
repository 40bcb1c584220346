"""The MuJoCo SITL harness (builds on :mod:`companion` and :mod:`link_firmware_sim`).

* ``python -m sitl fly`` -- batch mode (:mod:`.runner`, :mod:`.fly`): physics, every link's firmware
  and the companion engine in one process on one clock, deterministic;
* ``python -m sitl launch`` -- fleet mode (:mod:`.fleet`): one vehicle process per link, the
  companion daemon(s), the harness in lockstep over PX4-style simulator links;
* the plant: :mod:`.model` (MuJoCo model generated from the config), :mod:`.rotor` (rotor/ESC
  dynamics), :mod:`.sensors`; the scenario schema :mod:`.scenario`; :mod:`.metrics`,
  :mod:`.steplog`, :mod:`.plots`;
* :mod:`.synthetic` -- constraint-consistent chain motion without physics (the paper's sec. IV);
* :mod:`.bench` -- benchmarks that print figures.
"""

import os as _os

# Cameras and videos render offscreen (sitl.camera, sitl.video): MuJoCo picks its OpenGL backend
# when it is first imported, so choose a headless one here, before any sitl module imports it.
# osmesa renders on the CPU (Debian: libosmesa6); set MUJOCO_GL=egl yourself for a GPU.
_os.environ.setdefault("MUJOCO_GL", "osmesa")

"""The MuJoCo SITL harness (builds on :mod:`companion` and :mod:`link_firmware_sim`).

* ``python -m sitl fly`` -- batch mode (:mod:`.runner`): physics, every link's firmware and the
  companion engine in one process on one clock, deterministic; it flies every scenario kind;
* ``python -m sitl launch`` -- fleet mode (:mod:`.fleet`): one vehicle process per link, the
  companion daemon(s), the harness in lockstep over PX4-style simulator links; the kinds with a
  fleet form;
* the scenarios: the schema :mod:`.scenario`; the kinds, each a registered task with public hooks
  (:mod:`.task`) on the batch runner: :mod:`.scenarios` (chain, wall push, PSPM jump, slung load);
* the plant shared by both modes: :mod:`.plant` (the MuJoCo model generated from the config,
  rotor/ESC dynamics, sensors, wind); its compiled kernels: :mod:`.kernels`;
* :mod:`.cameras` (rendering, cameras and markers, video, frames over Zenoh; :mod:`.cameras.rendering`
  chooses MuJoCo's headless OpenGL, only for runs that render);
* :mod:`.metrics`, :mod:`.steplog`, :mod:`.plots`: what a run measures and draws;
* :mod:`.synthetic` -- constraint-consistent chain motion without physics (the paper's sec. IV);
* :mod:`.bench` -- benchmarks that print figures.
"""

import os as _os

# MuJoCo takes its OpenGL backend from MUJOCO_GL at its first import. Nothing here renders unless a
# run asks for it (cameras, a video), so by default none is loaded: the command lines choose a
# headless one before MuJoCo is imported when the run renders (sitl.cameras.rendering.choose_backend),
# and so can a program that renders (call it before importing mujoco).
_os.environ.setdefault("MUJOCO_GL", "disable")

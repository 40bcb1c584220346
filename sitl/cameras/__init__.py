"""Cameras and markers in the simulator: what a scenario's ``[[cameras]]`` and ``[[markers]]``
put in the MuJoCo model, how their frames are rendered and where they go.

* :mod:`.config`: the ``[[cameras]]`` and ``[[markers]]`` schema (no OpenCV, no MuJoCo);
* :mod:`.scene`: the ``[scene]`` schema (ground, light, clutter) and its seeded draws (no OpenCV, no
  MuJoCo); :mod:`.backdrop`: the scene in the MJCF;
* :mod:`.photometry`: the light over time and each camera's sensor response (numpy only);
* :mod:`.rendering`: MuJoCo's headless OpenGL backend, chosen before MuJoCo loads, only for runs
  that render;
* :mod:`.rig`: the cameras rendered on the simulation clock, with latency, jitter and noise, and
  the markers' textures;
* :mod:`.flight`: a batch flight's cameras, vision log and video as tick hooks of the runner;
* :mod:`.vision_log`: every PnP method on every frame against the truth;
* :mod:`.video`: the flight's MP4;
* :mod:`.stream`: fleet mode: the frames published over Zenoh to the vision consumer.
"""

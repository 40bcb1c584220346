"""SITL harness: synthetic chain kinematics and sensors (``synthetic``), benchmarks (``bench``).

The MuJoCo physics harness arrives with the SITL issue; importing ``sitl`` loads no simulator.
"""

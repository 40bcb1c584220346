"""The vehicle model shared by every layer (pure numpy; :mod:`.dynamics` needs pinocchio).

* :mod:`.body` -- the skeleton's links (length, mass distribution, inertia), the cable joints, gravity;
* :mod:`.rotors` -- an ODAR link's rotor geometry (thesis Table 2.1) and rotor/ESC parameters;
* :mod:`.kinematics` -- the chain's forward kinematics for batches, its middle point, cable tension;
* :mod:`.dynamics` -- the chain's multibody model (pinocchio): kinematics, RNEA, cable forces.
"""

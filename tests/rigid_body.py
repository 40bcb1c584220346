"""One rigid link in closed loop without MuJoCo: the thesis's eq. 2.7 for controller tests."""

from __future__ import annotations

import numpy as np

from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat
from companion.skeleton.body import GRAVITY_M_S2


def rigid_body_step(p, v, R, w, U, inertia, dt, wrench_ext=None):
    """(2.7) for one link over ``dt``, semi-implicit Euler with an exact rotation update: ``U`` the
    rotors' wrench (force and torque, body frame), ``wrench_ext`` an external force (world) and
    torque (body); returns ``(p, v, R, w)``."""
    J = np.asarray(inertia.inertia_kgm2)
    f_ext, tau_ext = (np.zeros(3), np.zeros(3)) if wrench_ext is None else (wrench_ext[:3], wrench_ext[3:])
    a = (R @ U[:3] + f_ext) / inertia.mass_kg - np.array([0.0, 0.0, GRAVITY_M_S2])
    wdot = (U[3:] + tau_ext - np.cross(w, J * w)) / J
    v = v + dt * a
    w = w + dt * wdot
    return p + dt * v, v, R @ quat_to_rotmat(quat_from_rotvec(w * dt)), w

"""The body rate of a link whose gyro is stale: its rigid body turned by the torque its rotors were
commanded, corrected by the attitude references (pure).

While the gyro is stale nothing measures the rate that eq. 1's damping term needs. Differencing the
attitude estimate gives it late and noisy (the references' noise over their 20 ms period), and an
end link, whose cables pull at one tip only, swings over on it. This observer predicts the rate from
Euler's equation instead,

    J dw/dt = tau_act - w x J w + J a,

with ``tau_act`` the commanded torque through the rotors' first-order lag (the ESC time constant)
and ``a`` the angular acceleration of everything else (the cables' and the joints' torques, drag),
and corrects attitude, rate and ``a`` by each attitude reference: per body axis a Kalman filter on
(attitude error, rate, ``a``), ``a`` a random walk. At the start the rate is unknown (the gyro has
repeated one sample for a while: :data:`~.imu_health.STALE_S`) and ``a`` is what held the link
still, ``-tau_act / J``: the cables' torque that the rotors were balancing.
"""

from __future__ import annotations

import numpy as np

from companion.estimation.so3 import quat_conj, quat_mul, quat_from_rotvec, quat_to_rotvec

__all__ = ["RATE_ACCEL_NOISE", "DISTURBANCE_NOISE", "START_RATE_VAR", "StaleGyroRate"]

#: density of the rate's model error [rad^2/s^3]: thrust noise and the rotors' lag mis-modelled
RATE_ACCEL_NOISE = 0.3
#: density of the other torques' change [rad^2/s^5]: the cables' pull changing as the chain moves
DISTURBANCE_NOISE = 4.0
#: the rate's variance at the start [rad^2/s^2]: unknown, about a radian per second
START_RATE_VAR = 1.0
#: the variance of ``a`` at the start [rad^2/s^4]
START_DISTURBANCE_VAR = 4.0


class StaleGyroRate:
    """The observer of the module docstring for a link of principal inertia ``inertia_kgm2`` [kg m^2]
    whose rotors reach a commanded torque with time constant ``actuator_time_constant_s``; the
    attitude references' variance per body axis ``ref_var_rad2`` (roll, pitch, yaw) [rad^2].

    :meth:`start` at the first stale tick, :meth:`predict` at every stale tick, :meth:`update` at
    each attitude reference while stale; :attr:`rate_b_rad_s` is the rate for the controller and the
    attitude's propagation. :attr:`running` until :meth:`stop`.
    """

    def __init__(self, inertia_kgm2, actuator_time_constant_s: float, ref_var_rad2):
        self.J = np.asarray(inertia_kgm2, dtype=float).reshape(3)
        if not np.all(self.J > 0):
            raise ValueError(f"inertia_kgm2 must be positive, got {inertia_kgm2!r}")
        if not actuator_time_constant_s >= 0.0:
            raise ValueError(f"actuator_time_constant_s must be >= 0, got {actuator_time_constant_s!r}")
        self.tau_s = float(actuator_time_constant_s)
        self.R = np.asarray(ref_var_rad2, dtype=float).reshape(3)
        if not np.all(self.R > 0):
            raise ValueError(f"ref_var_rad2 must be positive, got {ref_var_rad2!r}")
        self.running = False
        self.q_wxyz = np.array([1.0, 0.0, 0.0, 0.0])  # the observer's attitude, body to world
        self.rate_b_rad_s = np.zeros(3)
        self.accel_b_rad_s2 = np.zeros(3)  # ``a``
        self.torque_b_nm = np.zeros(3)  # ``tau_act``
        self.P = np.zeros((3, 3, 3))  # per axis: (attitude error, rate, a)
        self.updates = 0

    def start(self, q_wxyz, torque_cmd_b_nm) -> None:
        """The first stale tick: the attitude estimate ``q_wxyz`` and the commanded torque (reached:
        the link was flying steadily)."""
        self.running = True
        self.q_wxyz = np.array(q_wxyz, dtype=float)
        self.torque_b_nm = np.array(torque_cmd_b_nm, dtype=float)
        self.rate_b_rad_s = np.zeros(3)
        self.accel_b_rad_s2 = -self.torque_b_nm / self.J
        self.P = np.zeros((3, 3, 3))
        self.P[:, 0, 0] = self.R
        self.P[:, 1, 1] = START_RATE_VAR
        self.P[:, 2, 2] = START_DISTURBANCE_VAR
        self.updates = 0

    def stop(self) -> None:
        """The gyro is back."""
        self.running = False

    def predict(self, torque_cmd_b_nm, dt_s: float) -> np.ndarray:
        """One tick of ``dt_s`` under the commanded torque [N m]; the rate [rad/s] at its end."""
        dt = float(dt_s)
        lag = 1.0 if self.tau_s == 0.0 else dt / (self.tau_s + dt)
        self.torque_b_nm = self.torque_b_nm + lag * (np.asarray(torque_cmd_b_nm, dtype=float) - self.torque_b_nm)
        w, J = self.rate_b_rad_s, self.J
        wdot = (self.torque_b_nm - np.cross(w, J * w)) / J + self.accel_b_rad_s2
        self.rate_b_rad_s = w + dt * wdot
        self.q_wxyz = quat_mul(self.q_wxyz, quat_from_rotvec(self.rate_b_rad_s * dt))
        self.q_wxyz /= np.linalg.norm(self.q_wxyz)
        F = np.array([[1.0, dt, 0.0], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
        Q = np.diag([0.0, RATE_ACCEL_NOISE * dt, DISTURBANCE_NOISE * dt])
        self.P = F @ self.P @ F.T + Q
        return self.rate_b_rad_s

    def update(self, q_ref_wxyz) -> None:
        """An attitude reference (body to world): attitude, rate and ``a`` corrected per body axis."""
        e = quat_to_rotvec(quat_mul(quat_conj(self.q_wxyz), np.asarray(q_ref_wxyz, dtype=float)))  # body frame
        S = self.P[:, 0, 0] + self.R
        K = self.P[:, :, 0] / S[:, None]  # (axis, state)
        dx = K * e[:, None]
        self.q_wxyz = quat_mul(self.q_wxyz, quat_from_rotvec(dx[:, 0]))
        self.q_wxyz /= np.linalg.norm(self.q_wxyz)
        self.rate_b_rad_s = self.rate_b_rad_s + dx[:, 1]
        self.accel_b_rad_s2 = self.accel_b_rad_s2 + dx[:, 2]
        self.P = self.P - K[:, :, None] * self.P[:, 0, :][:, None, :]
        self.updates += 1

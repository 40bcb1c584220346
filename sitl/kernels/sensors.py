"""The IMU's compiled kernel: :meth:`sitl.plant.sensors.LinkSensors.imu`'s numpy code is its
specification (what runs without numba, and what ``tests/unit/test_fast_paths.py`` compares it
with, bit for bit).

A leaf: it imports numpy and the project's jit switch only.
"""

from __future__ import annotations

import numpy as np

from companion.kernels.jit import jit

__all__ = ["imu_kernel"]


@jit
def imu_kernel(draw, force_b, omega_b, accel_bias, gyro_bias, scales):
    """One IMU sample of every link from one draw of standard normals ``draw`` (4, n, 3): the
    accelerometer's and the gyro's bias random-walk steps (``accel_bias``, ``gyro_bias`` (n, 3),
    updated in place), then the gyro's and the accelerometer's white noise on the true body rate
    ``omega_b`` and specific force ``force_b`` (n, 3); ``scales`` ``(accel_walk, gyro_walk,
    gyro_std, accel_std)``, the walks already times sqrt(dt). Returns new (gyro, accel) arrays,
    each operation as the specification orders it."""
    accel_walk, gyro_walk, gyro_std, accel_std = scales
    n = force_b.shape[0]
    gyro = np.empty((n, 3))
    accel = np.empty((n, 3))
    for i in range(n):
        for k in range(3):
            accel_bias[i, k] += accel_walk * draw[0, i, k]
            gyro_bias[i, k] += gyro_walk * draw[1, i, k]
            gyro[i, k] = (omega_b[i, k] + gyro_bias[i, k]) + gyro_std * draw[2, i, k]
            accel[i, k] = (force_b[i, k] + accel_bias[i, k]) + accel_std * draw[3, i, k]
    return gyro, accel

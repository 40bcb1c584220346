"""The EKF as one simulated Pixhawk runs it: :class:`LinkEkf`, the state and its counters, over
the functional core of :mod:`.ekf`, with the one dispatch between that numpy specification and the
compiled kernels (:mod:`link_firmware_sim.kernels.ekf`): :func:`predict` and :func:`fuse`.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np

from companion.estimation.so3 import attitude_error
from companion.kernels.jit import ENABLED

from ..kernels.ekf import attitude_update_kernel, ekf_predict_kernel, update_block_kernel, update_rows_kernel
from ..kernels.layouts import EKF_ATT_COV, EKF_BARO_DENSITY, EKF_DENSITIES, EKF_GATE_SIGMA, EKF_GRAVITY_W, EKF_SIZE
from .ekf import (GRAVITY_W_M_S2, Measurement, as_covariance, attitude_measurement, attitude_variance,
                  baro_measurement, ekf_add_baro_offset, ekf_init, ekf_predict, ekf_remove_baro_offset,
                  ekf_reset_attitude, ekf_reset_position, ekf_reset_velocity, heading_measurement, innovation_test,
                  kalman_apply, mag_heading_measurement, position_measurement, sckf_view, velocity_measurement)
from .ekf_config import E_P, NE, NX_BARO, X_P, X_Q, X_V, EkfConfig, UpdateInfo

__all__ = ["NO_GYRO_ATT_RAD2_S", "NO_ACCEL_VEL_M2_S3", "ekf_parameters", "predict", "fuse", "LinkEkf"]

#: the attitude's process noise density while no gyro is used [rad^2/s]: in the 20 ms between two
#: 50 Hz attitude references its variance grows by half the reference's (0.04 rad^2)
NO_GYRO_ATT_RAD2_S = 1.0
#: the velocity's process noise density while the specific force is modelled, not measured (the
#: accelerometer stale) [(m/s)^2/s]: 1 m/s^2 of model error over a second
NO_ACCEL_VEL_M2_S3 = 1.0


@lru_cache(maxsize=32)
def _parameters(config: EkfConfig) -> np.ndarray:
    par = np.zeros(EKF_SIZE)
    par[EKF_DENSITIES:EKF_DENSITIES + NE] = config.noise.densities
    par[EKF_BARO_DENSITY] = config.noise.baro_bias_m2_s
    par[EKF_GRAVITY_W:EKF_GRAVITY_W + 3] = GRAVITY_W_M_S2
    par[EKF_GATE_SIGMA] = config.gate_sigma
    par[EKF_ATT_COV:EKF_ATT_COV + 9] = as_covariance(attitude_variance(config), 3).ravel()
    par.setflags(write=False)
    return par


def ekf_parameters(config: EkfConfig) -> np.ndarray:
    """What the kernels read of ``config`` (``EKF_*``): the process noise densities, the barometer
    offset's, gravity, the gate and the attitude reference's covariance (a new array)."""
    return _parameters(config).copy()


def predict(x, P, gyro_b_rad_s, accel_b_m_s2, dt_s: float, config: EkfConfig, compiled: bool,
            par: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~.ekf.ekf_predict` with ``config``'s process noise, by its kernel when ``compiled``
    (``par``: :func:`ekf_parameters` of ``config``)."""
    if not compiled:
        return ekf_predict(x, P, gyro_b_rad_s, accel_b_m_s2, dt_s, config.noise)
    if not dt_s > 0.0:
        raise ValueError(f"dt_s must be positive, got {dt_s!r}")
    return ekf_predict_kernel(x, P, np.asarray(gyro_b_rad_s, dtype=float), np.asarray(accel_b_m_s2, dtype=float),
                              float(dt_s), ekf_parameters(config) if par is None else par)


def fuse(x, P, m: Measurement | None, gate_sigma: float, compiled: bool):
    """The gated Joseph-form update of the measurement ``m`` (:func:`~.ekf.kalman_apply`), by the
    kernels when ``compiled``: ``(x, P, UpdateInfo)``."""
    if not compiled or m is None:
        return kalman_apply(x, P, m, gate_sigma)
    if m.block is not None:
        xn, Pn, accepted, test = update_block_kernel(x, P, m.r, m.block.start, m.Rm, float(gate_sigma))
    else:
        xn, Pn, accepted, test = update_rows_kernel(x, P, m.r, m.H, m.Rm, float(gate_sigma))
    return (xn, Pn, UpdateInfo(True, m.r, test)) if accepted else (x, P, UpdateInfo(False, m.r, test))


class LinkEkf:
    """Stateful wrapper around the functional EKF, as run on one simulated Pixhawk.

    Counts accepted and rejected (gated) measurements per kind. ``compiled`` (default: when numba
    is installed and not turned off, :data:`~companion.kernels.jit.ENABLED`) runs the kernels of
    :mod:`link_firmware_sim.kernels.ekf` instead of the numpy specification (:func:`predict` and
    :func:`fuse`, the one dispatch; same numbers to rounding, ``tests/unit/test_fast_paths.py``).
    """

    def __init__(self, p_w_m, v_w_m_s, q_wxyz, config: EkfConfig = EkfConfig(), compiled: bool | None = None):
        self.config = config
        self.compiled = ENABLED if compiled is None else bool(compiled)
        #: the kernels' parameters (``EKF_*`` of :mod:`link_firmware_sim.kernels.layouts`)
        self.par = ekf_parameters(config)
        self.x, self.P = ekf_init(p_w_m, v_w_m_s, q_wxyz, config)
        self.last_gyro_b_rad_s = np.zeros(3)
        kinds = ("pos", "vel", "att", "heading", "baro", "mag", "ext_pos")
        self.accepted: dict[str, int] = dict.fromkeys(kinds, 0)
        self.rejected: dict[str, int] = dict.fromkeys(kinds, 0)
        #: state resets (discontinuities), reported as the link state's reset_counter
        self.resets = 0
        #: per kind, measurements rejected since the last one accepted (a fused call's count of
        #: attitude references, when it accepted none, adds to it)
        self.rejected_run: dict[str, int] = dict.fromkeys(kinds, 0)

    def predict(self, gyro_b_rad_s, accel_b_m_s2, dt_s: float) -> None:
        self.x, self.P = predict(self.x, self.P, gyro_b_rad_s, accel_b_m_s2, dt_s, self.config, self.compiled,
                                 self.par)
        self.last_gyro_b_rad_s = np.asarray(gyro_b_rad_s, dtype=float).copy()

    def predict_stale(self, gyro_b_rad_s, accel_b_m_s2, dt_s: float, gyro_stale: bool, accel_stale: bool) -> None:
        """:meth:`predict` with a stale sensor. No rotation measured (``gyro_stale``):
        ``gyro_b_rad_s`` is the caller's model of it (a rate as a gyro reads it, bias included), the
        attitude's density :data:`NO_GYRO_ATT_RAD2_S` so that the attitude reference carries it.
        No specific force measured (``accel_stale``): ``accel_b_m_s2`` is the caller's model of it
        (the commanded thrust's), the velocity's density :data:`NO_ACCEL_VEL_M2_S3` so that the
        GPS and the companion's corrections carry it."""
        noise = self.config.noise
        if gyro_stale:
            noise = replace(noise, att_rad2_s=NO_GYRO_ATT_RAD2_S, att_yaw_rad2_s=None)
        if accel_stale:
            noise = replace(noise, vel_m2_s3=NO_ACCEL_VEL_M2_S3)
        self.x, self.P = ekf_predict(self.x, self.P, gyro_b_rad_s, accel_b_m_s2, dt_s, noise)
        self.last_gyro_b_rad_s = np.asarray(gyro_b_rad_s, dtype=float).copy()

    def _fuse(self, kind: str, m: Measurement | None) -> UpdateInfo:
        return self._record(kind, fuse(self.x, self.P, m, self.config.gate_sigma, self.compiled))

    def _record(self, kind: str, result) -> UpdateInfo:
        self.x, self.P, info = result
        (self.accepted if info.accepted else self.rejected)[kind] += 1
        self.rejected_run[kind] = 0 if info.accepted else self.rejected_run[kind] + 1
        return info

    def update_position(self, pos_w_m) -> UpdateInfo:
        cfg = self.config
        return self._fuse("pos", position_measurement(self.x, pos_w_m, cfg.gps_pos_var_m2))

    def update_external_position(self, pos_w_m, var_m2: float) -> UpdateInfo:
        """An external position (not the GPS: :mod:`.correction_aid`) of variance ``var_m2`` per
        axis, through the gate."""
        return self._fuse("ext_pos", position_measurement(self.x, pos_w_m, var_m2))

    def position_test_ratio(self, pos_w_m) -> float:
        """The gate's test ratio of a position fix (above 1: it would be rejected), no update."""
        S = self.P[E_P, E_P] + as_covariance(self.config.gps_pos_var_m2, 3)
        r = np.asarray(pos_w_m, dtype=float) - self.x[X_P]
        return innovation_test(r, np.diag(S), self.config.gate_sigma)

    def reset_position(self, pos_w_m, var_m2: float | None = None) -> None:
        """Reset the position to a fix of variance ``var_m2`` per axis (default: the GPS's); the
        barometer is referenced again at its next sample."""
        self.x, self.P = ekf_remove_baro_offset(self.x, self.P)
        self.x, self.P = ekf_reset_position(self.x, self.P, pos_w_m,
                                            self.config.gps_pos_var_m2 if var_m2 is None else var_m2)
        self.resets += 1

    @property
    def baro_referenced(self) -> bool:
        """The barometer's offset is a state (after its first sample)."""
        return len(self.x) == NX_BARO

    def update_baro(self, baro_height_m: float, ground_effect: bool = False) -> UpdateInfo:
        """A barometric height [m]: the first one references the barometer (counted as accepted,
        innovation 0), the others update ``z + b``; ``ground_effect``: apply the deadzone."""
        cfg = self.config
        if not self.baro_referenced:
            self.x, self.P = ekf_add_baro_offset(self.x, self.P, baro_height_m, cfg.baro_var_m2)
            self.accepted["baro"] += 1
            return UpdateInfo(True, np.array([0.0]), 0.0)
        deadzone = cfg.baro_ground_effect_deadzone_m if ground_effect else 0.0
        return self._fuse("baro", baro_measurement(self.x, baro_height_m, cfg.baro_var_m2, deadzone))

    def update_mag(self, mag_b_gauss) -> UpdateInfo:
        """A magnetometer sample (body FLU) as a heading (:func:`ekf_update_mag_heading`)."""
        cfg = self.config
        return self._fuse("mag", mag_heading_measurement(self.x, mag_b_gauss, cfg.mag_declination_rad,
                                                         cfg.mag_heading_var_rad2))

    def update_velocity(self, vel_w_m_s) -> UpdateInfo:
        cfg = self.config
        return self._fuse("vel", velocity_measurement(self.x, vel_w_m_s, cfg.gps_vel_var_m2_s2))

    def update_attitude(self, q_meas_wxyz) -> UpdateInfo:
        cfg = self.config
        if self.compiled:  # the measurement model too in one kernel (50 Hz per link)
            q = np.asarray(q_meas_wxyz, dtype=float)
            if q.shape != (4,):
                attitude_measurement(self.x, q, 0.0)  # raises the specification's error
            x, P, status, test, r = attitude_update_kernel(self.x, self.P, q, self.par)
            if status < 0:
                attitude_measurement(self.x, q, 0.0)  # raises the specification's error
            return self._record("att", (x, P, UpdateInfo(status == 1, r, test)))
        return self._fuse("att", attitude_measurement(self.x, q_meas_wxyz, attitude_variance(cfg)))

    def count_attitude(self, accepted: int, rejected: int) -> None:
        """Attitude references the fused ticks' kernels fused, counted as :meth:`update_attitude`
        counts them, the rejected ones after the accepted ones (a kernel's run of ticks ends at a
        rejection)."""
        self.accepted["att"] += accepted
        self.rejected["att"] += rejected
        self.rejected_run["att"] = rejected if accepted else self.rejected_run["att"] + rejected

    @property
    def attitude_reset_due(self) -> bool:
        """``att_reset_rejections`` attitude references in a row rejected: the next one resets
        the attitude (:meth:`reset_attitude`)."""
        n = self.config.att_reset_rejections
        return n > 0 and self.rejected_run["att"] >= n

    @property
    def velocity_reset_due(self) -> bool:
        """``vel_reset_rejections`` GPS velocities in a row rejected: the next one resets the
        velocity (:meth:`reset_velocity`)."""
        n = self.config.vel_reset_rejections
        return n > 0 and self.rejected_run["vel"] >= n

    def reset_attitude(self, q_wxyz) -> float:
        """Reset the attitude to the reference ``q_wxyz`` (:func:`~.ekf.ekf_reset_attitude`, with the
        reference's variance); returns the jump [rad]."""
        before = self.x[X_Q].copy()
        self.x, self.P = ekf_reset_attitude(self.x, self.P, q_wxyz, attitude_variance(self.config))
        self.resets += 1
        self.rejected_run["att"] = 0
        return float(np.linalg.norm(attitude_error(self.x[X_Q], before)))

    def reset_velocity(self, vel_w_m_s) -> float:
        """Reset the velocity to the GPS velocity ``vel_w_m_s`` (:func:`~.ekf.ekf_reset_velocity`,
        with its variance); returns the jump [m/s]."""
        before = self.x[X_V].copy()
        self.x, self.P = ekf_reset_velocity(self.x, self.P, vel_w_m_s, self.config.gps_vel_var_m2_s2)
        self.resets += 1
        self.rejected_run["vel"] = 0
        return float(np.linalg.norm(self.x[X_V] - before))

    def update_heading(self, yaw_rad: float) -> UpdateInfo:
        cfg = self.config
        return self._fuse("heading", heading_measurement(self.x, yaw_rad, cfg.heading_var_rad2))

    @property
    def p_w_m(self) -> np.ndarray:
        return self.x[X_P].copy()

    @property
    def v_w_m_s(self) -> np.ndarray:
        return self.x[X_V].copy()

    @property
    def q_wxyz(self) -> np.ndarray:
        return self.x[X_Q].copy()

    def sckf_view(self):
        """``(p, v, q, omega_b, P9)`` for the companion (see :func:`sckf_view`)."""
        return sckf_view(self.x, self.P, self.last_gyro_b_rad_s, self.config.gps_bias_var_m2)

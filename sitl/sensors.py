"""Seeded per-link sensors for the MuJoCo harness: IMU, GPS and an attitude/heading reference.

Every link carries the same suite at its centre (the Pixhawk and GPS of the real LASDRA):

* IMU: the simulator's specific force and body rate plus white noise and a bias random walk
  (each link starts with a random bias drawn from ``*_bias_init_std``);
* GPS: position and velocity with white noise and, on position, a slow drift below 0.1 Hz of
  about ``drift_amp_m`` amplitude (the paper's sec. IV drift), modelled as a sum of
  ``drift_components`` sinusoids with random axes, frequencies and phases so that every link's
  drift covers the band (a single sinusoid per link, as in the Table II benchmark, makes each
  link's error depend on the one frequency it drew: the EKF's drift-free GPS velocity removes
  much of a 0.1 Hz drift but little of a 0.02 Hz one); and/or, as a real receiver errs, first-
  order Gauss-Markov position biases: one per link (multipath, the receiver's own tracking) and
  one common to all links (atmosphere, ephemeris, satellite clocks: what receivers a few metres
  apart share), plus a Gauss-Markov velocity bias that is not the derivative of the position's
  (profiles ``m8`` and ``rtk`` below);
* attitude/heading reference (an AHRS: gravity and magnetometer): a measured attitude whose
  world-frame error has tilt and heading white noise and a slow drift.

Named profiles (:data:`PROFILES`) give consistent defaults; scenario configs pick one and
may override fields. All noise comes from one ``numpy.random.Generator``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from companion.configfile import require_nonnegative
from companion.estimation.so3 import quat_from_rotvec, quat_mul
from sitl.synthetic import SensorModel, draw_drifts

__all__ = ["ImuNoise", "GpsNoise", "AttitudeRefNoise", "SensorSuite", "PROFILES", "LinkSensors"]


@dataclass(frozen=True)
class ImuNoise:
    """Per-sample white noise [m/s^2, rad/s], bias random walks [per sqrt(s)], initial biases."""

    accel_std_m_s2: float = 0.05
    gyro_std_rad_s: float = 0.005
    accel_bias_rw_m_s2_sqrt_s: float = 1e-3
    gyro_bias_rw_rad_s_sqrt_s: float = 1e-4
    accel_bias_init_std_m_s2: float = 0.05
    gyro_bias_init_std_rad_s: float = 0.003

    def __post_init__(self) -> None:
        require_nonnegative(self, *self.__dataclass_fields__)


@dataclass(frozen=True)
class GpsNoise:
    """GPS white noise (horizontal, vertical, velocity) and the slow position drift."""

    pos_horizontal_std_m: float = 0.15
    pos_vertical_std_m: float = 0.3
    vel_std_m_s: float = 0.05
    drift_amp_m: float = 0.5
    drift_freq_min_hz: float = 0.02
    drift_freq_max_hz: float = 0.1
    drift_components: int = 4
    #: per-link Gauss-Markov position bias: stationary std per axis and time constant
    bias_horizontal_std_m: float = 0.0
    bias_vertical_std_m: float = 0.0
    bias_time_constant_s: float = 60.0
    #: the same, common to every link
    common_horizontal_std_m: float = 0.0
    common_vertical_std_m: float = 0.0
    common_time_constant_s: float = 300.0
    #: per-link Gauss-Markov velocity bias
    vel_bias_std_m_s: float = 0.0
    vel_bias_time_constant_s: float = 10.0

    def __post_init__(self) -> None:
        require_nonnegative(self, "pos_horizontal_std_m", "pos_vertical_std_m", "vel_std_m_s", "drift_amp_m",
                            "bias_horizontal_std_m", "bias_vertical_std_m", "common_horizontal_std_m",
                            "common_vertical_std_m", "vel_bias_std_m_s")
        for name in ("bias_time_constant_s", "common_time_constant_s", "vel_bias_time_constant_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.drift_components < 1:
            raise ValueError(f"drift_components must be >= 1, got {self.drift_components}")
        if not 0 < self.drift_freq_min_hz <= self.drift_freq_max_hz < 1.0:
            raise ValueError(
                f"drift_freq_min_hz must be in (0, drift_freq_max_hz], drift_freq_max_hz below 1 Hz; "
                f"got {self.drift_freq_min_hz}, {self.drift_freq_max_hz}"
            )


@dataclass(frozen=True)
class AttitudeRefNoise:
    """Attitude reference: tilt and heading white noise [rad] and a slow drift amplitude [rad]."""

    tilt_std_rad: float = math.radians(1.0)
    heading_std_rad: float = math.radians(3.0)
    drift_amp_rad: float = math.radians(2.0)

    def __post_init__(self) -> None:
        require_nonnegative(self, *self.__dataclass_fields__)


@dataclass(frozen=True)
class SensorSuite:
    """One named profile of the three sensors."""

    imu: ImuNoise = field(default_factory=ImuNoise)
    gps: GpsNoise = field(default_factory=GpsNoise)
    attitude: AttitudeRefNoise = field(default_factory=AttitudeRefNoise)


#: ``outdoor``: Pixhawk-class MEMS IMU, u-blox M8-class GPS with the paper's 0.5 m drift, an
#: AHRS with 1 deg tilt / 3 deg heading noise. ``paper``: the paper's Table I measurement
#: noise (variance 0.1 on GPS position and velocity, 0.01 per quaternion component) with its
#: 0.5 m / 5 deg drifts. ``ideal``: no noise, no drift, no bias (controller tests).
#: ``m8``: a standalone u-blox M8-class receiver as it errs: the data sheet's 2.5 m CEP
#: horizontal (NEO-M8N, GPS+GLONASS; CEP 2.5 m is about 2.1 m std per axis) split into a
#: common-mode bias that nearby receivers share (1.8 m per axis, 5 min: ionosphere,
#: troposphere, ephemeris and clock errors change over minutes) and a per-receiver bias
#: (0.8 m per axis, 60 s: multipath and tracking), vertical 1.5x; 0.1 / 0.2 m white noise;
#: velocity 0.05 m/s (the data sheet's speed accuracy) white plus 0.02 m/s correlated over
#: 10 s. ``rtk``: an RTK-fixed receiver (u-blox ZED-F9P: 0.01 m + 1 ppm CEP horizontal): 1 cm
#: per-link bias over 30 s, no common mode left, 5 / 10 mm white, 0.02 m/s velocity.
#: Both keep ``outdoor``'s IMU and attitude reference.
PROFILES: dict[str, SensorSuite] = {
    "outdoor": SensorSuite(),
    "paper": SensorSuite(
        gps=GpsNoise(
            pos_horizontal_std_m=math.sqrt(0.1), pos_vertical_std_m=math.sqrt(0.1), vel_std_m_s=math.sqrt(0.1)
        ),
        attitude=AttitudeRefNoise(tilt_std_rad=0.2, heading_std_rad=0.2, drift_amp_rad=math.radians(5.0)),
    ),
    "m8": SensorSuite(
        gps=GpsNoise(pos_horizontal_std_m=0.1, pos_vertical_std_m=0.2, vel_std_m_s=0.05, drift_amp_m=0.0,
                     bias_horizontal_std_m=0.8, bias_vertical_std_m=1.2, bias_time_constant_s=60.0,
                     common_horizontal_std_m=1.8, common_vertical_std_m=2.7, common_time_constant_s=300.0,
                     vel_bias_std_m_s=0.02, vel_bias_time_constant_s=10.0),
    ),
    "rtk": SensorSuite(
        gps=GpsNoise(pos_horizontal_std_m=0.005, pos_vertical_std_m=0.01, vel_std_m_s=0.02, drift_amp_m=0.0,
                     bias_horizontal_std_m=0.01, bias_vertical_std_m=0.015, bias_time_constant_s=30.0),
    ),
    "ideal": SensorSuite(
        imu=ImuNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        gps=GpsNoise(0.0, 0.0, 0.0, 0.0),
        attitude=AttitudeRefNoise(0.0, 0.0, 0.0),
    ),
}


class LinkSensors:
    """The sensors of all ``n`` links of one skeleton, vectorised over links."""

    def __init__(self, suite: SensorSuite, n_links: int, rng: np.random.Generator):
        self.suite = suite
        self.n = n_links
        self.rng = rng
        imu = suite.imu
        self.accel_bias = imu.accel_bias_init_std_m_s2 * rng.normal(size=(n_links, 3))
        self.gyro_bias = imu.gyro_bias_init_std_rad_s * rng.normal(size=(n_links, 3))
        drift_model = replace(
            SensorModel(), drift_freq_min_hz=suite.gps.drift_freq_min_hz, drift_freq_max_hz=suite.gps.drift_freq_max_hz
        )
        self.pos_drift = draw_drifts(rng, n_links, drift_model, suite.gps.drift_components)
        self.att_drift = draw_drifts(rng, n_links, drift_model, suite.gps.drift_components)
        g = suite.gps
        # Gauss-Markov biases, drawn from their stationary distributions (only when the profile has
        # them: the other profiles' random sequences stay as they were)
        self._gm = []  # (state (n or 1, 3), std (3,), time constant)
        for std, tau, rows in ((np.array([g.bias_horizontal_std_m] * 2 + [g.bias_vertical_std_m]), g.bias_time_constant_s, n_links),
                               (np.array([g.common_horizontal_std_m] * 2 + [g.common_vertical_std_m]), g.common_time_constant_s, 1)):
            if np.any(std > 0):
                self._gm.append((std * rng.normal(size=(rows, 3)), std, tau))
        self._vel_bias = g.vel_bias_std_m_s * rng.normal(size=(n_links, 3)) if g.vel_bias_std_m_s > 0 else None
        self._gps_t: float | None = None

    def imu(self, specific_force_b: np.ndarray, omega_b: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(gyro, accel), each (n, 3) body frame, from the true specific force and body rate."""
        imu = self.suite.imu
        rng = self.rng
        self.accel_bias += imu.accel_bias_rw_m_s2_sqrt_s * math.sqrt(dt_s) * rng.normal(size=(self.n, 3))
        self.gyro_bias += imu.gyro_bias_rw_rad_s_sqrt_s * math.sqrt(dt_s) * rng.normal(size=(self.n, 3))
        noise = rng.normal(size=(2, self.n, 3))
        gyro = omega_b + self.gyro_bias + imu.gyro_std_rad_s * noise[0]
        accel = specific_force_b + self.accel_bias + imu.accel_std_m_s2 * noise[1]
        return gyro, accel

    def gps(self, t_s: float, p_w: np.ndarray, v_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity), each (n, 3) world frame."""
        g = self.suite.gps
        std = np.array([g.pos_horizontal_std_m, g.pos_horizontal_std_m, g.pos_vertical_std_m])
        noise = self.rng.normal(size=(2, self.n, 3))
        pos = p_w + self.pos_drift.at(t_s, g.drift_amp_m) + std * noise[0]
        vel = v_w + g.vel_std_m_s * noise[1]
        if self._gm or self._vel_bias is not None:
            dt = 0.0 if self._gps_t is None else max(t_s - self._gps_t, 0.0)
            self._gps_t = t_s
            for k, (state, sd, tau) in enumerate(self._gm):
                a = math.exp(-dt / tau)
                state = a * state + math.sqrt(1.0 - a * a) * sd * self.rng.normal(size=state.shape)
                self._gm[k] = (state, sd, tau)
                pos = pos + state  # (n, 3) per link, or (1, 3) common to all
            if self._vel_bias is not None:
                a = math.exp(-dt / g.vel_bias_time_constant_s)
                self._vel_bias = a * self._vel_bias + math.sqrt(1.0 - a * a) * g.vel_bias_std_m_s * self.rng.normal(
                    size=self._vel_bias.shape)
                vel = vel + self._vel_bias
        return pos, vel

    def attitude(self, t_s: float, q_wxyz: np.ndarray) -> np.ndarray:
        """(n, 4) measured attitude: world-frame error rotation (drift + noise) applied on the left."""
        a = self.suite.attitude
        std = np.array([a.tilt_std_rad, a.tilt_std_rad, a.heading_std_rad])
        error = self.att_drift.at(t_s, a.drift_amp_rad) + std * self.rng.normal(size=(self.n, 3))
        return quat_mul(quat_from_rotvec(error), q_wxyz)

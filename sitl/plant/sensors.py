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
  world-frame error has tilt and heading white noise and a slow drift;
* optional barometer (:class:`BaroNoise`): the height above the origin as a pressure altitude,
  with white noise, a first-order Gauss-Markov drift (the sensor's warm-up and the weather) and
  the rotor downwash's ground effect (the barometer reads low near the ground while the rotors
  blow: their over-pressure);
* optional magnetometer (:class:`MagNoise`): the earth's field
  (:data:`~link_firmware_sim.geo.MAG_FIELD_NED_GAUSS`) plus a constant local disturbance per link
  (world frame: ground anomalies, the link's own iron and currents as calibration leaves them), in
  the body frame, with white noise.

The barometer and the magnetometer are off in the profiles that do not name them
(``SensorSuite.baro`` / ``.mag`` ``None``): those profiles draw exactly the random numbers they
drew before, so their flights and figures are unchanged.

Named profiles (:data:`PROFILES`) give consistent defaults; scenario configs pick one and
may override fields. All noise comes from one ``numpy.random.Generator``.

The numpy code of :meth:`LinkSensors.imu` is the specification; with numba installed its
arithmetic after the draw runs as :func:`sitl.kernels.sensors.imu_kernel` (the same numbers bit for
bit, ``tests/unit/test_fast_paths.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from companion.configfile import require_nonnegative
from companion.estimation.so3 import quat_from_rotvec, quat_mul, quat_to_rotmat
from companion.kernels.jit import ENABLED as _COMPILED_DEFAULT
from companion.mavlink.frames import enu_ned
from companion.skeleton.body import GRAVITY_M_S2
from link_firmware_sim.geo import MAG_FIELD_NED_GAUSS
from sitl.kernels.sensors import imu_kernel
from sitl.synthetic import SensorModel, draw_drifts

__all__ = ["ImuNoise", "GpsNoise", "AttitudeRefNoise", "BaroNoise", "MagNoise", "SensorSuite", "PROFILES",
           "LinkSensors", "MAG_FIELD_ENU_GAUSS", "downwash_fraction", "warm_up"]

#: The earth's field of the simulated world in the simulator's frame (ENU, gauss).
MAG_FIELD_ENU_GAUSS = enu_ned(MAG_FIELD_NED_GAUSS)


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
class BaroNoise:
    """Barometric height [m]: white noise, a first-order Gauss-Markov drift and the ground effect.

    The drift (stationary std ``drift_std_m``, time constant ``drift_time_constant_s``) stands for
    what a temperature-compensated MEMS barometer still does over a flight: warm-up drift and
    the weather's pressure changes. The ground effect: with the rotors carrying the link, their
    downwash's over-pressure makes the barometer read ``ground_effect_m`` low at the ground,
    fading linearly to nothing at ``ground_effect_height_m`` above it (the link centre's height;
    scaled by the rotors' thrust over the link's weight, capped at 1: nothing with the rotors off).
    """

    height_std_m: float = 0.1
    drift_std_m: float = 0.3
    drift_time_constant_s: float = 300.0
    ground_effect_m: float = 0.5
    ground_effect_height_m: float = 1.0

    def __post_init__(self) -> None:
        require_nonnegative(self, "height_std_m", "drift_std_m", "ground_effect_m")
        for name in ("drift_time_constant_s", "ground_effect_height_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass(frozen=True)
class MagNoise:
    """Magnetometer [gauss]: white noise per body axis and a constant disturbance per link.

    The disturbance is drawn once per link (``disturbance_std_gauss`` per world axis) and added to
    the earth's field before it is rotated into the body: a local anomaly and what calibration
    leaves of the link's own fields, as a heading error of about ``disturbance / 0.21 G`` rad.
    """

    field_std_gauss: float = 0.003
    disturbance_std_gauss: float = 0.008

    def __post_init__(self) -> None:
        require_nonnegative(self, *self.__dataclass_fields__)


@dataclass(frozen=True)
class SensorSuite:
    """One named profile of the sensors (barometer and magnetometer: ``None``, not fitted)."""

    imu: ImuNoise = field(default_factory=ImuNoise)
    gps: GpsNoise = field(default_factory=GpsNoise)
    attitude: AttitudeRefNoise = field(default_factory=AttitudeRefNoise)
    baro: BaroNoise | None = None
    mag: MagNoise | None = None


# the u-blox M8-class receiver of the profiles m8 and m8_baro_mag (see below)
_M8_GPS = GpsNoise(pos_horizontal_std_m=0.1, pos_vertical_std_m=0.2, vel_std_m_s=0.05, drift_amp_m=0.0,
                   bias_horizontal_std_m=0.8, bias_vertical_std_m=1.2, bias_time_constant_s=60.0,
                   common_horizontal_std_m=1.8, common_vertical_std_m=2.7, common_time_constant_s=300.0,
                   vel_bias_std_m_s=0.02, vel_bias_time_constant_s=10.0)


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
#: ``m8_baro_mag``: ``m8`` plus a barometer and a magnetometer on every link (the Pixhawk's own).
#: Barometer (MS5611, the Pixhawk's): 0.1 m white (the data sheet's 0.012 mbar RMS at OSR 4096,
#: "10 cm resolution"); 0.3 m Gauss-Markov drift over 300 s (warm-up and weather: a few
#: decimetres over the minutes of a flight, about 0.2 m within 60 s; 1 hPa per 3 h of weather is
#: 8 m per 3 h, 5 cm per minute); ground effect 0.5 m low at the ground fading out at 1 m, with
#: the rotors carrying the link (the downwash's over-pressure, which PX4's EKF2_GND_EFF_DZ /
#: EKF2_GND_MAX_HGT and ArduPilot's takeoff/touchdown-expected logic exist for). Magnetometer:
#: 3 mG white per axis (HMC5883L-class noise floor 2 mG, IST8310 / LIS3MDL 3-4 mG RMS), 8 mG per
#: axis constant disturbance per link (about 2 deg of heading on the 0.21 G horizontal field: a
#: calibrated compass near eight motors and their currents).
PROFILES: dict[str, SensorSuite] = {
    "outdoor": SensorSuite(),
    "paper": SensorSuite(
        gps=GpsNoise(
            pos_horizontal_std_m=math.sqrt(0.1), pos_vertical_std_m=math.sqrt(0.1), vel_std_m_s=math.sqrt(0.1)
        ),
        attitude=AttitudeRefNoise(tilt_std_rad=0.2, heading_std_rad=0.2, drift_amp_rad=math.radians(5.0)),
    ),
    "m8": SensorSuite(
        gps=_M8_GPS,
    ),
    "rtk": SensorSuite(
        gps=GpsNoise(pos_horizontal_std_m=0.005, pos_vertical_std_m=0.01, vel_std_m_s=0.02, drift_amp_m=0.0,
                     bias_horizontal_std_m=0.01, bias_vertical_std_m=0.015, bias_time_constant_s=30.0),
    ),
    "m8_baro_mag": SensorSuite(
        gps=_M8_GPS,
        baro=BaroNoise(height_std_m=0.1, drift_std_m=0.3, drift_time_constant_s=300.0, ground_effect_m=0.5,
                       ground_effect_height_m=1.0),
        mag=MagNoise(field_std_gauss=0.003, disturbance_std_gauss=0.008),
    ),
    "ideal": SensorSuite(
        imu=ImuNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        gps=GpsNoise(0.0, 0.0, 0.0, 0.0),
        attitude=AttitudeRefNoise(0.0, 0.0, 0.0),
    ),
}


class LinkSensors:
    """The sensors of all ``n`` links of one skeleton, vectorised over links."""

    def __init__(self, suite: SensorSuite, n_links: int, rng: np.random.Generator, *, compiled: bool | None = None):
        self.suite = suite
        #: the IMU's arithmetic by :func:`sitl.kernels.sensors.imu_kernel` (default: when numba is installed)
        self.compiled = _COMPILED_DEFAULT if compiled is None else bool(compiled)
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
        # barometer and magnetometer: from a child of ``rng`` (spawned only when one is fitted, which
        # draws nothing from ``rng`` itself), so that every other sensor and the wind draw the same
        # numbers with and without them: a profile and the same profile with a barometer see the
        # same GNSS errors (and the profiles without them are unchanged)
        b, m = suite.baro, suite.mag
        self._aux_rng = rng.spawn(1)[0] if b is not None or m is not None else None
        self._baro_drift_m = b.drift_std_m * self._aux_rng.normal(size=n_links) if b is not None else None
        self._baro_t: float | None = None
        self._mag_field_w = (MAG_FIELD_ENU_GAUSS + m.disturbance_std_gauss * self._aux_rng.normal(size=(n_links, 3))
                             if m is not None else None)

    @property
    def has_baro(self) -> bool:
        return self.suite.baro is not None

    @property
    def has_mag(self) -> bool:
        return self.suite.mag is not None

    def imu(self, specific_force_b: np.ndarray, omega_b: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(gyro, accel), each (n, 3) body frame, from the true specific force and body rate."""
        imu = self.suite.imu
        # one draw, in the order of the draws it stands for: the biases' steps, the gyro's noise, the accelerometer's
        draw = self.rng.normal(size=(4, self.n, 3))
        accel_walk = imu.accel_bias_rw_m_s2_sqrt_s * math.sqrt(dt_s)
        gyro_walk = imu.gyro_bias_rw_rad_s_sqrt_s * math.sqrt(dt_s)
        if self.compiled:
            scales = (accel_walk, gyro_walk, float(imu.gyro_std_rad_s), float(imu.accel_std_m_s2))
            return imu_kernel(draw, np.asarray(specific_force_b, dtype=float), np.asarray(omega_b, dtype=float),
                              self.accel_bias, self.gyro_bias, scales)
        accel_step, gyro_step, gyro_noise, accel_noise = draw
        self.accel_bias += accel_walk * accel_step
        self.gyro_bias += gyro_walk * gyro_step
        gyro = omega_b + self.gyro_bias + imu.gyro_std_rad_s * gyro_noise
        accel = specific_force_b + self.accel_bias + imu.accel_std_m_s2 * accel_noise
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

    def baro(self, t_s: float, p_w: np.ndarray, downwash: np.ndarray | None = None) -> np.ndarray:
        """(n,) barometric height above the origin [m] (a pressure altitude minus the origin's), the
        ground flat at height 0; ``downwash`` (n,) in [0, 1] scales the ground effect (``None``: 1)."""
        b = self.suite.baro
        if b is None:
            raise RuntimeError("this sensor suite has no barometer")
        dt = 0.0 if self._baro_t is None else max(t_s - self._baro_t, 0.0)
        self._baro_t = t_s
        a = math.exp(-dt / b.drift_time_constant_s)
        rng = self._aux_rng
        self._baro_drift_m = a * self._baro_drift_m + math.sqrt(1.0 - a * a) * b.drift_std_m * rng.normal(size=self.n)
        height = np.asarray(p_w, dtype=float)[:, 2]
        out = height + self._baro_drift_m + b.height_std_m * rng.normal(size=self.n)
        if b.ground_effect_m > 0:
            fade = np.clip(1.0 - height / b.ground_effect_height_m, 0.0, 1.0)
            blow = 1.0 if downwash is None else np.clip(np.asarray(downwash, dtype=float), 0.0, 1.0)
            out = out - b.ground_effect_m * fade * blow
        return out

    def mag(self, q_wxyz: np.ndarray) -> np.ndarray:
        """(n, 3) magnetic field in the body frame (FLU) [gauss] at the true attitudes ``q_wxyz``."""
        m = self.suite.mag
        if m is None:
            raise RuntimeError("this sensor suite has no magnetometer")
        R = quat_to_rotmat(np.asarray(q_wxyz, dtype=float))  # (n, 3, 3) body to world
        field_b = np.einsum("nji,nj->ni", R, self._mag_field_w)
        return field_b + m.field_std_gauss * self._aux_rng.normal(size=(self.n, 3))


def downwash_fraction(thrust_n: np.ndarray, mass_kg: float) -> np.ndarray:
    """(n,) how much the rotors blow: each link's summed rotor thrust magnitude over its weight,
    capped at 1 (``thrust_n``: (n, rotors) [N]); the barometer's ground effect scales with it."""
    total = np.abs(np.asarray(thrust_n, dtype=float)).sum(axis=-1)
    return np.minimum(total / (mass_kg * GRAVITY_M_S2), 1.0)


def warm_up() -> None:
    """Load (or compile) the IMU's kernel through the path :meth:`LinkSensors.imu` calls it by: a
    run's first firmware tick then costs no more than any other (without numba: nothing)."""
    if not _COMPILED_DEFAULT:
        return
    LinkSensors(PROFILES["outdoor"], 2, np.random.default_rng(0)).imu(np.zeros((2, 3)), np.zeros((2, 3)), 0.002)

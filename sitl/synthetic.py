"""Kinematic chain ground truth and synthetic sensors (no physics engine).

This is the "artificial measurements" simulation of the paper's sec. IV: a chain of rigid
links that satisfies the joint constraint (eq. 3) exactly, moving smoothly, observed by a
per-link IMU, GPS (position and velocity) and an attitude reference, with white noise and
slow drifts. It feeds the Table II benchmark and the estimator tests; the MuJoCo harness
replaces it for closed-loop flights.

World frame z-up. Link ``i`` (0-based) has attitude ``Rz(yaw_i) Ry(pitch_i) Rx(roll_i)``
with travelling-wave angles, link 0's centre follows a slow Lissajous path, and every other
centre follows from the joints: ``p_{i+1} = p_i + R_i d + R_{i+1} d``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.configfile import require_positive
from companion.estimation.so3 import quat_from_euler_zyx, quat_from_rotvec, quat_mul, quat_normalize, quat_to_rotmat
from companion.skeleton.body import GRAVITY_W_M_S2
from companion.skeleton.kinematics import chain_offsets

__all__ = ["ChainMotion", "ChainTruth", "chain_truth", "SensorModel", "Drift", "draw_drifts", "Sensors"]

_TWO_PI = 2.0 * math.pi
_GRAVITY_W = np.array(GRAVITY_W_M_S2)


@dataclass(frozen=True)
class ChainMotion:
    """A smooth, constraint-consistent motion of an n-link chain (angles in rad, Hz, m)."""

    n_links: int = 12
    link_length_m: float = 1.0
    base_amp_m: tuple[float, float, float] = (1.0, 0.6, 0.3)
    base_freq_hz: tuple[float, float, float] = (0.05, 0.07, 0.11)
    base_height_m: float = 5.0
    yaw_amp_rad: float = 0.35
    pitch_amp_rad: float = 0.25
    roll_amp_rad: float = 0.15
    yaw_freq_hz: float = 0.25
    pitch_freq_hz: float = 0.2
    roll_freq_hz: float = 0.3
    yaw_lag_rad: float = 0.6
    pitch_lag_rad: float = 0.5
    roll_lag_rad: float = 0.4

    def __post_init__(self) -> None:
        if self.n_links < 1:
            raise ValueError(f"n_links must be >= 1, got {self.n_links}")
        require_positive(self, "link_length_m")

    @property
    def d(self) -> np.ndarray:
        """(n, 3) centre-to-right-tip vectors in the body frame."""
        return np.tile([0.5 * self.link_length_m, 0.0, 0.0], (self.n_links, 1))


@dataclass(frozen=True)
class ChainTruth:
    """Ground truth at K times: t (K,), p/v/a (K, n, 3), q (K, n, 4), w_b (K, n, 3)."""

    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    q: np.ndarray
    w_b: np.ndarray


def _angles(motion: ChainMotion, t: np.ndarray):
    """Euler angles and their rates, each (K, n)."""
    i = np.arange(motion.n_links)[None, :]
    tt = np.asarray(t, dtype=float)[:, None]
    out = []
    for amp, freq, lag, offset in (
        (motion.yaw_amp_rad, motion.yaw_freq_hz, -motion.yaw_lag_rad, 0.0),
        (motion.pitch_amp_rad, motion.pitch_freq_hz, -motion.pitch_lag_rad, 1.0),
        (motion.roll_amp_rad, motion.roll_freq_hz, motion.roll_lag_rad, 0.0),
    ):
        arg = _TWO_PI * freq * tt + lag * i + offset
        out.append((amp * np.sin(arg), amp * _TWO_PI * freq * np.cos(arg)))
    return out


def _pose_velocity(motion: ChainMotion, t: np.ndarray):
    (yaw, dyaw), (pitch, dpitch), (roll, droll) = _angles(motion, t)
    q = quat_from_euler_zyx(yaw, pitch, roll)
    # Body rates of R = Rz(yaw) Ry(pitch) Rx(roll).
    w_b = np.stack(
        (
            droll - dyaw * np.sin(pitch),
            dpitch * np.cos(roll) + dyaw * np.cos(pitch) * np.sin(roll),
            -dpitch * np.sin(roll) + dyaw * np.cos(pitch) * np.cos(roll),
        ),
        axis=-1,
    )
    r, rd = chain_offsets(quat_to_rotmat(q), w_b, motion.d)
    tt = np.asarray(t, dtype=float)[:, None]
    amp = np.asarray(motion.base_amp_m)
    om = _TWO_PI * np.asarray(motion.base_freq_hz)
    base_p = amp * np.sin(om * tt) + np.array([0.0, 0.0, motion.base_height_m])
    base_v = amp * om * np.cos(om * tt)
    p = base_p[:, None] + r
    v = base_v[:, None] + rd
    return p, v, q, w_b


def chain_truth(motion: ChainMotion, t: np.ndarray, h: float = 1e-4) -> ChainTruth:
    """Ground truth at times ``t``; accelerations by central differences of exact velocities."""
    t = np.asarray(t, dtype=float)
    p, v, q, w_b = _pose_velocity(motion, t)
    _, v_plus, _, _ = _pose_velocity(motion, t + h)
    _, v_minus, _, _ = _pose_velocity(motion, t - h)
    a = (v_plus - v_minus) / (2.0 * h)
    return ChainTruth(t=t, p=p, v=v, a=a, q=q, w_b=w_b)


@dataclass(frozen=True)
class SensorModel:
    """Sensor noise of the Table II protocol (variances, per sample, unless stated).

    GPS and attitude white noise are the paper's Table I measurement noise; drifts are
    the sec. IV low-frequency biases (sinusoids below 0.1 Hz, 0.5 m and 5 deg amplitude
    along a random axis per link). IMU noise is MEMS grade: Table I's process noise is the
    filter's tuning (see :class:`link_firmware_sim.estimators.ekf_config.EkfNoise`), not a sensor property.
    """

    gps_pos_var_m2: float = 0.1
    gps_vel_var_m2_s2: float = 0.1
    quat_component_var: float = 0.01
    pos_drift_amp_m: float = 0.5
    att_drift_amp_rad: float = math.radians(5.0)
    drift_freq_min_hz: float = 0.02
    drift_freq_max_hz: float = 0.1
    accel_std_m_s2: float = 0.05
    gyro_std_rad_s: float = 0.005

    @classmethod
    def noiseless(cls) -> SensorModel:
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.02, 0.1, 0.0, 0.0)


@dataclass(frozen=True)
class Drift:
    """Per-link slow drift: a sum of ``K`` sinusoids, each along its own unit axis.

    Component amplitudes are ``amplitude / sqrt(K)`` so the drift's RMS magnitude equals that
    of one sinusoid of amplitude ``amplitude`` (``amplitude / sqrt(2)``) for any ``K``.
    """

    axis: np.ndarray  # (n, K, 3) unit vectors
    freq_hz: np.ndarray  # (n, K)
    phase_rad: np.ndarray  # (n, K)

    def at(self, t: float, amplitude: float) -> np.ndarray:
        """(n, 3) drift at time ``t``."""
        k = self.freq_hz.shape[1]
        waves = np.sin(_TWO_PI * self.freq_hz * t + self.phase_rad)[:, :, None]
        return (amplitude / math.sqrt(k)) * np.sum(self.axis * waves, axis=1)


def draw_drifts(rng: np.random.Generator, n: int, model: SensorModel, components: int = 1) -> Drift:
    """Random axes, frequencies (uniform in the model's band) and phases for ``n`` links."""
    if components < 1:
        raise ValueError(f"components must be >= 1, got {components}")
    axis = rng.normal(size=(n, components, 3))
    axis /= np.linalg.norm(axis, axis=2, keepdims=True)
    freq = rng.uniform(model.drift_freq_min_hz, model.drift_freq_max_hz, size=(n, components))
    phase = rng.uniform(0.0, _TWO_PI, size=(n, components))
    return Drift(axis, freq, phase)


class Sensors:
    """Seeded sensor suite of one chain: every draw comes from ``rng``."""

    def __init__(self, model: SensorModel, n_links: int, rng: np.random.Generator):
        self.model = model
        self.n = n_links
        self.rng = rng
        self.pos_drift = draw_drifts(rng, n_links, model)
        self.att_drift = draw_drifts(rng, n_links, model)

    def imu(self, truth: ChainTruth, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(gyro (n, 3) rad/s, specific force (n, 3) m/s^2), body frame, at truth index k."""
        m = self.model
        R = quat_to_rotmat(truth.q[k])
        f_b = np.einsum("nji,nj->ni", R, truth.a[k] - _GRAVITY_W)
        gyro = truth.w_b[k] + m.gyro_std_rad_s * self.rng.normal(size=(self.n, 3))
        accel = f_b + m.accel_std_m_s2 * self.rng.normal(size=(self.n, 3))
        return gyro, accel

    def gps(self, truth: ChainTruth, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(position (n, 3) m, velocity (n, 3) m/s) with drift and white noise."""
        m = self.model
        t = float(truth.t[k])
        pos = truth.p[k] + self.pos_drift.at(t, m.pos_drift_amp_m)
        pos = pos + math.sqrt(m.gps_pos_var_m2) * self.rng.normal(size=(self.n, 3))
        vel = truth.v[k] + math.sqrt(m.gps_vel_var_m2_s2) * self.rng.normal(size=(self.n, 3))
        return pos, vel

    def attitude(self, truth: ChainTruth, k: int) -> np.ndarray:
        """(n, 4) measured attitude: drift rotation, then white noise on each component."""
        m = self.model
        t = float(truth.t[k])
        q = quat_mul(quat_from_rotvec(self.att_drift.at(t, m.att_drift_amp_rad)), truth.q[k])
        q = q + math.sqrt(m.quat_component_var) * self.rng.normal(size=(self.n, 4))
        return quat_normalize(q)

"""Per-link EKFs on a synthetic chain, sampled at the SCKF rate (paper sec. IV protocol).

Runs one :class:`link_firmware_sim.estimators.link_ekf.LinkEkf` per link on the seeded synthetic sensors of
:mod:`sitl.synthetic` and records, at every SCKF tick, what the companion would receive
(state, body rate, 9x9 covariance) beside the ground truth. The result is also the input
format of ``python -m companion replay``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_positive
from companion.replay import REPLAY_KEYS, ReplayData
from link_firmware_sim.estimators import EkfConfig, EkfNoise, LinkEkf
from sitl.plant.schedule import rate_divisor
from sitl.synthetic import ChainMotion, Sensors, SensorModel, chain_truth

__all__ = [
    "ChainRun",
    "EkfStream",
    "EKF_CONFIGS",
    "drift_seen",
    "honest_noise",
    "consistent_ekf_config",
    "ekf_config",
    "simulate_ekf_chain",
]

#: The EKF tunings the Table II benchmark compares (see :func:`ekf_config`).
EKF_CONFIGS = ("paper", "consistent")


@dataclass(frozen=True)
class ChainRun:
    """Protocol of one synthetic EKF run (defaults: the paper's sec. IV simulation)."""

    motion: ChainMotion = field(default_factory=ChainMotion)
    sensors: SensorModel = field(default_factory=SensorModel)
    ekf: EkfConfig = field(default_factory=EkfConfig)
    duration_s: float = 20.0
    ekf_rate_hz: float = 100.0
    gps_rate_hz: float = 10.0
    att_rate_hz: float = 100.0
    sckf_rate_hz: float = 20.0

    def __post_init__(self) -> None:
        require_positive(self, "duration_s")
        for name in ("gps", "att", "sckf"):
            rate_divisor(self.ekf_rate_hz, getattr(self, f"{name}_rate_hz"), name)


def drift_seen(var_per_axis: float, f_min_hz: float, f_max_hz: float, memory_s: float) -> float:
    """Per-axis variance of a sinusoidal drift left in a first-order average of memory ``memory_s``.

    A drift ``A sin(2 pi f t + phi)`` along a random unit axis has per-axis variance
    ``var_per_axis = A^2 / 6``. A filter that averages its measurements over a time constant
    ``tau`` passes it through the low-pass ``1 / (1 + (2 pi f tau)^2)`` (power); with ``f``
    uniform in ``[f_min, f_max]`` the mean gain is ``(atan(2 pi f_max tau) - atan(2 pi f_min
    tau)) / (2 pi tau (f_max - f_min))``: about 1 for ``tau`` well below the slowest period
    (the estimate follows the drift), ``1 / ((2 pi tau)^2 f_min f_max)`` well above it.
    """
    a, b = 2.0 * math.pi * f_min_hz * memory_s, 2.0 * math.pi * f_max_hz * memory_s
    gain = 1.0 / (1.0 + a * a) if b - a < 1e-9 else (math.atan(b) - math.atan(a)) / (b - a)
    return var_per_axis * gain


def honest_noise(white_var: float, drift_var_seen: float, rate_hz: float, memory_s: float) -> tuple[float, float]:
    """``(R, q)``: measurement variance and random-walk density that make a filter honest about a drift.

    A state with process noise density ``q`` measured at ``rate_hz`` with variance ``R`` has, in
    steady state, the memory (time constant) ``tau = sqrt(R / (q rate))``: it averages ``N =
    tau rate`` measurements and claims the variance ``P = R / N``. Its actual error, when the
    true state is predicted almost perfectly (the IMU is far better than the random walk the
    filter assumes), is the white noise averaged over ``2 N`` measurements, ``white / (2 N)``,
    plus the drift it cannot average out, ``drift_var_seen`` (:func:`drift_seen`). ``P`` equals
    that for ``R = white / 2 + N drift_var_seen``, and the memory is kept by ``q = R / (rate
    tau^2)``.
    """
    n = memory_s * rate_hz
    R = 0.5 * white_var + n * drift_var_seen
    return R, R / (rate_hz * memory_s * memory_s)


def consistent_ekf_config(
    sensors: SensorModel = SensorModel(), gps_rate_hz: float = 10.0, att_rate_hz: float = 100.0,
    imu_rate_hz: float = 100.0,
) -> EkfConfig:
    """An EKF tuning whose covariance is honest about the protocol's slow drifts.

    The default :class:`EkfConfig` (the paper's Table I) assumes the measurements carry white
    noise only; the protocol's GPS position and attitude reference also drift (one sinusoid per
    link along a random axis, frequency uniform in ``[f_min, f_max]`` = 0.02-0.1 Hz). Derived
    from ``sensors`` (numbers for the default :class:`SensorModel`):

    * Drift per axis: ``A^2 / 6`` (mean square ``A^2 / 2`` of a sinusoid, a third on each axis):
      position 0.5 m -> 0.0417 m^2, attitude 5 deg -> 1.27e-3 rad^2.
    * White noise: GPS position 0.1 m^2, velocity 0.1 (m/s)^2 (no drift) at ``gps_rate_hz``;
      attitude ``4 c`` rad^2 per axis for a variance ``c`` per quaternion component (the rotation
      error is twice the component orthogonal to the quaternion): 0.04 rad^2 at ``att_rate_hz``.
    * IMU: gyro 0.005 rad/s and accelerometer 0.05 m/s^2 per ``imu_rate_hz`` sample, i.e. random
      walks of ``std^2 / rate`` = 2.5e-7 rad^2/s and 2.5e-5 (m/s)^2/s: the velocity process
      noise, and a floor under the attitude's.
    * Position and attitude: :func:`honest_noise` for a memory ``tau`` with the drift left in
      it (:func:`drift_seen`). Position: ``tau = 1 / (2 pi f_max)`` = 1.6 s, shorter than every
      drift period, so the estimate follows the drift it cannot separate (the drift-free GPS
      velocity integrates to a position that wanders too much over a drift period): R = 0.54
      m^2, q = 0.021 m^2/s. Attitude: the gyro predicts it almost perfectly, so the memory can
      be as long as the drift model holds within a 20 s run: ``tau = 1 / (2 pi f_min)`` = 8 s,
      the slowest drift's time constant: R = 0.17 rad^2, q = 2.7e-5 rad^2/s. A long attitude
      memory also lets the GPS velocity correct the attitude (an attitude error ``e`` is an
      acceleration error ``g e`` in tilt, and in yaw whenever the link accelerates sideways),
      which this per-measurement derivation leaves out: the attitude covariance errs on the
      large side.
    * Initial variances: those of the first fix the filter starts from (white + drift).

    Longer attitude memories than this derivation's lower the quaternion error and raise the NEES:
    much longer ones turn over-confident (a 20 s run stays in the transient after the first fix,
    where the drift has not averaged out yet). How this tuning and the paper's compare:
    ``python -m sitl.bench table2`` (docs/bench/table2.md). Compare
    :func:`link_firmware_sim.estimators.tunings.outdoor_ekf_config`, the same idea for the SITL sensors.
    """
    m = sensors
    pos_drift = m.pos_drift_amp_m ** 2 / 6.0
    att_drift = m.att_drift_amp_rad ** 2 / 6.0
    att_white = 4.0 * m.quat_component_var
    f1, f2 = m.drift_freq_min_hz, m.drift_freq_max_hz
    tau_p = 1.0 / (2.0 * math.pi * f2)
    tau_a = 1.0 / (2.0 * math.pi * f1)
    R_p, q_p = honest_noise(m.gps_pos_var_m2, drift_seen(pos_drift, f1, f2, tau_p), gps_rate_hz, tau_p)
    R_a, q_a = honest_noise(att_white, drift_seen(att_drift, f1, f2, tau_a), att_rate_hz, tau_a)
    vel_var = max(m.gps_vel_var_m2_s2, 1e-6)
    return EkfConfig(
        noise=EkfNoise(
            pos_m2_s=q_p,
            vel_m2_s3=max(m.accel_std_m_s2 ** 2 / imu_rate_hz, 1e-9),
            att_rad2_s=q_a + m.gyro_std_rad_s ** 2 / imu_rate_hz,
        ),
        gps_pos_var_m2=max(R_p, 1e-6),
        gps_vel_var_m2_s2=vel_var,
        att_var_rad2=max(R_a, 1e-8),
        init_pos_var_m2=max(m.gps_pos_var_m2 + pos_drift, 1e-6),
        init_vel_var_m2_s2=vel_var,
        init_att_var_rad2=max(att_white + att_drift, 1e-8),
    )


def ekf_config(name: str, run: ChainRun | None = None) -> EkfConfig:
    """The EKF tuning ``name`` (one of :data:`EKF_CONFIGS`) for the sensors and rates of ``run``.

    ``paper``: :class:`EkfConfig`'s defaults, Table I (white measurement noise only, the drifts
    unmodelled); ``consistent``: :func:`consistent_ekf_config`.
    """
    run = ChainRun() if run is None else run
    if name == "paper":
        return EkfConfig()
    if name == "consistent":
        return consistent_ekf_config(run.sensors, run.gps_rate_hz, run.att_rate_hz, run.ekf_rate_hz)
    raise ValueError(f"unknown EKF config {name!r}; expected one of {', '.join(EKF_CONFIGS)}")


@dataclass(frozen=True)
class EkfStream(ReplayData):
    """EKF outputs at the SCKF ticks (the ``companion replay`` input) with the ground truth.

    Replay fields: ``t`` (K,), ``p``/``v`` (K, n, 3), ``q`` (K, n, 4), ``w`` (K, n, 3) body
    rate, ``P`` (K, n, 9, 9), ``d`` (n, 3); truth: ``p_true``, ``v_true``, ``q_true``.
    """

    p_true: np.ndarray
    v_true: np.ndarray
    q_true: np.ndarray

    def replay_arrays(self) -> dict[str, np.ndarray]:
        """The keys of the ``companion replay`` input format."""
        return {key: getattr(self, key) for key in REPLAY_KEYS}


def simulate_ekf_chain(run: ChainRun, seed: int, progress=None) -> EkfStream:
    """Run every link's EKF on the synthetic chain and sample it at the SCKF rate.

    All randomness (drift axes/frequencies/phases, white noise) comes from
    ``numpy.random.default_rng(seed)``. The EKFs start from the first GPS fix and attitude
    measurement. ``progress`` is an optional callable ``progress(n_ticks_done)``.
    """
    rng = np.random.default_rng(seed)
    n = run.motion.n_links
    dt = 1.0 / run.ekf_rate_hz
    n_ticks = int(round(run.duration_s * run.ekf_rate_hz))
    gps_div = rate_divisor(run.ekf_rate_hz, run.gps_rate_hz, "gps")
    att_div = rate_divisor(run.ekf_rate_hz, run.att_rate_hz, "att")
    sckf_div = rate_divisor(run.ekf_rate_hz, run.sckf_rate_hz, "sckf")
    truth = chain_truth(run.motion, np.arange(n_ticks + 1) * dt)
    sensors = Sensors(run.sensors, n, rng)

    pos0, vel0 = sensors.gps(truth, 0)
    att0 = sensors.attitude(truth, 0)
    ekfs = [LinkEkf(pos0[i], vel0[i], att0[i], run.ekf) for i in range(n)]

    K = n_ticks // sckf_div
    out = {key: np.empty((K, n, 3)) for key in ("p", "v", "w", "p_true", "v_true")}
    out["q"] = np.empty((K, n, 4))
    out["q_true"] = np.empty((K, n, 4))
    out["P"] = np.empty((K, n, 9, 9))
    t_out = np.empty(K)
    k_out = 0
    for k in range(n_ticks):
        gyro, accel = sensors.imu(truth, k)
        for i, ekf in enumerate(ekfs):
            ekf.predict(gyro[i], accel[i], dt)
        kk = k + 1
        if kk % gps_div == 0:
            pos, vel = sensors.gps(truth, kk)
            for i, ekf in enumerate(ekfs):
                ekf.update_position(pos[i])
                ekf.update_velocity(vel[i])
        if kk % att_div == 0:
            att = sensors.attitude(truth, kk)
            for i, ekf in enumerate(ekfs):
                ekf.update_attitude(att[i])
        if kk % sckf_div == 0:
            t_out[k_out] = truth.t[kk]
            for i, ekf in enumerate(ekfs):
                p, v, q, w, P9 = ekf.sckf_view()
                out["p"][k_out, i], out["v"][k_out, i], out["q"][k_out, i] = p, v, q
                out["w"][k_out, i], out["P"][k_out, i] = w, P9
            out["p_true"][k_out] = truth.p[kk]
            out["v_true"][k_out] = truth.v[kk]
            out["q_true"][k_out] = truth.q[kk]
            k_out += 1
        if progress is not None:
            progress(1)
    return EkfStream(t=t_out, d=run.motion.d, **out)

"""Per-link EKFs on a synthetic chain, sampled at the SCKF rate (paper sec. IV protocol).

Runs one :class:`link_firmware_sim.ekf.LinkEkf` per link on the seeded synthetic sensors of
:mod:`sitl.synthetic` and records, at every SCKF tick, what the companion would receive
(state, body rate, 9x9 covariance) beside the ground truth. The result is also the input
format of ``python -m companion replay``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.configfile import require_positive
from companion.replay import REPLAY_KEYS, ReplayData
from link_firmware_sim.ekf import EkfConfig, LinkEkf
from sitl.synthetic import ChainMotion, Sensors, SensorModel, chain_truth

__all__ = ["ChainRun", "EkfStream", "rate_divisor", "simulate_ekf_chain"]


def rate_divisor(base_hz: float, rate_hz: float, name: str) -> int:
    """Ticks of the base rate per event of ``rate_hz``; ``ValueError`` unless a whole multiple."""
    if not (rate_hz > 0 and base_hz > 0):
        raise ValueError(f"{name}: rates must be positive (base {base_hz} Hz, {name} {rate_hz} Hz)")
    ratio = base_hz / rate_hz
    div = round(ratio)
    if div < 1 or abs(ratio - div) > 1e-9 * ratio:
        raise ValueError(f"{name} rate {rate_hz} Hz is not a whole divisor of the base tick rate {base_hz} Hz")
    return int(div)


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

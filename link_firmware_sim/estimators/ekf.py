"""Per-link SE(3) error-state EKF of the simulated Pixhawk (paper eq. 2).

Nominal state ``x = [p; v; q; b_a; b_g]`` (16 numbers): world-frame position [m] and
velocity [m/s] of the link centre, body-to-world attitude (Hamilton, w first), accelerometer
bias [m/s^2] and gyro bias [rad/s] (body frame). Error state
``dx = [dp; dv; dtheta; db_a; db_g]`` (15 numbers) with the world-frame attitude error of
DESIGN.md sec. 4 (``q = dq(dtheta) (x) q_hat``), the convention of the SCKF (paper sec. III-A)
and of Sola, "Quaternion kinematics for the error-state Kalman filter" (2017), sec. 7
("global angular error"). The first 9 error states are the paper's ``[p~; v~; dtheta]``;
:func:`sckf_view` exposes them with their 9x9 covariance block.

World frame z-up, gravity ``[0, 0, -g]``; accelerometers measure specific force
``f = R^T (a - g)`` in the body frame.

Functional core (``ekf_predict``, ``ekf_update_*``: ``(x, P, ...) -> (x, P[, info])``, no
state, no clocks) and a thin stateful :class:`LinkEkf` on top. Covariance updates use the
Joseph form and keep ``P`` symmetric.

Biases are estimated only if their process noise / initial variance is non-zero; with both
zero the filter reduces exactly to the paper's 9-state EKF.

Barometer: the first barometric height after start-up (or after a position reset) fixes the
barometer's offset to the EKF's height, as PX4's baro height reference does, but as a state: the
nominal state grows by the offset ``b`` (``X_BARO``), the error state by its error (``E_BARO``),
whose covariance row is that of the height error it was taken against (``b = h_baro - z``, so
``db = -dz - noise``). The barometer then measures ``z + b`` (:func:`ekf_update_baro`): it tells
the filter how the height changes, never where it is better than the GNSS height the offset was
taken against, and the covariance says so; ``b`` walks with the barometer's drift
(``EkfNoise.baro_bias_m2_s``). Without barometer samples the state stays at 16 / 15 numbers and
every operation is the one it was.

Magnetometer: :func:`ekf_update_mag_heading` fuses the heading of the measured field, rotated into
the world with the estimated attitude (tilt compensation), against the known declination, with
the Jacobian of that heading with respect to the attitude error (:func:`mag_heading_jacobian`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import numpy as np

from companion.estimation.chain import ERR_DIM, ERR_P, ERR_TH, ERR_V
from companion.estimation.so3 import attitude_error, quat_normalize, quat_to_rotmat, retract, rotmat_tuple
from companion.skeleton.body import GRAVITY_W_M_S2

from . import _fast
from .geo import MAG_DECLINATION_RAD

__all__ = [
    "X_P",
    "X_V",
    "X_Q",
    "X_BA",
    "X_BG",
    "NX",
    "E_P",
    "E_V",
    "E_TH",
    "E_BA",
    "E_BG",
    "E_SCKF",
    "NE",
    "E_PZ",
    "X_BARO",
    "E_BARO",
    "NX_BARO",
    "NE_BARO",
    "GRAVITY_W_M_S2",
    "EkfNoise",
    "EkfConfig",
    "UpdateInfo",
    "ekf_init",
    "ekf_predict",
    "error_transition",
    "inject_error",
    "ekf_update_position",
    "ekf_reset_position",
    "ekf_update_velocity",
    "ekf_update_attitude",
    "attitude_variance",
    "ekf_update_heading",
    "heading_jacobian",
    "ekf_add_baro_offset",
    "ekf_remove_baro_offset",
    "ekf_update_baro",
    "ekf_update_mag_heading",
    "mag_heading_jacobian",
    "sckf_view",
    "LinkEkf",
]

# Nominal state slices.
X_P = slice(0, 3)
X_V = slice(3, 6)
X_Q = slice(6, 10)
X_BA = slice(10, 13)
X_BG = slice(13, 16)
NX = 16
# Error state slices. The first nine are, by contract, the SCKF's per-link error state.
E_P = ERR_P
E_V = ERR_V
E_TH = ERR_TH
E_BA = slice(9, 12)
E_BG = slice(12, 15)
#: The paper's error state [p~; v~; dtheta] (what the SCKF consumes).
E_SCKF = slice(0, ERR_DIM)
NE = 15
#: The vertical position error (the barometer's block).
E_PZ = slice(E_P.start + 2, E_P.start + 3)
#: The barometer's offset, appended once a barometer has referenced it (see the module docstring).
X_BARO = slice(NX, NX + 1)
E_BARO = slice(NE, NE + 1)
NX_BARO = NX + 1
NE_BARO = NE + 1

_DIAG = np.diag_indices(NE)


@dataclass(frozen=True)
class EkfNoise:
    """Continuous-time process noise densities (variance growth per second).

    Defaults are the paper's Table I process noise ``diag[0.1 I3, 0.1 I3, 0.01 I3]`` on
    ``[p; v; theta]``, read as densities (m^2/s, (m/s)^2/s, rad^2/s), and no bias walk.
    ``att_yaw_rad2_s`` gives the vertical axis of the world-frame attitude error (the heading)
    its own density (``None``: ``att_rad2_s`` on every axis): the tilt is held by gravity and the
    GPS velocity, the heading only by the heading reference.
    """

    pos_m2_s: float = 0.1
    vel_m2_s3: float = 0.1
    att_rad2_s: float = 0.01
    accel_bias_m2_s5: float = 0.0
    gyro_bias_rad2_s3: float = 0.0
    att_yaw_rad2_s: float | None = None
    #: random walk of the barometer's offset, once it is a state: its drift (the paper has no
    #: barometer; default: a MEMS barometer's 0.3 m Gauss-Markov drift over 300 s, ``2 s^2 / tau``)
    baro_bias_m2_s: float = 6e-4

    def __post_init__(self) -> None:
        for name in ("pos_m2_s", "vel_m2_s3", "att_rad2_s", "accel_bias_m2_s5", "gyro_bias_rad2_s3", "att_yaw_rad2_s",
                     "baro_bias_m2_s"):
            val = getattr(self, name)
            if val is None and name == "att_yaw_rad2_s":
                continue
            if not (math.isfinite(val) and val >= 0.0):
                raise ValueError(f"EkfNoise.{name} must be a finite non-negative number, got {val!r}")

    @cached_property
    def densities(self) -> np.ndarray:
        """(15,) diagonal of the continuous process noise over the error state."""
        out = np.repeat(
            [self.pos_m2_s, self.vel_m2_s3, self.att_rad2_s, self.accel_bias_m2_s5, self.gyro_bias_rad2_s3], 3
        )
        if self.att_yaw_rad2_s is not None:
            out[E_TH.start + 2] = self.att_yaw_rad2_s
        return out


@dataclass(frozen=True)
class EkfConfig:
    """EKF tuning: process noise, measurement variances, gates and initial uncertainty.

    Measurement variances default to the paper's Table I (0.1 m^2 position, 0.1 (m/s)^2
    velocity, 0.01 per quaternion component = 0.04 rad^2 per attitude axis because
    ``dq ~ [1; dtheta/2]``). ``att_var_rad2`` applies to every axis of the world-frame attitude
    error unless ``att_yaw_var_rad2`` gives the vertical (heading) axis its own: an AHRS's tilt
    (from gravity) and heading (from the magnetometer) err differently. ``gate_sigma`` rejects a
    measurement when any axis of its innovation exceeds that many standard deviations (as PX4
    EKF2's ``*_GATE`` parameters).

    Barometer and magnetometer (fused when their samples arrive, unless ``fuse_baro`` /
    ``fuse_mag`` is off; PX4's EKF2_BARO_CTRL / EKF2_MAG_TYPE): ``baro_var_m2`` is the white
    noise of a barometric height (its drift is the offset state's random walk,
    ``EkfNoise.baro_bias_m2_s``); while the link is in its rotors' ground effect (armed, less
    than ``baro_ground_effect_height_m`` above where it armed: PX4's EKF2_GND_MAX_HGT) a
    barometer reading up to ``baro_ground_effect_deadzone_m`` below the estimate is taken as
    agreeing with it, a lower one as that much higher (PX4's EKF2_GND_EFF_DZ).
    ``mag_heading_var_rad2`` is the variance of the magnetometer's heading, ``mag_declination_rad``
    the declination of the earth's field (east of north; PX4's EKF2_MAG_DECL).
    """

    noise: EkfNoise = field(default_factory=EkfNoise)
    gps_pos_var_m2: float = 0.1
    gps_vel_var_m2_s2: float = 0.1
    att_var_rad2: float = 0.04
    att_yaw_var_rad2: float | None = None
    heading_var_rad2: float = 0.01
    gate_sigma: float = 5.0
    init_pos_var_m2: float = 1.0
    init_vel_var_m2_s2: float = 0.25
    init_att_var_rad2: float = 0.05
    init_accel_bias_var: float = 0.0
    init_gyro_bias_var: float = 0.0
    fuse_baro: bool = True
    baro_var_m2: float = 0.01
    baro_ground_effect_height_m: float = 1.0
    baro_ground_effect_deadzone_m: float = 1.0
    fuse_mag: bool = True
    mag_heading_var_rad2: float = 0.04
    mag_declination_rad: float = MAG_DECLINATION_RAD
    #: variance of the GNSS position bias the filter does not estimate [m^2], horizontal and
    #: vertical: the filter follows the receiver, bias and all, and this is added to the position
    #: covariance it reports (a "consider" state, marginalised; the filter's gains do not see it)
    gps_bias_var_m2: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        for name in (
            "gps_pos_var_m2",
            "gps_vel_var_m2_s2",
            "att_var_rad2",
            "heading_var_rad2",
            "baro_var_m2",
            "mag_heading_var_rad2",
            "gate_sigma",
            "init_pos_var_m2",
            "init_vel_var_m2_s2",
            "init_att_var_rad2",
        ):
            val = getattr(self, name)
            if not (math.isfinite(val) and val > 0.0):
                raise ValueError(f"EkfConfig.{name} must be a positive number, got {val!r}")
        if self.att_yaw_var_rad2 is not None and not (math.isfinite(self.att_yaw_var_rad2) and self.att_yaw_var_rad2 > 0):
            raise ValueError(f"EkfConfig.att_yaw_var_rad2 must be a positive number or None, got {self.att_yaw_var_rad2!r}")
        if len(self.gps_bias_var_m2) != 2 or not all(math.isfinite(v) and v >= 0.0 for v in self.gps_bias_var_m2):
            raise ValueError(f"EkfConfig.gps_bias_var_m2 must be two finite non-negative variances (horizontal, "
                             f"vertical), got {self.gps_bias_var_m2!r}")
        for name in ("init_accel_bias_var", "init_gyro_bias_var", "baro_ground_effect_height_m",
                     "baro_ground_effect_deadzone_m"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val >= 0.0):
                raise ValueError(f"EkfConfig.{name} must be a finite non-negative number, got {val!r}")
        if not (math.isfinite(self.mag_declination_rad) and abs(self.mag_declination_rad) <= math.pi):
            raise ValueError(f"EkfConfig.mag_declination_rad must be within +-pi, got {self.mag_declination_rad!r}")


@dataclass(frozen=True)
class UpdateInfo:
    """Outcome of one measurement update.

    ``test_ratio`` is the largest ``innov_k^2 / (gate^2 S_kk)`` over the measurement's axes
    (PX4's innovation test ratio): the update is rejected when it exceeds 1.
    """

    accepted: bool
    innovation: np.ndarray
    test_ratio: float


def ekf_init(p_w_m, v_w_m_s, q_wxyz, config: EkfConfig = EkfConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Initial state (zero biases) and diagonal covariance from ``config``."""
    x = np.zeros(NX)
    x[X_P] = p_w_m
    x[X_V] = v_w_m_s
    x[X_Q] = quat_normalize(np.asarray(q_wxyz, dtype=float))
    P = np.zeros((NE, NE))
    P[E_P, E_P] = config.init_pos_var_m2 * np.eye(3)
    P[E_V, E_V] = config.init_vel_var_m2_s2 * np.eye(3)
    P[E_TH, E_TH] = config.init_att_var_rad2 * np.eye(3)
    P[E_BA, E_BA] = config.init_accel_bias_var * np.eye(3)
    P[E_BG, E_BG] = config.init_gyro_bias_var * np.eye(3)
    return x, P


def _block_index(rows: slice, cols: slice) -> np.ndarray:
    """Flat indices of a 3x3 block of a 15x15 matrix, row-major."""
    r = np.arange(rows.start, rows.stop)
    c = np.arange(cols.start, cols.stop)
    return (r[:, None] * NE + c[None, :]).ravel()


# The entries of F that depend on the state, in the order _transition fills them.
_F_VARYING = np.concatenate(
    [_block_index(*b) for b in ((E_P, E_TH), (E_P, E_BA), (E_V, E_TH), (E_V, E_BA), (E_TH, E_BG))]
)


@lru_cache(maxsize=16)
def _transition_base(dt_s: float) -> np.ndarray:
    F = np.eye(NE)
    F[E_P, E_V] = dt_s * np.eye(3)
    return F


def _transition(R: tuple, f_w: tuple, dt_s: float) -> np.ndarray:
    """``F`` from ``R`` (row-major 9-tuple) and the world specific force ``f_w`` (3-tuple).

    Blocks: ``F[p, th] = -dt^2/2 S(f_w)``, ``F[p, ba] = -dt^2/2 R``, ``F[v, th] = -dt S(f_w)``,
    ``F[v, ba] = -dt R``, ``F[th, bg] = -dt R`` (see :func:`error_transition`).
    """
    fx, fy, fz = f_w
    ms = (0.0, fz, -fy, -fz, 0.0, fx, fy, -fx, 0.0)  # -S(f_w), row-major
    h = 0.5 * dt_s * dt_s
    values = (
        [h * v for v in ms] + [-h * v for v in R] + [dt_s * v for v in ms] + [-dt_s * v for v in R] * 2
    )
    F = _transition_base(dt_s).copy()
    F.flat[_F_VARYING] = values
    return F


def error_transition(x, gyro_b_rad_s, accel_b_m_s2, dt_s: float) -> np.ndarray:
    """Error-state transition of :func:`ekf_predict`.

    World-frame attitude error (Sola 2017, sec. 7): ``dp' = dv``,
    ``dv' = -S(R f) dtheta - R db_a``, ``dtheta' = -R db_g``, biases constant; discretised
    like the nominal state (the position picks up the ``dt^2/2`` acceleration terms).
    """
    R = rotmat_tuple(x[X_Q].tolist())
    f = (np.asarray(accel_b_m_s2, dtype=float) - x[X_BA]).tolist()
    f_w = tuple(R[3 * i] * f[0] + R[3 * i + 1] * f[1] + R[3 * i + 2] * f[2] for i in range(3))
    return _transition(R, f_w, dt_s)


def ekf_predict(x, P, gyro_b_rad_s, accel_b_m_s2, dt_s: float, noise: EkfNoise) -> tuple[np.ndarray, np.ndarray]:
    """IMU propagation over ``dt_s`` (gyro rate and specific force in the body frame).

    Nominal: ``p += v dt + a dt^2/2``, ``v += a dt`` with ``a = R (f - b_a) + g``, and
    ``q <- q (x) Exp((w - b_g) dt)``. Covariance ``F P F^T + Q dt`` with
    :func:`error_transition` and the process noise densities.

    The nominal part is a few dozen scalar operations; it runs on plain floats (numpy's
    per-call overhead would dominate at 500 Hz per link) and the covariance on numpy.
    """
    if not dt_s > 0.0:
        raise ValueError(f"dt_s must be positive, got {dt_s!r}")
    px, py, pz, vx, vy, vz, qw, qx, qy, qz, bax, bay, baz, bgx, bgy, bgz = x[:NX].tolist()
    gx, gy, gz = np.asarray(gyro_b_rad_s, dtype=float).tolist()
    ax_, ay_, az_ = np.asarray(accel_b_m_s2, dtype=float).tolist()
    R = rotmat_tuple((qw, qx, qy, qz))
    fb = (ax_ - bax, ay_ - bay, az_ - baz)
    f_w = tuple(R[3 * i] * fb[0] + R[3 * i + 1] * fb[1] + R[3 * i + 2] * fb[2] for i in range(3))
    g = GRAVITY_W_M_S2
    acc = (f_w[0] + g[0], f_w[1] + g[1], f_w[2] + g[2])
    h = 0.5 * dt_s * dt_s
    # q <- q (x) Exp(w dt)
    rx, ry, rz = (gx - bgx) * dt_s, (gy - bgy) * dt_s, (gz - bgz) * dt_s
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-8:
        ew, k = 1.0, 0.5
    else:
        ew, k = math.cos(0.5 * angle), math.sin(0.5 * angle) / angle
    ex, ey, ez = k * rx, k * ry, k * rz
    nw = qw * ew - qx * ex - qy * ey - qz * ez
    nx = qw * ex + qx * ew + qy * ez - qz * ey
    ny = qw * ey - qx * ez + qy * ew + qz * ex
    nz = qw * ez + qx * ey - qy * ex + qz * ew
    inv = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    xn = np.array(
        (
            px + vx * dt_s + h * acc[0], py + vy * dt_s + h * acc[1], pz + vz * dt_s + h * acc[2],
            vx + acc[0] * dt_s, vy + acc[1] * dt_s, vz + acc[2] * dt_s,
            nw * inv, nx * inv, ny * inv, nz * inv,
            bax, bay, baz, bgx, bgy, bgz,
        )
    )
    F = _transition(R, f_w, dt_s)
    if len(P) == NE:
        Pn = F @ P @ F.T
        Pn[_DIAG] += noise.densities * dt_s
    else:  # with the barometer's offset: a random walk appended to the core state
        xn = np.concatenate((xn, x[NX:]))
        Pn = np.empty_like(P)
        core = F @ P[:NE, :NE] @ F.T
        core[_DIAG] += noise.densities * dt_s
        cross = F @ P[:NE, NE:]
        Pn[:NE, :NE] = core
        Pn[:NE, NE:] = cross
        Pn[NE:, :NE] = cross.T
        Pn[NE:, NE:] = P[NE:, NE:]
        Pn[E_BARO, E_BARO] += noise.baro_bias_m2_s * dt_s
    return xn, 0.5 * (Pn + Pn.T)


def inject_error(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """Nominal state corrected by an error state ``dx`` (attitude on the left, world frame)."""
    xn = x.copy()
    xn[X_P] += dx[E_P]
    xn[X_V] += dx[E_V]
    xn[X_Q] = retract(x[X_Q], dx[E_TH])
    xn[X_BA] += dx[E_BA]
    xn[X_BG] += dx[E_BG]
    if len(dx) > NE:
        xn[NX:] += dx[NE:]
    return xn


def _gate(r: np.ndarray, S_diag: np.ndarray, gate_sigma: float) -> float:
    """PX4-style innovation test ratio: the largest ``r_k^2 / (gate^2 S_kk)``."""
    return float(np.max(r * r / (gate_sigma * gate_sigma * S_diag)))


def _update(x, P, r, H, Rm, gate_sigma: float):
    """Gated Kalman update with residual ``r = z - h(x)`` and Joseph-form covariance."""
    PHt = P @ H.T
    S = H @ PHt + Rm
    test = _gate(r, np.diag(S), gate_sigma)
    if not math.isfinite(test) or test > 1.0:
        return x, P, UpdateInfo(False, r, test)
    K = np.linalg.solve(S, PHt.T).T
    IKH = np.eye(len(P)) - K @ H
    Pn = IKH @ P @ IKH.T + K @ Rm @ K.T
    return inject_error(x, K @ r), 0.5 * (Pn + Pn.T), UpdateInfo(True, r, test)


def _update_block(x, P, r, block: slice, Rm, gate_sigma: float):
    """:func:`_update` for ``H`` selecting the error-state ``block`` (GPS, attitude).

    Same Joseph form without forming ``H``: ``P H^T = P[:, b]``, ``S = P[b, b] + R``,
    ``A = (I - K H) P = P - K P[b, :]`` and ``A (I - K H)^T = A - A[:, b] K^T``.
    """
    PHt = P[:, block]
    S = PHt[block] + Rm
    test = _gate(r, np.diag(S), gate_sigma)
    if not math.isfinite(test) or test > 1.0:
        return x, P, UpdateInfo(False, r, test)
    K = np.linalg.solve(S, PHt.T).T
    A = P - K @ P[block]
    Pn = A - A[:, block] @ K.T + K @ Rm @ K.T
    return inject_error(x, K @ r), 0.5 * (Pn + Pn.T), UpdateInfo(True, r, test)


def attitude_variance(config: EkfConfig) -> float | np.ndarray:
    """The attitude reference's variance as :func:`ekf_update_attitude` takes it: the scalar
    ``att_var_rad2``, or per world axis ``[tilt, tilt, yaw]`` when the heading has its own."""
    if config.att_yaw_var_rad2 is None:
        return config.att_var_rad2
    return np.array([config.att_var_rad2, config.att_var_rad2, config.att_yaw_var_rad2])


def _as_cov(var, dim: int) -> np.ndarray:
    """Scalar, per-axis vector or full matrix variance as a (dim, dim) matrix."""
    a = np.asarray(var, dtype=float)
    if a.ndim == 0:
        return float(a) * np.eye(dim)
    if a.ndim == 1:
        return np.diag(a)
    return a


def _check_meas(z, name: str, size: int) -> np.ndarray:
    a = np.asarray(z, dtype=float)
    if a.shape != (size,) or not np.isfinite(a).all():
        raise ValueError(f"{name}: expected {size} finite numbers, got {a!r}")
    return a


def ekf_update_position(x, P, pos_w_m, var_m2, gate_sigma: float = 5.0):
    """GPS position update (world frame, metres)."""
    return _position(x, P, pos_w_m, var_m2, gate_sigma, _NUMPY)


def _position(x, P, pos_w_m, var_m2, gate_sigma, la):
    z = _check_meas(pos_w_m, "position", 3)
    return la.block(x, P, z - x[X_P], E_P, _as_cov(var_m2, 3), gate_sigma)


def ekf_reset_position(x, P, pos_w_m, var_m2):
    """Reset the position to a fix (a discontinuity, as EKF2's ``resetHorizontalPositionTo``):
    ``p = pos``, its covariance the fix's, its correlations with the rest of the state zero."""
    x = np.array(x, dtype=float)
    P = np.array(P, dtype=float)
    x[X_P] = np.asarray(pos_w_m, dtype=float)
    P[E_P, :] = 0.0
    P[:, E_P] = 0.0
    P[E_P, E_P] = _as_cov(var_m2, 3)
    return x, P


def ekf_update_velocity(x, P, vel_w_m_s, var_m2_s2, gate_sigma: float = 5.0):
    """GPS velocity update (world frame, m/s)."""
    return _velocity(x, P, vel_w_m_s, var_m2_s2, gate_sigma, _NUMPY)


def _velocity(x, P, vel_w_m_s, var_m2_s2, gate_sigma, la):
    z = _check_meas(vel_w_m_s, "velocity", 3)
    return la.block(x, P, z - x[X_V], E_V, _as_cov(var_m2_s2, 3), gate_sigma)


def ekf_update_attitude(x, P, q_meas_wxyz, var_rad2, gate_sigma: float = 5.0):
    """Attitude reference update from a measured quaternion (AHRS-like).

    Residual is the world-frame rotation vector from the estimate to the measurement,
    so ``H = [0 0 I 0 0]``; ``var_rad2`` is per axis.
    """
    return _attitude(x, P, q_meas_wxyz, var_rad2, gate_sigma, _NUMPY)


def _attitude(x, P, q_meas_wxyz, var_rad2, gate_sigma, la):
    z = quat_normalize(_check_meas(q_meas_wxyz, "attitude quaternion", 4))
    return la.block(x, P, attitude_error(z, x[X_Q]), E_TH, _as_cov(var_rad2, 3), gate_sigma)


def heading_jacobian(q_wxyz) -> np.ndarray:
    """``d yaw / d dtheta`` (1x3) for yaw = atan2(R10, R00) and world-frame errors.

    With ``R <- (I + S(dtheta)) R``: ``dR00 = -R10 dth_z + R20 dth_y`` and
    ``dR10 = R00 dth_z - R20 dth_x``, so
    ``d yaw = (-R20 R00 dth_x - R20 R10 dth_y + (R00^2 + R10^2) dth_z) / (R00^2 + R10^2)``.
    """
    R = quat_to_rotmat(q_wxyz)
    h = R[0, 0] ** 2 + R[1, 0] ** 2
    return np.array([-R[2, 0] * R[0, 0] / h, -R[2, 0] * R[1, 0] / h, 1.0])


def ekf_update_heading(x, P, yaw_rad: float, var_rad2: float, gate_sigma: float = 5.0):
    """Heading (magnetometer-like) update: yaw of the body x axis about world z."""
    return _heading(x, P, yaw_rad, var_rad2, gate_sigma, _NUMPY)


def _heading(x, P, yaw_rad, var_rad2, gate_sigma, la):
    if not math.isfinite(yaw_rad):
        raise ValueError(f"heading: expected a finite angle, got {yaw_rad!r}")
    R = quat_to_rotmat(x[X_Q])
    if R[0, 0] ** 2 + R[1, 0] ** 2 < 1e-6:
        # Body x axis vertical: heading undefined, skip rather than divide by zero.
        return x, P, UpdateInfo(False, np.array([0.0]), math.inf)
    yaw_hat = math.atan2(R[1, 0], R[0, 0])
    r = np.array([(yaw_rad - yaw_hat + math.pi) % (2.0 * math.pi) - math.pi])
    H = np.zeros((1, NE))
    H[0, E_TH] = heading_jacobian(x[X_Q])
    return la.rows(x, P, r, H, np.array([[var_rad2]]), gate_sigma)


def ekf_add_baro_offset(x, P, baro_height_m: float, var_m2: float):
    """Reference the barometer: append its offset ``b = h_baro - z`` to the state (PX4's baro height
    offset, taken against the current height estimate) with the covariance of that choice: the
    offset's error is minus the height's error (plus the sample's noise ``var_m2``), so the
    barometer adds no knowledge of the absolute height."""
    if len(x) != NX:
        raise ValueError("the barometer is already referenced")
    if not math.isfinite(baro_height_m):
        raise ValueError(f"barometric height: expected a finite number, got {baro_height_m!r}")
    xa = np.concatenate((x, [baro_height_m - x[X_P][2]]))
    Pa = np.zeros((NE_BARO, NE_BARO))
    Pa[:NE, :NE] = P
    row = -P[E_PZ, :]
    Pa[E_BARO, :NE] = row
    Pa[:NE, E_BARO] = row.T
    Pa[E_BARO, E_BARO] = P[E_PZ, E_PZ] + var_m2
    return xa, Pa


def ekf_remove_baro_offset(x, P):
    """The state without the barometer's offset (it is taken again at the next sample)."""
    return np.array(x[:NX], dtype=float), np.array(P[:NE, :NE], dtype=float)


def ekf_update_baro(x, P, baro_height_m: float, var_m2: float, gate_sigma: float = 5.0,
                    deadzone_m: float = 0.0):
    """Barometric height update: ``h_baro = z + b`` (scalar; ``b`` from :func:`ekf_add_baro_offset`).

    ``deadzone_m`` > 0 (in the rotors' ground effect, where the barometer reads low): an
    innovation between ``-deadzone_m`` and 0 becomes 0, a lower one ``deadzone_m`` less negative
    (PX4's EKF2_GND_EFF_DZ)."""
    return _baro(x, P, baro_height_m, var_m2, gate_sigma, deadzone_m, _NUMPY)


def _baro(x, P, baro_height_m, var_m2, gate_sigma, deadzone_m, la):
    if len(x) != NX_BARO:
        raise ValueError("the barometer is not referenced yet (ekf_add_baro_offset)")
    if not math.isfinite(baro_height_m):
        raise ValueError(f"barometric height: expected a finite number, got {baro_height_m!r}")
    r = baro_height_m - x[X_P][2] - x[X_BARO][0]
    if deadzone_m > 0.0 and r < 0.0:
        r = min(r + deadzone_m, 0.0)
    H = np.zeros((1, NE_BARO))
    H[0, E_PZ] = 1.0
    H[0, E_BARO] = 1.0
    return la.rows(x, P, np.array([r]), H, np.array([[var_m2]]), gate_sigma)


def mag_heading_jacobian(q_wxyz, mag_b_gauss) -> np.ndarray:
    """``d phi / d dtheta`` (3,) of the horizontal direction ``phi = atan2(m_y, m_x)`` of the field
    ``m = R(q) m_b`` rotated into the world, for world-frame attitude errors.

    With ``R <- (I + S(dtheta)) R``: ``dm = dtheta x m``, so ``dm_x = dth_y m_z - dth_z m_y``,
    ``dm_y = dth_z m_x - dth_x m_z`` and ``d phi = (m_x dm_y - m_y dm_x) / (m_x^2 + m_y^2)
    = dth_z - (m_x m_z dth_x + m_y m_z dth_y) / (m_x^2 + m_y^2)``: a tilt error turns the
    measured heading through the field's inclination (:func:`heading_jacobian`'s form, with the
    field in place of the body x axis).
    """
    m = quat_to_rotmat(q_wxyz) @ np.asarray(mag_b_gauss, dtype=float)
    h = m[0] ** 2 + m[1] ** 2
    return np.array([-m[0] * m[2] / h, -m[1] * m[2] / h, 1.0])


def ekf_update_mag_heading(x, P, mag_b_gauss, declination_rad: float, var_rad2: float,
                           gate_sigma: float = 5.0):
    """Magnetometer heading update: the measured body-frame field (FLU, any unit), rotated into
    the world with the estimated attitude (tilt compensation), must point along the earth's
    horizontal field, ``declination_rad`` east of north (in ENU at ``pi/2 - declination`` from
    east). Residual: that angle minus the rotated field's, wrapped; Jacobian
    :func:`mag_heading_jacobian`; skipped (not accepted) when the field is nearly vertical."""
    return _mag_heading(x, P, mag_b_gauss, declination_rad, var_rad2, gate_sigma, _NUMPY)


def _mag_heading(x, P, mag_b_gauss, declination_rad, var_rad2, gate_sigma, la):
    mb = _check_meas(mag_b_gauss, "magnetic field", 3)
    m = quat_to_rotmat(x[X_Q]) @ mb
    h = m[0] ** 2 + m[1] ** 2
    if not h > 1e-4 * float(mb @ mb):  # within 0.6 deg of vertical (or no field): no heading
        return x, P, UpdateInfo(False, np.array([0.0]), math.inf)
    phi_earth = 0.5 * math.pi - declination_rad
    r = np.array([(phi_earth - math.atan2(m[1], m[0]) + math.pi) % (2.0 * math.pi) - math.pi])
    H = np.zeros((1, len(P)))
    H[0, E_TH] = (-m[0] * m[2] / h, -m[1] * m[2] / h, 1.0)
    return la.rows(x, P, r, H, np.array([[var_rad2]]), gate_sigma)


def sckf_view(x, P, gyro_b_rad_s, gps_bias_var_m2=(0.0, 0.0)):
    """What the link reports to the companion: ``(p, v, q, omega_b, P9)``.

    ``omega_b`` is the bias-corrected body rate (input of eq. 3), ``P9`` the covariance of
    ``[p~; v~; dtheta]``, its position block plus the GNSS bias the filter does not estimate
    (``EkfConfig.gps_bias_var_m2``: horizontal, vertical).
    """
    omega = np.asarray(gyro_b_rad_s, dtype=float) - x[X_BG]
    P9 = P[E_SCKF, E_SCKF].copy()
    h, v = gps_bias_var_m2
    if h or v:
        P9[E_P, E_P] += np.diag((h, h, v))
    return x[X_P].copy(), x[X_V].copy(), x[X_Q].copy(), omega, P9


class _Linalg:
    """The linear algebra of an EKF step: the numpy specification (``_NUMPY``: :func:`ekf_predict`,
    :func:`_update_block`, :func:`_update`) or the compiled kernels beside it (``_COMPILED``,
    :mod:`._fast`). The measurement models (residuals, Jacobians, gates' inputs) are written once,
    in the ``ekf_update_*`` functions, and take one of the two."""

    def __init__(self, predict, block, rows):
        self.predict, self.block, self.rows = predict, block, rows


_GRAVITY_W = np.array(GRAVITY_W_M_S2, dtype=float)


def _predict_compiled(x, P, gyro_b_rad_s, accel_b_m_s2, dt_s: float, noise: EkfNoise):
    """:func:`ekf_predict` by :func:`._fast.ekf_predict_kernel`."""
    if not dt_s > 0.0:
        raise ValueError(f"dt_s must be positive, got {dt_s!r}")
    return _fast.ekf_predict_kernel(x, P, np.asarray(gyro_b_rad_s, dtype=float), np.asarray(accel_b_m_s2, dtype=float),
                                    float(dt_s), noise.densities, noise.baro_bias_m2_s, _GRAVITY_W)


def _update_block_compiled(x, P, r, block: slice, Rm, gate_sigma: float):
    """:func:`_update_block` by :func:`._fast.update_block_kernel`."""
    xn, Pn, accepted, test = _fast.update_block_kernel(x, P, r, block.start, Rm, float(gate_sigma))
    return (xn, Pn, UpdateInfo(True, r, test)) if accepted else (x, P, UpdateInfo(False, r, test))


def _update_compiled(x, P, r, H, Rm, gate_sigma: float):
    """:func:`_update` by :func:`._fast.update_rows_kernel`."""
    xn, Pn, accepted, test = _fast.update_rows_kernel(x, P, r, H, Rm, float(gate_sigma))
    return (xn, Pn, UpdateInfo(True, r, test)) if accepted else (x, P, UpdateInfo(False, r, test))


_NUMPY = _Linalg(ekf_predict, _update_block, _update)
_COMPILED = _Linalg(_predict_compiled, _update_block_compiled, _update_compiled)


@lru_cache(maxsize=32)
def _covariances(config: EkfConfig) -> dict[str, np.ndarray]:
    """The measurement covariances of a (frozen) config as the updates take them, made once."""
    return {"att": _as_cov(attitude_variance(config), 3)}


class LinkEkf:
    """Stateful wrapper around the functional EKF, as run on one simulated Pixhawk.

    Counts accepted and rejected (gated) measurements per kind. ``compiled`` (default: when numba
    is installed, :data:`._fast.ENABLED`) runs the compiled kernels of :mod:`._fast` instead of the
    numpy functions (same numbers to rounding: ``tests/test_fast_paths.py``).
    """

    def __init__(self, p_w_m, v_w_m_s, q_wxyz, config: EkfConfig = EkfConfig(), compiled: bool | None = None):
        self.config = config
        self._la = _COMPILED if (_fast.ENABLED if compiled is None else compiled) else _NUMPY
        self.x, self.P = ekf_init(p_w_m, v_w_m_s, q_wxyz, config)
        self.last_gyro_b_rad_s = np.zeros(3)
        kinds = ("pos", "vel", "att", "heading", "baro", "mag")
        self.accepted: dict[str, int] = dict.fromkeys(kinds, 0)
        self.rejected: dict[str, int] = dict.fromkeys(kinds, 0)
        #: state resets (discontinuities), reported as the link state's reset_counter
        self.resets = 0

    def predict(self, gyro_b_rad_s, accel_b_m_s2, dt_s: float) -> None:
        self.x, self.P = self._la.predict(self.x, self.P, gyro_b_rad_s, accel_b_m_s2, dt_s, self.config.noise)
        self.last_gyro_b_rad_s = np.asarray(gyro_b_rad_s, dtype=float).copy()

    def _record(self, kind: str, result) -> UpdateInfo:
        self.x, self.P, info = result
        (self.accepted if info.accepted else self.rejected)[kind] += 1
        return info

    def update_position(self, pos_w_m) -> UpdateInfo:
        cfg = self.config
        return self._record("pos", _position(self.x, self.P, pos_w_m, cfg.gps_pos_var_m2, cfg.gate_sigma, self._la))

    def position_test_ratio(self, pos_w_m) -> float:
        """The gate's test ratio of a position fix (above 1: it would be rejected), no update."""
        S = self.P[E_P, E_P] + _as_cov(self.config.gps_pos_var_m2, 3)
        r = np.asarray(pos_w_m, dtype=float) - self.x[X_P]
        return _gate(r, np.diag(S), self.config.gate_sigma)

    def reset_position(self, pos_w_m) -> None:
        """Reset the position to a fix; the barometer is referenced again at its next sample."""
        self.x, self.P = ekf_remove_baro_offset(self.x, self.P)
        self.x, self.P = ekf_reset_position(self.x, self.P, pos_w_m, self.config.gps_pos_var_m2)
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
        return self._record("baro", _baro(self.x, self.P, baro_height_m, cfg.baro_var_m2, cfg.gate_sigma, deadzone,
                                          self._la))

    def update_mag(self, mag_b_gauss) -> UpdateInfo:
        """A magnetometer sample (body FLU) as a heading (:func:`ekf_update_mag_heading`)."""
        cfg = self.config
        return self._record("mag", _mag_heading(self.x, self.P, mag_b_gauss, cfg.mag_declination_rad,
                                                cfg.mag_heading_var_rad2, cfg.gate_sigma, self._la))

    def update_velocity(self, vel_w_m_s) -> UpdateInfo:
        cfg = self.config
        return self._record(
            "vel", _velocity(self.x, self.P, vel_w_m_s, cfg.gps_vel_var_m2_s2, cfg.gate_sigma, self._la)
        )

    def update_attitude(self, q_meas_wxyz) -> UpdateInfo:
        cfg = self.config
        if self._la is _COMPILED:  # the measurement model too in one kernel (50 Hz per link)
            q = np.asarray(q_meas_wxyz, dtype=float)
            if q.shape != (4,):
                _check_meas(q, "attitude quaternion", 4)
            x, P, status, test, r = _fast.attitude_update_kernel(self.x, self.P, q, *self.attitude_kernel_args(),
                                                                 X_Q.start, E_TH.start)
            if status < 0:
                quat_normalize(_check_meas(q, "attitude quaternion", 4))  # raises the specification's error
            return self._record("att", (x, P, UpdateInfo(status == 1, r, test)))
        return self._record("att", _attitude(self.x, self.P, q_meas_wxyz, attitude_variance(cfg), cfg.gate_sigma,
                                             self._la))

    def attitude_kernel_args(self) -> tuple[np.ndarray, float]:
        """The measurement covariance and the gate :meth:`update_attitude` passes to
        :func:`._fast.attitude_update_kernel`, for the kernels that fuse an attitude reference
        inside a tick (:func:`._fast.hil_tick_kernel`)."""
        return _covariances(self.config)["att"], float(self.config.gate_sigma)

    def count_attitude(self, accepted: int, rejected: int) -> None:
        """Attitude references those kernels fused, counted as :meth:`update_attitude` counts them."""
        self.accepted["att"] += accepted
        self.rejected["att"] += rejected

    def update_heading(self, yaw_rad: float) -> UpdateInfo:
        cfg = self.config
        return self._record(
            "heading", _heading(self.x, self.P, yaw_rad, cfg.heading_var_rad2, cfg.gate_sigma, self._la)
        )

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

"""The EKF's state layout, its tuning and an update's outcome (paper eq. 2's filter, :mod:`.ekf`).

Nominal state ``x = [p; v; q; b_a; b_g]`` (16 numbers): world-frame position [m] and velocity
[m/s] of the link centre, body-to-world attitude (Hamilton, w first), accelerometer bias [m/s^2]
and gyro bias [rad/s] (body frame). Error state ``dx = [dp; dv; dtheta; db_a; db_g]`` (15
numbers), the world-frame attitude error (DESIGN.md sec. 4). The first 9 error states are the
paper's ``[p~; v~; dtheta]`` (the SCKF's per-link error state). Once a barometer has referenced its
offset, both grow by it (``X_BARO``, ``E_BARO``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from companion.estimation.chain import ERR_DIM, ERR_P, ERR_TH, ERR_V

from ..geo import MAG_DECLINATION_RAD

__all__ = ["X_P", "X_V", "X_Q", "X_BA", "X_BG", "NX", "E_P", "E_V", "E_TH", "E_BA", "E_BG", "E_SCKF", "NE", "E_PZ",
           "X_BARO", "E_BARO", "NX_BARO", "NE_BARO", "EkfNoise", "EkfConfig", "UpdateInfo"]

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

    ``att_reset_rejections`` / ``vel_reset_rejections``: after that many attitude references /
    GPS velocities in a row rejected by the gate, the next one resets the attitude / velocity to
    it (the estimate has run off, e.g. on a stuck gyro, and would reject every one from then on;
    EKF2 resets the velocity to GNSS when its fusion times out, ``resetVelocityToGnss``); 0: never.
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
    att_reset_rejections: int = 25
    vel_reset_rejections: int = 10

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
        for name in ("att_reset_rejections", "vel_reset_rejections"):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, int) or val < 0:
                raise ValueError(f"EkfConfig.{name} must be a whole number >= 0, got {val!r}")
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

"""Typed messages between the link firmware and the companion (one schema for every wire).

Frames and units are in the field names: ``_w`` is the world frame of the estimation core
(z-up; MAVLink's NED appears only in the MAVLink codec), ``_b`` the link body frame (x along
the link towards its right tip). Times are the link's flight-controller clock [s].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LinkState", "Correction"]


@dataclass(frozen=True)
class LinkState:
    """A link's EKF output as reported to its companion (paper: state and 9x9 covariance).

    Attributes:
        link: 0-based link index in the chain.
        time_s: EKF time of the estimate.
        p_w_m, v_w_m_s: position and velocity of the link centre.
        q_wxyz: body-to-world attitude.
        omega_b_rad_s: bias-corrected body rate (input of eq. 3).
        P: (9, 9) covariance of ``[dp_w; dv_w; dtheta_w]``.
    """

    link: int
    time_s: float
    p_w_m: np.ndarray
    v_w_m_s: np.ndarray
    q_wxyz: np.ndarray
    omega_b_rad_s: np.ndarray
    P: np.ndarray


@dataclass(frozen=True)
class Correction:
    """Constraint correction for one link: corrected estimate minus EKF estimate.

    The link adds it to its EKF output for control only (never to the EKF itself: paper
    sec. III-A), holding it between companion cycles and fading it out when stale.

    Attributes:
        link: 0-based link index.
        ekf_time_s: the EKF time of the state it was computed against.
        dp_w_m, dv_w_m_s: position and velocity corrections.
        dtheta_w_rad: world-frame attitude correction, ``q_corr = dq(dtheta) (x) q_ekf``.
        seq: companion cycle counter.
    """

    link: int
    ekf_time_s: float
    dp_w_m: np.ndarray
    dv_w_m_s: np.ndarray
    dtheta_w_rad: np.ndarray
    seq: int = 0

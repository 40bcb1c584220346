"""What estimates on one simulated Pixhawk: the per-link EKF (paper eq. 2) and the GPS's health.

* :mod:`.ekf_config`: the EKF's state layout, tuning and an update's outcome;
* :mod:`.ekf`: the EKF's functional core, the readable specification of its kernels;
* :mod:`.link_ekf`: :class:`LinkEkf`, the stateful filter, with the one dispatch between the
  specification and the kernels (:mod:`link_firmware_sim.kernels.ekf`);
* :mod:`.tunings`: named tunings for the simulator's sensor profiles;
* :mod:`.gps_health`: the GPS fault and reset logic around the EKF's position fixes.

The names most callers need are here too.
"""

from .ekf_config import (E_BA, E_BARO, E_BG, E_P, E_PZ, E_SCKF, E_TH, E_V, NE, NE_BARO, NX, NX_BARO, X_BA, X_BARO,
                         X_BG, X_P, X_Q, X_V, EkfConfig, EkfNoise, UpdateInfo)
from .gps_health import GpsHealth, GpsHealthConfig
from .link_ekf import LinkEkf
from .tunings import EKF_TUNINGS, m8_ekf_config, outdoor_ekf_config, paper_ekf_config, rtk_ekf_config

__all__ = ["X_P", "X_V", "X_Q", "X_BA", "X_BG", "NX", "E_P", "E_V", "E_TH", "E_BA", "E_BG", "E_SCKF", "NE", "E_PZ",
           "X_BARO", "E_BARO", "NX_BARO", "NE_BARO", "EkfNoise", "EkfConfig", "UpdateInfo", "LinkEkf", "GpsHealth",
           "GpsHealthConfig", "EKF_TUNINGS", "outdoor_ekf_config", "m8_ekf_config",
           "paper_ekf_config", "rtk_ekf_config"]

"""The companion's corrected position aiding a link's EKF while its GPS is in fault
(link_firmware_sim.estimators.correction_aid): a correction is rebased on the moves made since its
state, a dead-reckoning link stays where its corrections put it and its correction stays small;
without the aid the correction grows past the firmware's bound."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from companion.messages import Correction
from link_firmware_sim.estimators.correction_aid import CorrectionAid
from link_firmware_sim.estimators.ekf_config import X_P
from link_firmware_sim.estimators.gps_health import GpsHealthConfig
from link_firmware_sim.firmware import CorrectionRejected, FirmwareConfig

from .test_gps_health import GRAVITY_UP, _hovering_firmware


class _Ekf:
    """An EKF stand-in whose external position update moves it by half the innovation."""

    def __init__(self):
        self.x = np.zeros(16)
        self.x[6] = 1.0

    def update_external_position(self, pos_w_m, var_m2):
        self.x[X_P] += 0.5 * (np.asarray(pos_w_m) - self.x[X_P])
        return type("Info", (), {"accepted": True})()


def _correction(ekf_time_s, dp):
    return Correction(0, ekf_time_s, np.asarray(dp, dtype=float), np.zeros(3), np.zeros(3))


def test_a_correction_is_rebased_on_the_moves_made_since_its_state():
    aid, ekf = CorrectionAid(0.2), _Ekf()
    out = aid.fuse(ekf, 1.0, _correction(0.95, [1.0, 0.0, 0.0]))
    np.testing.assert_allclose(ekf.x[X_P], [0.5, 0.0, 0.0])
    np.testing.assert_allclose(out.dp_w_m, [0.5, 0.0, 0.0])  # EKF + dp unchanged for control
    # computed against a state from before the move (at the move's own time too): the move taken off
    for stamp in (0.98, 1.0):
        np.testing.assert_allclose(aid.rebase(_correction(stamp, [1.0, 0.0, 0.0])).dp_w_m, [0.5, 0.0, 0.0])
    later = _correction(1.002, [0.5, 0.0, 0.0])
    assert aid.rebase(later) is later  # computed against the moved EKF: as it came
    with pytest.raises(ValueError):
        CorrectionAid(-1.0)


@pytest.mark.parametrize("aid_std_m", [0.2, 0.0], ids=["aided", "not_aided"])
def test_a_dead_reckoning_link_stays_where_its_corrections_put_it(aid_std_m):
    """A still link whose GPS is lost at 1 s and whose accelerometer reads 0.05 m/s^2 off (its EKF
    drifts 2.5 m in 10 s), corrected at 20 Hz by a companion that knows where it is, the
    corrections computed against the state of one cycle earlier: aided, the EKF stays within
    0.3 m of the link and every correction under 0.3 m; not aided, the corrections grow past the
    2 m bound and are refused."""
    fw, q = _hovering_firmware(FirmwareConfig(gps=GpsHealthConfig(aid_std_m=aid_std_m)))
    rng = np.random.default_rng(4)
    accel = GRAVITY_UP + np.array([0.05, 0.0, 0.0])
    states = deque(maxlen=2)  # (time, EKF position) as sent, one cycle's way to the companion
    largest, refused = 0.0, 0
    for k in range(1, 12 * 500):
        t = k / 500
        if k % 50 == 0 and t < 1.0:
            fw.on_gps(t, rng.normal(0, 0.05, 3), np.zeros(3))
        if k % 10 == 0:
            fw.on_attitude(t, q)
        if k % 25 == 0:
            if len(states) == 2:
                stamp, p_sent = states[0]
                dp = -p_sent + rng.normal(0, 0.02, 3)  # the link is at the origin
                try:
                    fw.on_correction(t, _correction(stamp, dp))
                    largest = max(largest, float(np.linalg.norm(fw.correction.dp_w_m))) if t > 2.0 else largest
                except CorrectionRejected:
                    refused += 1
            states.append((fw.time_s, fw.ekf.x[X_P].copy()))
        fw.on_imu(t, np.zeros(3), accel)
    assert fw.gps_health.fault
    if aid_std_m:
        assert np.linalg.norm(fw.ekf.x[X_P]) < 0.3 and largest < 0.3 and refused == 0
        assert fw.ekf.accepted["ext_pos"] > 150
    else:
        assert refused > 0 and fw.ekf.accepted["ext_pos"] == 0 and np.linalg.norm(fw.ekf.x[X_P]) > 2.0

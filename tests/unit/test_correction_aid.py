"""The companion's corrected position aiding a link's EKF while its GPS is in fault
(link_firmware_sim.estimators.correction_aid): a correction is rebased on the moves made since its
state, a dead-reckoning link stays where its corrections put it and its correction stays small;
without the aid the correction grows past the firmware's bound."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

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


@pytest.mark.parametrize("case", ["gps_fault", "gps_healthy", "aid_off", "jumping"])
def test_a_link_that_dead_reckoned_alone_is_reset_to_the_chains_view(case):
    """A still link whose accelerometer reads 0.1 m/s^2 off gets no corrections for 8 s (alone:
    its neighbours unheard) and dead-reckons past the 2 m bound; then the corrections (where the
    chain says it is: the origin) come back. In a GPS fault with the aid on, they are refused for
    SKL_GPS_AID_RST (0.5 s), then the position and velocity are reset to the corrected ones (one
    "reset" event) and the corrections are accepted and small again. With its GPS healthy, or the
    aid off, they are refused throughout and the estimate is not moved by them. Corrections whose
    corrected positions jump by up to 1 m per axis from one to the next (a glitching source, or a
    forger on an unsigned wire) never agree with each other: no reset, each one counted."""
    aid_std = 0.0 if case == "aid_off" else 0.2
    fw, q = _hovering_firmware(FirmwareConfig(gps=GpsHealthConfig(aid_std_m=aid_std)))
    rng = np.random.default_rng(7)
    accel = GRAVITY_UP + np.array([0.1, 0.0, 0.0])
    refused, accepted_after, first_refused, resets = 0, [], None, []
    for k in range(1, 14 * 500):
        t = k / 500
        if k % 50 == 0 and (t < 1.0 or case == "gps_healthy"):
            fw.on_gps(t, fw.ekf.x[X_P] + rng.normal(0, 0.02, 3), fw.ekf.x[3:6].copy())  # a GPS that follows it
        if k % 10 == 0:
            fw.on_attitude(t, q)
        if k % 25 == 0 and t >= 10.0:
            dp = -fw.ekf.x[X_P] + (rng.uniform(-1.0, 1.0, 3) if case == "jumping" else rng.normal(0, 0.02, 3))
            try:
                fw.on_correction(t, Correction(0, fw.time_s, dp, -fw.ekf.x[3:6].copy(), np.zeros(3)))
                if first_refused is not None:
                    accepted_after.append(float(np.linalg.norm(fw.correction.dp_w_m)))
            except CorrectionRejected:
                refused += 1
                first_refused = t if first_refused is None else first_refused
        fw.on_imu(t, np.zeros(3), accel)
        resets += [(t, e.text) for e in fw.events if e.kind == "reset" and "the chain" in e.text]
        fw.events.clear()
    if case == "gps_fault":
        assert fw.gps_health.fault
        assert len(resets) == 1 and resets[0][0] - first_refused == pytest.approx(0.5, abs=0.06), resets
        assert 9 <= refused <= 11 and len(accepted_after) > 50 and max(accepted_after) < 0.3
        assert np.linalg.norm(fw.ekf.x[X_P]) < 0.3 and fw.correction_aid.resets == 1
        assert fw.gps_report(t)["chain"] == {"resets": 1, "disagreed": 0}
    elif case == "jumping":
        assert fw.gps_health.fault and not resets and fw.correction_aid.resets == 0
        assert fw.correction_aid.disagreed > 60 and np.linalg.norm(fw.ekf.x[X_P]) > 2.0
    else:
        assert not resets and len(accepted_after) == 0 and refused == 80
        assert fw.correction_aid.resets == 0


@given(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(0.01, 1.0), st.floats(-1.0, 1.0))
def test_refused_corrections_agree_when_their_track_is_coherent(v0, v1, dt, miss):
    """A corrected position agrees with the last one carried forward by the mean of the two
    velocities when it is within std_m (0.2 m) of it, whatever the velocities and the time between
    them; a state time not after the last one's never agrees."""
    aid = CorrectionAid(0.2)
    p0, vel0, vel1 = np.array([1.0, -2.0, 2.5]), np.array([v0, 0.0, 0.0]), np.array([v1, 0.0, 0.0])
    p1 = p0 + 0.5 * (vel0 + vel1) * dt + np.array([0.0, miss, 0.0])
    assert aid.agrees((5.0, p0, vel0), (5.0 + dt, p1, vel1)) == (abs(miss) <= 0.2)
    assert not aid.agrees((5.0, p0, vel0), (5.0, p0, vel0))

"""PSPM teleoperation in the firmware (thesis sec. 2.3.4): operator set poses modulated before the
slave law, over MAVLink (SET_POSITION_TARGET_LOCAL_NED / SET_ATTITUDE_TARGET) with the reservoirs streamed."""

from __future__ import annotations

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_euler_zyx
from companion.mavlink.dialect import load_dialect
from companion.mavlink.standard import encode_attitude_target, encode_position_target
from companion.messages import PoseTarget
from companion.skeleton.body import LinkInertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware
from link_firmware_sim.controllers import ImpedanceController
from link_firmware_sim.controllers.pspm import PspmSlave, pspm_init, pspm_update, slave_wrench
from link_firmware_sim.vehicle.streams.controller import PSPM_DEBUG_NAME

#: the kernels compiled (or loaded) before a vehicle here runs against a deadline
pytestmark = pytest.mark.usefixtures("compiled_kernels")

D = load_dialect()
INERTIA = LinkInertia(2.6, (0.05, 0.3, 0.3))
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])
GRAVITY_SPECIFIC_FORCE = np.array([0.0, 0.0, 9.80665])


def _armed(mode: str) -> LinkFirmware:
    fw = LinkFirmware(0, FirmwareConfig(pspm_mode=mode), INERTIA, RotorGeometry.odar())
    fw.initialize(0.0, np.array([0.0, 0.0, 2.0]), np.zeros(3), LEVEL)
    assert fw.arm(0.0)
    return fw


def test_firmware_modulates_an_operator_jump_as_the_functional_api_does():
    fw = _armed("on")
    jump = PoseTarget.hold(np.array([1.0, 0.0, 2.0]), quat_from_euler_zyx(np.radians(60.0), 0.0, 0.0))
    fw.set_target(0.002, jump)
    p, _, q = fw.control_estimate(0.002)
    gains = fw.config.pspm
    ref = pspm_update(pspm_init(p, q, gains, 0.002), gains, jump.p_w_m, jump.q_wxyz, p, q, 0.002)
    np.testing.assert_allclose(fw.target.p_w_m, ref.p_bar_w_m, atol=1e-12)
    np.testing.assert_allclose(fw.target.q_wxyz, ref.q_bar_wxyz, atol=1e-12)
    assert fw.operator_target is jump
    # at rest nothing dissipates: only the initial reservoir passes (0.4 J of the 11 N/m spring: 0.27 m)
    step = np.linalg.norm(fw.target.p_w_m - p)
    assert step == pytest.approx(np.sqrt(2 * gains.e0_t_j / gains.kp_n_m[0]), rel=1e-6)
    e_t, e_r, lag = fw.pspm_report()
    assert e_t == pytest.approx(0.0, abs=1e-9) and e_r >= 0.0 and lag == pytest.approx(1.0 - step)


def test_the_slave_law_drives_the_rotors_and_books_dissipation():
    fw = _armed("on")
    fw.set_target(0.002, PoseTarget.hold(np.array([1.0, 0.0, 2.0]), LEVEL))
    assert isinstance(fw.controller, PspmSlave) and fw.observer is None
    cmd = fw.on_imu(0.004, np.zeros(3), GRAVITY_SPECIFIC_FORCE)
    p, v, q = fw.control_estimate(0.004)
    U_ref = slave_wrench(p, v, q, np.zeros(3), fw.target.p_w_m, fw.target.q_wxyz, fw.config.pspm, INERTIA.mass_kg)
    assert U_ref[0] > 1.0  # the spring pulls towards +x (body x = world x, level)
    np.testing.assert_allclose(fw.allocator.mapping_matrix @ cmd, U_ref, atol=1e-9)  # what the rotors produce
    gyro = np.array([0.0, 0.0, 0.5])  # a yaw rate: the rotational damper dissipates K_w w^2 dt per tick
    for k in range(10):
        fw.on_imu(0.006 + 0.002 * k, gyro, GRAVITY_SPECIFIC_FORCE)
    assert fw.pspm.state.diss_r_j == pytest.approx(10 * fw.config.pspm.kw_nms[2] * 0.25 * 0.002, rel=0.05)


def test_bypass_passes_the_raw_set_pose_and_off_keeps_the_selected_controller():
    fw = _armed("bypass")
    jump = PoseTarget.hold(np.array([1.0, 0.0, 2.0]), LEVEL)
    fw.set_target(0.002, jump)
    assert fw.target is jump and fw.pspm is None and fw.pspm_report() is None
    off = _armed("off")
    assert isinstance(off.controller, ImpedanceController) and off.pspm is None  # eq. 1, untouched
    off.set_target(0.002, jump)
    assert off.target is jump
    with pytest.raises(ValueError, match="PSPM"):
        LinkFirmware(0, FirmwareConfig(controller="hybrid", pspm_mode="on"), INERTIA,
                     RotorGeometry.odar()).set_contact(0.0, None)


def test_vehicle_modulates_mavlink_set_poses_and_streams_the_reservoirs(rig):
    rig.start(0.1)
    rig.vehicle.set_param("SKL_PSPM_EN", 1)  # what a PARAM_SET does
    fw = rig.vehicle.fw
    assert fw.arm(rig.t)
    jump = PoseTarget.hold(np.array([1.0, 0.0, 2.0]), quat_from_euler_zyx(np.radians(60.0), 0.0, 0.0))
    rig.gcs_send(D.MAVLink_command_long_message(2, 1, D.MAV_CMD_SET_MESSAGE_INTERVAL, 0, D.MAVLINK_MSG_ID_DEBUG_VECT,
                                                20000, 0, 0, 0, 0, 0))
    rig.gcs_send(encode_position_target(jump, rig.vehicle.time_boot_ms, 2))
    rig.gcs_send(encode_attitude_target(jump, rig.vehicle.time_boot_ms, 2))
    msgs = rig.gcs_collect(0.1)
    np.testing.assert_allclose(fw.operator_target.p_w_m, jump.p_w_m, atol=1e-5)
    p, _, _ = fw.control_estimate(rig.t)
    assert 0.1 < np.linalg.norm(fw.target.p_w_m - p) < 0.3  # the reservoir's share of the 1 m jump, not all of it
    vec = [m for m in msgs if m.get_type() == "DEBUG_VECT"]
    assert vec and vec[-1].name == PSPM_DEBUG_NAME.decode()
    assert vec[-1].x >= 0.0 and vec[-1].y >= 0.0 and 0.6 < vec[-1].z < 0.9  # reservoirs, lag of the set position
    logged = rig.vehicle.flight_log()["pspm"]  # E_t, E_r, lag per log row: NaN before PSPM's first sample
    assert np.isnan(logged[0]).all() and np.all(logged[-1][:2] >= 0.0) and logged[-1][2] > 0.6
    rig.vehicle.set_param("SKL_PSPM_EN", 0)
    assert fw.pspm is None and fw.pspm_report() is None

"""The PSPM jump scenario (sitl.scenarios.pspm_jump): config checks, the jump metrics, the jump
protocol on a rigid body as the oracle of the MuJoCo flight, a short MuJoCo flight."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.estimation.so3 import quat_from_euler_zyx, rotmat_to_quat
from companion.skeleton.body import GRAVITY_M_S2, SkeletonConfig, link_inertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.controllers.pspm import (HapticGains, PspmGains, master_set_pose, pspm_init, pspm_observe,
                                                pspm_update, slave_wrench)
from sitl.scenarios.pspm_jump.config import TeleopConfig, load_teleop_scenario
from sitl.scenarios.pspm_jump.flight import heading_deg, jump_metrics, jump_runner

from ..rigid_body import rigid_body_step

CONFIG = "configs/sitl/odar/pspm_jump.toml"


@pytest.mark.parametrize("kwargs, match", [
    ({"jump_axis_w": (1.0, 1.0, 0.0)}, "jump_axis_w"),
    ({"jump_m": -1.0}, "jump_m"),
    ({"yaw_jump_deg": 200.0}, "yaw_jump_deg"),
    ({"jump_s": 12.0, "yaw_jump_s": 11.0}, "after jump_s"),
])
def test_teleop_config_is_validated(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TeleopConfig(**kwargs)


def test_scenario_rejects_a_jump_during_the_take_off():
    with pytest.raises(ValueError, match="take-off"):
        replace(load_teleop_scenario(CONFIG), teleop=TeleopConfig(jump_s=1.0))


@pytest.mark.parametrize("peak", [1.1, 1.3, 1.6])
def test_jump_metrics_of_a_response_with_a_known_overshoot_and_settling(peak):
    """Up to ``peak`` one second after the jump, straight back to 1 over the next second, then 1."""
    t = np.arange(0.0, 10.0, 0.001)
    jump_s, yaw_s = 2.0, 8.0
    along = np.interp(t, [0.0, jump_s, jump_s + 1.0, jump_s + 2.0, 10.0], [0.0, 0.0, peak, 1.0, 1.0])
    yaw = np.interp(t, [0.0, yaw_s, yaw_s + 0.5, 10.0], [0.0, 0.0, 70.0, 60.0])
    e = np.linspace(0.3, 0.0, t.size)
    m = jump_metrics(t, along, yaw, e, e, np.zeros_like(t), 1.0, jump_s, 60.0, yaw_s)
    assert m["overshoot_m"] == pytest.approx(peak - 1.0, abs=1e-3)
    # the last sample outside the 5 % band: where the way back crosses 1.05
    assert m["settling_time_5pct_s"] == pytest.approx(1.0 + (peak - 1.05) / (peak - 1.0), abs=2e-3)
    assert m["yaw_overshoot_deg"] == pytest.approx(10.0, abs=0.05)
    assert m["reservoir_min_j"]["E_t"] == pytest.approx(0.0, abs=1e-12)


def _rigid_jump(modulated: bool, duration_s=16.0, jump_m=1.0, yaw_jump_deg=60.0, t_jump=2.0, t_yaw=9.0,
                operator_hz=125.0, control_hz=500.0, rotor_tau_s=0.05) -> dict:
    """The scripted operator's jumps (the MuJoCo scenario's protocol) on one rigid link (2.7) whose
    rotors' wrench lags by ``rotor_tau_s``: the slave law of sec. 2.3.4 on the PSPM-modulated set
    pose (``modulated``) or on the raw one; the jump metrics of the flight."""
    inertia = link_inertia(SkeletonConfig(n_links=1, link_length_m=1.2, link_mass_kg=2.6), RotorGeometry.odar())
    # reservoirs start full (an empty one at rest never releases a jump: nothing dissipates); the
    # caps set how much of a jump passes at once (0.4 J: 0.27 m of the 1 m spring; 0.3 J: 18 deg)
    gains = PspmGains(e_max_t_j=0.4, e_max_r_j=0.3, e0_t_j=0.4, e0_r_j=0.3)
    haptic = HapticGains(p0_w_m=(0.0, 0.0, 2.0))
    dt, every = 1.0 / control_hz, int(round(control_hz / operator_hz))
    level = np.array([1.0, 0.0, 0.0, 0.0])
    p, v, R, w = np.array([0.0, 0.0, 2.0]), np.zeros(3), np.eye(3), np.zeros(3)
    p0 = p.copy()
    wrench = np.array([0.0, 0.0, inertia.mass_kg * GRAVITY_M_S2, 0.0, 0.0, 0.0])  # hovering
    state = pspm_init(p, rotmat_to_quat(R), gains, 0.0)
    rec = {k: [] for k in ("t", "along", "yaw", "e_t", "e_r", "speed")}
    for k in range(int(round(duration_s / dt))):
        t, q = k * dt, rotmat_to_quat(R)
        if k % every == 0:  # an operator sample
            p_h = np.array([jump_m if t >= t_jump else 0.0, 0.0, 0.0])
            q_h = quat_from_euler_zyx(np.radians(yaw_jump_deg) if t >= t_yaw else 0.0, 0.0, 0.0)
            p_bar, q_bar = master_set_pose(p_h, q_h, haptic)
            if modulated:
                state = pspm_update(state, gains, p_bar, q_bar, p, q, t)
                p_bar, q_bar = state.p_bar_w_m, state.q_bar_wxyz
            for key, value in (("t", t), ("along", p[0] - p0[0]), ("yaw", heading_deg(q, level)),
                               ("e_t", state.energy_t_j if modulated else np.nan),
                               ("e_r", state.energy_r_j if modulated else np.nan), ("speed", np.linalg.norm(v))):
                rec[key].append(value)
        U = slave_wrench(p, v, q, w, p_bar, q_bar, gains, inertia.mass_kg)
        wrench = wrench + (1.0 - np.exp(-dt / rotor_tau_s)) * (U - wrench)
        p, v, R, w = rigid_body_step(p, v, R, w, wrench, inertia, dt)
        if modulated:
            state = pspm_observe(state, gains, p, w, dt)
    return jump_metrics(rec["t"], rec["along"], rec["yaw"], rec["e_t"], rec["e_r"], rec["speed"], jump_m, t_jump,
                        yaw_jump_deg, t_yaw)


def test_on_a_rigid_body_pspm_takes_the_jumps_without_their_overshoot():
    """The oracle of the MuJoCo flight, without MuJoCo, firmware or EKF: on the rigid body the
    slave law alone overshoots both jumps and speeds; with PSPM both jumps settle with a third of
    the overshoot, the reservoirs never below zero."""
    raw, pspm = _rigid_jump(False), _rigid_jump(True)
    assert raw["settled_in_window"] and pspm["settled_in_window"]
    assert raw["overshoot_m"] > 0.25 and pspm["overshoot_m"] < 0.5 * raw["overshoot_m"]
    assert raw["yaw_overshoot_deg"] > 30.0 and pspm["yaw_overshoot_deg"] < 0.5 * raw["yaw_overshoot_deg"]
    assert pspm["max_speed_m_s"] < 0.5 * raw["max_speed_m_s"]
    assert pspm["final_error_m"] < 0.01 and pspm["yaw_final_error_deg"] < 1.0
    assert pspm["reservoir_min_j"]["E_t"] >= 0.0 and pspm["reservoir_min_j"]["E_r"] >= 0.0


def test_short_mujoco_flight_modulates_the_jump_and_keeps_the_reservoirs_non_negative():
    sc = load_teleop_scenario(CONFIG)
    sc = replace(sc, duration_s=4.5, teleop=replace(sc.teleop, jump_s=2.0, yaw_jump_s=3.8))
    runner = jump_runner(sc, "on")
    runner.run(sc.duration_s)
    lg = {k: np.asarray(v) for k, v in runner.task.teleop_log.items()}
    assert not runner.crashed, runner.crash_reason
    e = np.concatenate((lg["energy_t_j"], lg["energy_r_j"]))
    assert np.all(e[np.isfinite(e)] >= 0.0) and np.isfinite(lg["energy_t_j"]).mean() > 0.9
    after = lg["t"] >= 2.0
    first = np.argmax(after)
    assert lg["along_d_m"][first] == pytest.approx(1.0)
    assert 0.1 < lg["along_bar_m"][first] < 0.4  # the full reservoir's share of the 1 m spring, not all of it
    assert lg["f_h_n"][first][0] < -5.0  # the operator feels what PSPM withheld
    assert lg["along_true_m"][lg["t"] < 3.8][-1] > 0.2  # and the link is on its way
    yaw_after = lg["t"] >= 3.8
    assert 0.0 < lg["yaw_bar_deg"][np.argmax(yaw_after)] < 30.0  # the yaw jump is modulated too

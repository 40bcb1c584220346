"""The PSPM jump scenario in MuJoCo (sitl.teleop, issue 17): config checks, the jump metrics, a short flight."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from sitl.teleop import PspmJumpRunner, TeleopConfig, jump_metrics, load_teleop_scenario

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


def test_short_mujoco_flight_modulates_the_jump_and_keeps_the_reservoirs_non_negative():
    sc = load_teleop_scenario(CONFIG)
    sc = replace(sc, duration_s=4.5, teleop=replace(sc.teleop, jump_s=2.0, yaw_jump_s=3.8))
    runner = PspmJumpRunner(sc, "on")
    runner.run(sc.duration_s)
    lg = {k: np.asarray(v) for k, v in runner.teleop_log.items()}
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

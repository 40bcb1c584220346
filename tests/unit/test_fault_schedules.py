"""Random fault schedules (sitl.campaign.faults): seeded, playable, inside the flight; the
per-kind table and the recovery time."""

import numpy as np
import pytest

from sitl.campaign.fault_campaign import fault_specs, replay_command
from sitl.campaign.faults import (FLEET_ONLY, INJECTED, KINDS, FaultEvent, draw_schedule, event_figures, fault_table,
                                  markdown_fault_table, power_loss_near, recovery_s)
from sitl.scenarios import load

from ..paths import SITL_CONFIGS


@pytest.mark.parametrize("fleet, n_groups", [(False, 0), (True, 0), (True, 3)])
def test_schedules_are_seeded_inside_the_flight_and_only_of_kinds_the_mode_can_play(fleet, n_groups):
    draws = [draw_schedule(np.random.default_rng(seed), 7, 7.0, 40.0, fleet, n_groups) for seed in range(200)]
    again = [draw_schedule(np.random.default_rng(seed), 7, 7.0, 40.0, fleet, n_groups) for seed in range(200)]
    assert draws == again
    kinds = {e.kind for events, _ in draws for e in events}
    allowed = {k for k in KINDS if (fleet or k not in FLEET_ONLY) and (k != "companion_kill" or n_groups)}
    assert kinds == allowed  # every allowed kind drawn somewhere in 200 flights, no other
    for events, settings in draws:
        assert events and len({k for k, _ in settings}) == len(settings)
        assert sum(e.kind in ("gps_step", "gps_ramp", "gps_outage") for e in events) <= 1
        assert sum(e.kind in INJECTED for e in events) <= 1
        for e in events:
            assert 7.0 <= e.start_s < e.end_s <= 40.0
            assert e.end_s <= 37.0 or e.kind == "mavlink_loss"
            if e.kind not in ("mavlink_loss",):
                assert e.start_s >= 8.0 and e.start_s <= 32.0
    overlapping = sum(any(a.start_s < b.end_s and b.start_s < a.end_s for a in ev for b in ev if a is not b)
                      for ev, _ in draws)
    assert overlapping > 20  # faults overlap as they happen to


def test_no_room_for_faults_and_a_scenario_with_faults_are_clear_errors():
    with pytest.raises(ValueError, match="no room for faults"):
        draw_schedule(np.random.default_rng(0), 3, 7.0, 15.0, False)
    with pytest.raises(ValueError, match="scripts faults of its own"):
        fault_specs(str(SITL_CONFIGS / "faults" / "link_reboot.toml"), 3, 0, "fleet")


@pytest.mark.parametrize("name, mode", [("chain/three_link.toml", "batch"), ("chain/seven_link.toml", "fleet")])
def test_every_drawn_schedule_loads_as_a_scenario(name, mode):
    config = str(SITL_CONFIGS / name)
    specs, events = fault_specs(config, 25, seed=3, mode=mode)
    assert [s.key for s in specs] == [s.key for s in fault_specs(config, 25, seed=3, mode=mode)[0]]
    assert len({s.key for s in specs}) == 25
    for spec, ev in zip(specs, events):
        _, sc = load(spec.config, settings=dict(spec.settings), seed=spec.seed)
        reboot = [e for e in ev if e.kind == "link_reboot"]
        assert bool(sc.faults.link.kill) == bool(reboot)
        if reboot:
            assert sc.faults.link.kill == reboot[0].target
            assert sc.faults.link.kill_at_s == pytest.approx(reboot[0].start_s, abs=1e-3)
        assert bool(sc.faults.fleet_only) == any(e.kind in FLEET_ONLY for e in ev)
        injected = [e for e in ev if e.kind in INJECTED]
        assert sc.faults.inject.link == (injected[0].target if injected else 0)
        assert f"--seed {spec.seed}" in replay_command(spec)
        assert replay_command(spec).startswith("python -m sitl fly " if mode == "batch" else
                                               "python -m sitl launch --speed 0.0 ")


def test_a_paced_fault_campaign_replays_its_crashes_at_that_pace():
    config = str(SITL_CONFIGS / "chain" / "three_link.toml")
    specs, _ = fault_specs(config, 3, seed=3, mode="fleet", speed=1.0)
    unpaced, _ = fault_specs(config, 3, seed=3, mode="fleet")
    assert [s.settings for s in specs] == [s.settings for s in unpaced]  # the same schedules
    assert all(s.speed == 1.0 and replay_command(s).startswith("python -m sitl launch --speed 1.0 ") for s in specs)
    with pytest.raises(ValueError, match="batch mode has no pace"):
        fault_specs(config, 3, seed=3, mode="batch", speed=1.0)


def test_recovery_is_the_time_until_every_link_tracks_again():
    t = np.arange(0.0, 10.0, 0.1)
    err = np.full((t.size, 2), 0.05)
    err[(t >= 3.0) & (t < 6.0), 1] = 1.0  # link 2 off until 6 s
    err[(t >= 6.0) & (t < 6.5), 1] = np.nan  # no estimate for a moment: not recovered
    assert recovery_s(t, err, 5.0) == pytest.approx(1.5, abs=1e-9)
    assert recovery_s(t, err, 7.0) == 0.0
    err[-1, 0] = 2.0
    assert recovery_s(t, err, 5.0) is None  # off at the end of the log
    assert recovery_s(t, err, 20.0) is None


def test_each_fault_is_measured_in_its_own_window():
    t = np.arange(0.0, 30.0, 0.1)
    p_true = np.zeros((t.size, 3, 3))
    p_target = np.zeros_like(p_true)
    p_true[(t >= 10.0) & (t < 14.0), 1, 0] = 0.6  # link 2 off while the fault lasts, back 1 s after
    steps = {"t_sckf": t[::5], "con_pos_after": np.full((t[::5].size, 2), 0.002),
             "corrected_sckf": np.ones((t[::5].size, 3), dtype=bool)}
    steps["con_pos_after"][(steps["t_sckf"] >= 10.0) & (steps["t_sckf"] <= 13.0)] = 0.3
    steps["corrected_sckf"][(steps["t_sckf"] >= 10.0) & (steps["t_sckf"] < 11.0), 0] = False
    log = {"t": t, "p_true": p_true, "p_target": p_target, **steps}
    fig = event_figures(FaultEvent("link_reboot", 2, 10.0, 13.0), log, [2])
    assert fig["track_during_m"] == pytest.approx(0.6) and fig["track_after_m"] == pytest.approx(0.6 * np.sqrt(0.09))  # 13.1-13.9 s of (13, 23]
    assert fig["constraint_during_m"] == pytest.approx(0.3) and fig["constraint_after_m"] == pytest.approx(0.002)
    assert fig["uncorrected_max"] == pytest.approx(2 / 7)  # link 1 missed 2 of the window's 7 steps
    assert fig["recovery_s"] == pytest.approx(1.0, abs=0.11)
    assert "recovery_s" not in event_figures(FaultEvent("mavlink_loss", 0, 8.0, 30.0), log)  # lasts to the end


def test_the_table_counts_per_kind_and_keeps_failed_runs():
    reboot = {**FaultEvent("link_reboot", 2, 10.0, 13.0).as_dict(), "track_during_m": 0.9, "track_after_m": 0.2,
              "constraint_during_m": 0.3, "constraint_after_m": 0.01, "uncorrected_max": 0.2, "recovery_s": None}
    gps = {**FaultEvent("gps_step", 1, 12.0, 14.0).as_dict(), "track_during_m": 0.5, "recovery_s": 2.0}
    rows = [  # a crash at 30 s: 17 s after the reboot's end (not near it), during the GPS step
        {"events": [reboot, {**gps, "start_s": 29.0, "end_s": 31.0}], "status": "ok", "crashed": True,
         "crash_time_s": 30.0, "min_altitude_m": 0.1},
        {"events": [{**reboot, "track_during_m": 0.3, "constraint_after_m": 0.02, "recovery_s": 1.0}], "status": "ok",
         "crashed": False, "min_altitude_m": 1.5},
        {"events": [reboot, gps], "status": "ok", "crashed": False, "min_altitude_m": 2.0},
        {"events": [FaultEvent("gps_step", 1, 12.0, 14.0).as_dict()], "status": "failed"},
    ]
    table = fault_table(rows)
    assert set(table) == {"link_reboot", "gps_step"}
    r = table["link_reboot"]  # the figures: of the flights that did not crash
    assert (r["flights"], r["failed"], r["crashes"], r["crashes_near"], r["min_altitude_m"]) == (3, 0, 1, 0, 0.1)
    assert (r["track_during_m"], r["constraint_after_m"], r["recovery_s_max"], r["not_recovered"]) == (0.9, 0.02, 1.0, 1)
    g = table["gps_step"]
    assert (g["flights"], g["failed"], g["crashes"], g["crashes_near"]) == (3, 1, 1, 1)
    assert (g["track_during_m"], g["recovery_s_max"], g["track_after_m"]) == (0.5, 2.0, None)
    assert "| link_reboot | 3 | 0 | 1 | 0 | 0.10 | 0.900 |" in markdown_fault_table(table)


def test_a_crash_is_read_against_the_power_loss_near_it():
    reboot = {"kind": "link_reboot", "target": 3, "start_s": 10.0, "end_s": 13.0}
    gps = {"kind": "gps_outage", "target": 1, "start_s": 20.0, "end_s": 30.0}
    row = {"crashed": True, "crash_time_s": 22.9, "events": [reboot, gps]}
    assert power_loss_near(row) is reboot  # within AFTER_S of the reboot's end
    assert power_loss_near(dict(row, crash_time_s=23.1)) is None  # after it: the outage's
    assert power_loss_near(dict(row, crashed=False)) is None and power_loss_near(dict(row, crash_time_s=None)) is None

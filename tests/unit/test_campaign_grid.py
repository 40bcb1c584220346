"""A campaign's grid (sitl.campaign.grid) and the dotted settings it sets in scenario files
(companion.configfile.with_settings, load_setup's settings)."""

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.configfile import ConfigError, parse_setting, with_settings
from sitl.campaign.grid import RunSpec, format_value, make_grid, parse_seeds, parse_sweep
from sitl.scenarios import load

from ..paths import ROOT

THREE_LINK = str(ROOT / "configs/sitl/chain/three_link.toml")


@pytest.mark.parametrize("text, key, values", [
    ("firmware.ekf.gate_sigma=3,4.5", "firmware.ekf.gate_sigma", (3, 4.5)),
    ("firmware.ekf.noise.vel_m2_s3=1e-5,3e-5", "firmware.ekf.noise.vel_m2_s3", (1e-5, 3e-5)),
    ("sensors.profile=m8,outdoor", "sensors.profile", ("m8", "outdoor")),
    ('sensors.profile="m8"', "sensors.profile", ("m8",)),
    ("wind.mean_w_m_s=[1.0, 0.0, 0.0],[0.0, 2, 0]", "wind.mean_w_m_s", ([1.0, 0.0, 0.0], [0.0, 2, 0.0])),
    ("companion.enabled=true,false", "companion.enabled", (True, False)),
    ("duration_s=20", "duration_s", (20,)),
])
def test_a_sweep_reads_each_value_as_toml(text, key, values):
    sweep = parse_sweep(text)
    assert sweep.key == key and sweep.values == values


@pytest.mark.parametrize("text, match", [
    ("firmware.ekf.gate_sigma", "KEY=VALUE"),
    ("firmware.ekf.gate_sigma=", "empty value"),
    ("a=1,,2", "empty value"),
    ("a=2.5,2.5", "given twice"),
    ("firm ware=1", "dotted path"),
    ("a..b=1", "dotted path"),
])
def test_a_malformed_sweep_is_refused_with_the_reason(text, match):
    with pytest.raises(ValueError, match=match):
        parse_sweep(text)


@pytest.mark.parametrize("text, seeds", [("0-3", [0, 1, 2, 3]), ("7", [7]), ("0,5,3-4", [0, 5, 3, 4]),
                                         ("2-3,3", [2, 3])])
def test_seeds_are_ranges_and_lists(text, seeds):
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize("text", ["4-2", "a", "-1", "1-", "", "1;2"])
def test_bad_seeds_are_refused(text):
    with pytest.raises(ValueError, match="--seeds"):
        parse_seeds(text)


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_a_float_value_reads_back_to_the_same_bits(x):
    assert parse_setting(f"k={format_value(x)}")[1] == x


def test_the_grid_is_every_combination_with_its_own_key_and_folder():
    specs = make_grid(["a/one.toml", "b/two.toml"], [parse_sweep("x.y=1,2"), parse_sweep("z=m8,rtk")], [0, 1, 2])
    assert len(specs) == 2 * 2 * 2 * 3
    assert len({s.key for s in specs}) == len(specs) == len({s.folder() for s in specs})
    first = specs[0]
    assert first.key == "one|batch|x.y=1,z=m8|seed=0" and first.group == "one|batch|x.y=1,z=m8"
    assert str(first.folder()) == "one/x.y=1,z=m8/seed-0"
    assert first.columns() == {"scenario": "one", "mode": "batch", "set:x.y": "1", "set:z": "m8", "seed": 0}
    assert [s.seed for s in specs[:3]] == [0, 1, 2]  # seeds innermost
    fleet = RunSpec("a/one.toml", (), 3, "fleet", 8.0)
    assert str(fleet.folder()) == "one-fleet/base/seed-3" and "duration_s=8.0" in fleet.key


def test_a_paced_fleet_run_is_another_run_with_its_own_folder():
    unpaced = RunSpec("a/one.toml", (), 3, "fleet")
    paced = RunSpec("a/one.toml", (), 3, "fleet", speed=1.0)
    assert unpaced.key == "one|fleet|base|seed=3" and paced.key == "one|fleet|base|speed=1.0|seed=3"
    assert str(paced.folder()) == "one-fleet-x1.0/base/seed-3" and paced.folder() != unpaced.folder()
    assert paced.columns()["speed"] == 1.0 and "speed" not in unpaced.columns()
    assert [s.speed for s in make_grid(["a/one.toml"], [], [0, 1], "fleet", speed=2.0)] == [2.0, 2.0]


@pytest.mark.parametrize("mode, speed, match", [("batch", 1.0, "batch mode has no pace"),
                                                ("fleet", -1.0, "speed must be >= 0"),
                                                ("fleet", float("nan"), "speed must be >= 0"),
                                                ("fleet", float("inf"), "speed must be >= 0")])
def test_a_pace_batch_mode_cannot_have_or_no_clock_can_keep_is_refused(mode, speed, match):
    with pytest.raises(ValueError, match=match):
        RunSpec("a/one.toml", (), 0, mode, speed=speed)


def test_odd_or_long_settings_make_a_safe_folder_name():
    odd = RunSpec("s.toml", (("wind.mean_w_m_s", [1.0, 0.0, 0.0]),), 0)
    assert "/" not in odd.folder().parts[1] and " " not in str(odd.folder())
    long = RunSpec("s.toml", tuple((f"section.key_{i}", 1.0 * i) for i in range(20)), 0)
    assert long.folder().parts[1].startswith("settings-") and len(long.folder().parts[1]) < 30


@pytest.mark.parametrize("configs, sweeps, seeds, match", [
    (["a.toml"], ["x=1", "x=2"], [0], "swept twice"),
    (["a/s.toml", "b/s.toml"], [], [0], "same name"),
    (["a.toml"], [], [], "no seeds"),
])
def test_a_grid_that_would_mix_runs_is_refused(configs, sweeps, seeds, match):
    with pytest.raises(ValueError, match=match):
        make_grid(configs, [parse_sweep(s) for s in sweeps], seeds)


def test_settings_set_nested_keys_and_refuse_a_path_through_a_value():
    data = {"firmware": {"rate_hz": 500.0}, "name": "x"}
    out = with_settings(data, {"firmware.ekf.gate_sigma": 4.0, "name": "y"}, "f.toml")
    assert out == {"firmware": {"rate_hz": 500.0, "ekf": {"gate_sigma": 4.0}}, "name": "y"}
    assert data == {"firmware": {"rate_hz": 500.0}, "name": "x"}  # the parsed file is left as it was
    with pytest.raises(ConfigError, match="name: setting name.x: not a table"):
        with_settings(data, {"name.x": 1}, "f.toml")


def test_a_scenario_loads_with_settings_checked_as_the_file_would_be():
    _, sc = load(THREE_LINK, settings={"firmware.ekf.gate_sigma": 4, "sensors.profile": "m8"}, seed=3)
    assert sc.firmware.ekf.gate_sigma == 4.0 and sc.sensors.profile == "m8" and sc.seed == 3
    assert sc.firmware.rate_hz == 500.0  # the file's other keys stay
    with pytest.raises(ConfigError, match=r"firmware\.ekf\.gate_sigm: unknown key"):
        load(THREE_LINK, settings={"firmware.ekf.gate_sigm": 4})
    with pytest.raises(ConfigError, match=r"sensors\.profile"):
        load(THREE_LINK, settings={"sensors.profile": "gps9000"})
    assert math.isclose(load(THREE_LINK, settings={"duration_s": 9.5})[1].duration_s, 9.5)


def test_fly_and_launch_take_the_same_settings_one_at_a_time():
    from sitl.__main__ import _scenario, build_parser

    for command in ("fly", "launch"):
        args = build_parser().parse_args([command, "--config", THREE_LINK, "--set", "firmware.ekf.gate_sigma=4",
                                          "--set", "wind.gust_std_m_s=0.5"])
        _, sc = _scenario(args)
        assert sc.firmware.ekf.gate_sigma == 4.0 and sc.wind.gust_std_m_s == 0.5
    bad = build_parser().parse_args(["fly", "--config", THREE_LINK, "--set", "firmware.ekf.gate_sigma"])
    with pytest.raises(ConfigError, match="--set: 'firmware.ekf.gate_sigma': expected KEY=VALUE"):
        _scenario(bad)


@pytest.mark.parametrize("speed, ok", [("0", True), ("2.5", True), ("-1", False), ("nan", False), ("inf", False),
                                       ("fast", False)])
def test_launch_and_campaigns_take_the_same_pace(speed, ok, capsys):
    """``sitl launch --speed`` and ``sitl campaign faults --speed`` share one check: a finite pace
    >= 0 (0: unpaced); anything else is a usage error naming the value."""
    from sitl.__main__ import build_parser

    for argv in (["launch", "--config", THREE_LINK], ["campaign", "faults", "--config", THREE_LINK, "--flights", "1"]):
        if ok:
            assert build_parser().parse_args([*argv, "--speed", speed]).speed == float(speed)
        else:
            with pytest.raises(SystemExit) as exc:
                build_parser().parse_args([*argv, "--speed", speed])
            assert exc.value.code == 2 and repr(speed) in capsys.readouterr().err

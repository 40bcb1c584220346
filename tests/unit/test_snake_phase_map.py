"""Eq. 4.1's map for the ground robots (sitl.scenarios.ground.phase_sweep): the argmax refined on a
wrapping grid, the map unwrapped over the inputs, and the snake's and the pivotboard's scenarios
reading it from their files."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from companion.configfile import ConfigError
from sitl.scenarios.ground.phase_sweep import best_phases, map_lines, phase_map
from sitl.scenarios.pivotboard.config import load_pivot_scenario
from sitl.scenarios.snake.config import load_snake_scenario

from ..paths import ROOT

PHI = np.arange(12) * 2 * math.pi / 12 - math.pi


@pytest.mark.parametrize("peak", [-3.0, -0.17, 0.4, 3.1])
def test_the_best_phase_of_a_smooth_periodic_speed_is_found_between_grid_points(peak):
    v = 1.0 + 0.5 * np.cos(PHI - peak)  # a parabola near its top: the refinement is close to exact
    got = best_phases(v[None], PHI)[0]
    assert abs(math.remainder(got - peak, 2 * math.pi)) < 0.02


def test_the_map_is_unwrapped_across_the_grid_and_interpolates_without_a_jump():
    best = np.array([[3.1, -3.1], [3.0, -3.05]])  # the same phase either side of pi
    m = phase_map((np.radians([10.0, 20.0]), np.radians([0.0, 5.0])), best)
    values = np.reshape(m.values, (2, 2))
    assert np.all(np.abs(np.diff(values, axis=0)) < 1.0) and np.all(np.abs(np.diff(values, axis=1)) < 1.0)
    assert abs(math.remainder(m(math.radians(15.0), math.radians(2.5)) - math.pi, 2 * math.pi)) < 0.1


def test_a_map_with_a_one_point_axis_is_constant_along_it_and_writes_as_a_table():
    """The pivotboard's map of ``(A, B, v_dot_d)``: its sweep holds ``v_dot_d``, one point."""
    best = np.array([[1.4, 1.5], [1.3, 1.6]])
    m = phase_map((np.radians([10.0, 40.0]), np.radians([0.0, 30.0]), (0.0,)), best[..., None])
    assert m(math.radians(40.0), 0.0, 0.0) == pytest.approx(1.3) and m(math.radians(40.0), 0.0, 5.0) == pytest.approx(1.3)
    lines = map_lines("phase", m)
    assert lines[0] == "[phase]" and lines[1].startswith("axes = [[") and lines[2].count(",") == 3


def test_a_scenario_reads_its_phase_map_file(tmp_path):
    (tmp_path / "map.toml").write_text("[phase_hv]\naxes = [[0.1, 0.5], [0.0, 0.2]]\nvalues = [0.1, 0.2, 0.3, 0.4]\n")
    config = tmp_path / "snake.toml"
    text = (ROOT / "configs/sitl/ground/snake.toml").read_text()
    config.write_text(re.sub(r'(?m)^phase_map_file = .*$', 'phase_map_file = "map.toml"', text))
    sc = load_snake_scenario(config)
    assert sc.cpg.phase_hv(0.5, 0.2) == pytest.approx(0.4) and sc.phase_map_file == str(tmp_path / "map.toml")
    (tmp_path / "map.toml").write_text("[phase_hv]\naxes = [[0.1, 0.5]]\nvalues = [0.1, 0.2]\n")
    with pytest.raises(ConfigError, match="phase_map_file"):  # a map of one input: not the snake's (A, B)
        load_snake_scenario(config)
    (tmp_path / "map.toml").unlink()
    with pytest.raises(ConfigError, match="phase_map_file"):
        load_snake_scenario(config)


def test_the_pivotboard_reads_its_map_of_three_inputs_and_refuses_the_snakes(tmp_path):
    config = tmp_path / "pivotboard.toml"
    text = (ROOT / "configs/sitl/ground/pivotboard.toml").read_text()
    config.write_text(re.sub(r'(?m)^phase_map_file = .*$', 'phase_map_file = "map.toml"', text))
    (tmp_path / "map.toml").write_text("[phase]\naxes = [[0.1, 0.5], [0.0], [0.0]]\nvalues = [1.2, 1.4]\n")
    assert load_pivot_scenario(config).cpg.phase(0.5, 0.3, 1.0) == pytest.approx(1.4)
    (tmp_path / "map.toml").write_text("[phase]\naxes = [[0.1, 0.5], [0.0]]\nvalues = [1.2, 1.4]\n")
    with pytest.raises(ConfigError, match="phase_map_file"):
        load_pivot_scenario(config)


def test_a_sweep_whose_flights_are_too_short_to_average_names_the_points_and_writes_nothing(tmp_path, capsys):
    from sitl.scenarios.snake.phase_map import main

    out = tmp_path / "map.toml"
    status = main(["--config", str(ROOT / "configs/sitl/ground/snake.toml"), "--A", "20", "--B", "0",
                   "--phases", "3", "--duration", "2", "--out", str(out)])
    err = capsys.readouterr().err
    assert status == 2 and not out.exists()
    assert "3 of 3 grid points have no speed" in err and "A=20 B=0 phi=-3.1416" in err and "--duration" in err


def test_speedless_points_are_named_by_their_grid_values():
    from sitl.scenarios.ground.phase_sweep import speedless_points

    v = np.ones((2, 1, 3))
    v[1, 0, 2] = np.nan
    assert speedless_points(v, [10.0, 20.0], [5.0], PHI[:3]) == [f"A=20 B=5 phi={PHI[2]:.4f}"]
    assert speedless_points(np.ones((1, 1, 2)), [1.0], [1.0], PHI[:2]) == []

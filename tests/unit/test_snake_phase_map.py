"""Eq. 4.1's map for the snake (sitl.scenarios.snake.phase_map): the argmax refined on a wrapping
grid, the map unwrapped over the inputs, and a scenario reading it from its file."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from companion.configfile import ConfigError
from sitl.scenarios.snake.config import load_snake_scenario
from sitl.scenarios.snake.phase_map import best_phases, phase_map

from ..paths import ROOT

PHI = np.arange(12) * 2 * math.pi / 12 - math.pi


@pytest.mark.parametrize("peak", [-3.0, -0.17, 0.4, 3.1])
def test_the_best_phase_of_a_smooth_periodic_speed_is_found_between_grid_points(peak):
    v = 1.0 + 0.5 * np.cos(PHI - peak)  # a parabola near its top: the refinement is close to exact
    got = best_phases(v[None], PHI)[0]
    assert abs(math.remainder(got - peak, 2 * math.pi)) < 0.02


def test_the_map_is_unwrapped_across_the_grid_and_interpolates_without_a_jump():
    best = np.array([[3.1, -3.1], [3.0, -3.05]])  # the same phase either side of pi
    m = phase_map([10.0, 20.0], [0.0, 5.0], best)
    values = np.reshape(m.values, (2, 2))
    assert np.all(np.abs(np.diff(values, axis=0)) < 1.0) and np.all(np.abs(np.diff(values, axis=1)) < 1.0)
    assert abs(math.remainder(m(math.radians(15.0), math.radians(2.5)) - math.pi, 2 * math.pi)) < 0.1


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

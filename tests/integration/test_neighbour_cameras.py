"""Chain cameras seeing their neighbours' markers in a batch flight (sitl.cameras.neighbours): each
rendered frame's pose reaches the companion's step and is applied there; switched off, every one
is counted and dropped, and the flight's corrections differ."""

from __future__ import annotations

import numpy as np
import pytest

from sitl.cameras.neighbours import neighbour_views
from sitl.scenario import load_scenario
from sitl.scenarios import load
from sitl.scenarios.chain.flight import fly

CONFIG = "configs/sitl/cameras/three_link_neighbours.toml"


def test_the_views_pair_each_camera_with_the_next_links_marker():
    sc = load_scenario(CONFIG)
    views = neighbour_views(sc.cameras, sc.markers)
    assert {name: {mid: v[:2] for mid, v in by.items()} for name, by in views.items()} == {
        "link1_fwd": {1: (0, 1)}, "link2_fwd": {2: (1, 2)}}


@pytest.mark.rendering
def test_neighbour_poses_reach_the_step_and_are_applied(tmp_path):
    """2.5 s on the ground and lifting off: both cameras' 10 Hz frames each give their
    neighbour's pose (within 1 cm of the truth at capture), every one applied by the step; with
    ``companion.neighbour_cameras = false`` none is, and link 2's corrections differ."""
    metrics = {}
    logs = {}
    for on in (True, False):
        _, sc = load(CONFIG, settings={"duration_s": 2.5, "trajectory.takeoff_start_s": 0.5,
                                       "trajectory.takeoff_duration_s": 1.5, "companion.neighbour_cameras": on})
        metrics[on] = fly(sc, tmp_path / str(on), plots=False)["neighbour_cameras"]
        logs[on] = np.load(tmp_path / str(on) / "log.npz")
    got = metrics[True]
    assert got["frames"] == 50 and got["poses"] == 50 and got["pos_err_max_m"] < 0.01
    assert got["steps"] == [{"received": 50, "applied": 50, "not_applied": 0, "too_old": 0, "left_out": 0}]
    assert metrics[False]["steps"][0]["applied"] == 0 and metrics[False]["steps"][0]["left_out"] == 50
    assert not np.allclose(logs[True]["q_corr_sckf"][-10:, 1], logs[False]["q_corr_sckf"][-10:, 1], atol=1e-5)

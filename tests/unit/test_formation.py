"""The formation carrying a slung load as the companion's target source (companion.load.formation,
``trajectory.kind = "formation"``) and its configuration (``[load]`` in companion.config)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import CompanionConfig, CompanionSetup, load_setup
from companion.configfile import ConfigError, dump_toml
from companion.load.config import LoadConfig
from companion.load.formation import CircleFormationConfig, FormationTrajectory, formation_targets
from companion.motion.schedule import MotionConfig
from companion.skeleton.body import SkeletonConfig
from companion.trajectory import TrajectoryConfig, make_trajectory
from sitl.scenarios.slung_load.config import load_slung_scenario

from ..paths import ROOT

CONFIG = ROOT / "configs" / "sitl" / "load" / "slung_load_three.toml"


def _setup(**changes) -> CompanionSetup:
    base = dict(name="carry", skeleton=SkeletonConfig(n_links=3), companion=CompanionConfig(enabled=False),
                trajectory=TrajectoryConfig(kind="formation"), load=LoadConfig())
    return CompanionSetup(**{**base, **changes})


@pytest.mark.parametrize("t", [0.0, 0.02, 3.99, 4.0, 5.3, 8.0, 12.7, 40.0])
def test_the_trajectory_is_the_formations_targets(t):
    load = LoadConfig(mass_kg=1.3, formation=CircleFormationConfig(start_s=4.0, ramp_s=4.0, speed_m_s=1.2))
    traj = make_trajectory(TrajectoryConfig(kind="formation"), MotionConfig(), SkeletonConfig(n_links=3),
                           np.zeros(3), load=load)
    assert isinstance(traj, FormationTrajectory)
    want = formation_targets(t, load.formation, load_mass_kg=load.mass_kg, cable_dirs_f=load.cable_dirs_f())
    for passive in (frozenset(), frozenset({1})):  # no carried links in a formation: passive is ignored
        got = traj.targets(t, passive=passive)
        assert len(got) == len(want) == 3
        for g, w in zip(got, want):
            for name in ("p_w_m", "q_wxyz", "v_w_m_s", "a_w_m_s2", "omega_d_rad_s", "omega_dot_d_rad_s2",
                         "force_ff_w_n"):
                np.testing.assert_array_equal(getattr(g, name), getattr(w, name), err_msg=name)
    assert np.linalg.norm(sum(x.force_ff_w_n for x in want)) > 1.3 * 9.0  # the cables carry the load


def test_the_formation_needs_its_load():
    with pytest.raises(ValueError, match="load"):
        make_trajectory(TrajectoryConfig(kind="formation"), MotionConfig(), SkeletonConfig(n_links=3), np.zeros(3))


def test_a_formation_setup_validates():
    setup = _setup()
    assert setup.load.formation.n_vehicles == setup.skeleton.n_links == 3


@pytest.mark.parametrize("changes, match", [
    (dict(load=None), r"^trajectory\.kind 'formation' needs a \[load\]"),
    (dict(trajectory=TrajectoryConfig(kind="hover")), r"^trajectory\.kind must be 'formation'"),
    (dict(skeleton=SkeletonConfig(n_links=4)), r"^load\.formation\.n_vehicles \(3\) must equal skeleton\.n_links \(4\)"),
    (dict(companion=CompanionConfig(enabled=True)), r"^companion\.enabled must be false"),
])
def test_a_formation_setup_is_refused(changes, match):
    with pytest.raises(ValueError, match=match):
        _setup(**changes)


def test_a_formation_takes_no_chain_feedforward():
    with pytest.raises(ValueError, match="^feedforward"):
        TrajectoryConfig(kind="formation", feedforward=True)


def test_a_setup_without_load_is_unchanged():
    setup = CompanionSetup(name="chain")
    assert setup.load is None and "load" not in dump_toml(setup)


def test_the_file_names_the_key(tmp_path):
    path = tmp_path / "companion.toml"
    path.write_text(dump_toml(_setup(trajectory=TrajectoryConfig(kind="hover"), load=None))
                    + "\n[load.formation]\nn_vehicles = 3\n")
    with pytest.raises(ConfigError) as info:
        load_setup(CompanionSetup, path)
    assert info.value.key == "trajectory"


def test_the_slung_load_companion_setup_loads_back_equal(tmp_path):
    setup = load_slung_scenario(CONFIG).companion_setup()
    assert type(setup) is CompanionSetup and setup.trajectory.kind == "formation" and setup.load is not None
    path = tmp_path / "companion.toml"
    path.write_text(dump_toml(setup))
    back = load_setup(CompanionSetup, path)
    assert back == setup

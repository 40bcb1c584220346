"""The configuration schemas compose: a SITL scenario is a companion setup and a vehicle setup;
each process validates its own part strictly (hardware configs by the companion's schema alone)."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from companion.config import CompanionSetup, load_setup
from companion.configfile import ConfigError, dump_toml
from link_firmware_sim.config import VehicleSetup
from sitl.scenario import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[1]
SITL = sorted((ROOT / "configs" / "sitl").glob("*.toml"))
HARDWARE = sorted((ROOT / "configs" / "hardware").glob("*.toml"))


@pytest.mark.parametrize("path", SITL, ids=lambda p: p.stem)
def test_every_scenario_splits_into_parts_that_load_back_strictly(path, tmp_path):
    from sitl.slung_load_config import is_slung_load_file, load_slung_scenario

    sc = load_slung_scenario(path) if is_slung_load_file(path) else load_scenario(path)  # as `sitl fly` does
    assert isinstance(sc, CompanionSetup) and isinstance(sc, VehicleSetup)
    for cls, part in ((CompanionSetup, sc.companion_setup()), (VehicleSetup, sc.vehicle_setup())):
        assert type(part) is cls
        file = tmp_path / f"{cls.__name__}.toml"
        file.write_text(dump_toml(part))
        assert load_setup(cls, file) == part


@pytest.mark.parametrize("path", HARDWARE, ids=lambda p: p.stem)
def test_hardware_configs_are_companion_setups_and_nothing_else(path, tmp_path):
    setup = load_setup(CompanionSetup, path)
    assert setup.companion.links
    bad = tmp_path / "with_rotors.toml"
    bad.write_text(path.read_text() + "\n[rotors]\nthrust_max_n = 8.0\n")
    with pytest.raises(ConfigError) as info:
        load_setup(CompanionSetup, bad)
    assert info.value.key == "rotors" and info.value.reason.startswith("unknown key")


def test_a_scenario_given_to_the_companion_names_the_first_simulator_key():
    proc = subprocess.run([sys.executable, "-m", "companion", "--config", str(ROOT / "configs/sitl/three_link.toml"),
                           "--duration", "0"], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2
    assert "three_link.toml: duration_s: unknown key" in proc.stderr and "companion.toml" in proc.stderr


def test_the_scenario_checks_each_parts_rules():
    sc = load_scenario(ROOT / "configs" / "sitl" / "three_link.toml")
    with pytest.raises(ValueError, match="thrust_max_n"):  # the vehicle's rule
        replace(sc, rotors=replace(sc.rotors, thrust_max_n=6.0))
    with pytest.raises(ValueError, match="keeps the links on the ground"):  # the companion's rule
        replace(sc, trajectory=replace(sc.trajectory, kind="rest"))
    with pytest.raises(ValueError, match="duration_s"):  # the simulator's rule
        replace(sc, duration_s=2.0)
    assert Scenario.__mro__[1:3] == (CompanionSetup, VehicleSetup)


def test_the_wall_push_scenario_loads_as_one():
    """configs/sitl/odar/wall_push.toml is a wall-push scenario ([contact]); as a plain scenario
    its extra table is named."""
    from sitl.contact import load_wall_scenario

    path = ROOT / "configs" / "sitl" / "odar" / "wall_push.toml"
    sc = load_wall_scenario(path)
    assert sc.contact.force_n > 0 and sc.firmware.controller == "hybrid"
    with pytest.raises(ConfigError) as info:
        load_scenario(path)
    assert info.value.key == "contact"

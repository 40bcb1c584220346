"""The configuration schemas compose: a SITL scenario is a companion setup and a vehicle setup;
each process validates its own part strictly (hardware configs by the companion's schema alone)."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import pytest

from companion.config import CompanionSetup, load_setup
from companion.configfile import ConfigError, dump_toml
from link_firmware_sim.config import VehicleSetup
from sitl.scenario import Scenario, load_scenario
from sitl.scenarios import KINDS, kind_of, load

from ..paths import ROOT

SITL = sorted((ROOT / "configs" / "sitl").rglob("*.toml"))
HARDWARE = sorted((ROOT / "configs" / "hardware").glob("*.toml"))
#: the kind of every scenario file, by the folder it is in (configs/sitl/<folder>/)
FOLDER_KINDS = {"chain": {"chain"}, "cameras": {"chain"}, "faults": {"chain"}, "odar": {"chain", "wall_push", "pspm_jump"},
                "load": {"slung_load"}, "ground": {"snake", "pivotboard"}}


def test_the_scenario_folders_mirror_the_kinds_and_each_has_a_readme():
    folders = {p.parent.name for p in SITL}
    assert folders == set(FOLDER_KINDS) and not list((ROOT / "configs" / "sitl").glob("*.toml"))
    assert all((ROOT / "configs" / "sitl" / f / "README.md").exists() for f in folders)
    assert set().union(*FOLDER_KINDS.values()) == set(KINDS)


@pytest.mark.parametrize("path", SITL, ids=lambda p: p.stem)
def test_every_scenario_splits_into_parts_that_load_back_strictly(path, tmp_path):
    kind, sc = load(path)  # as `sitl fly` does
    assert kind.name in FOLDER_KINDS[path.parent.name] and sc.kind == kind.name
    if path.parent.name == "ground":  # a ground robot: no companion nor vehicle; its file loads back equal
        file = tmp_path / "scenario.toml"
        file.write_text(dump_toml(sc))
        assert load(file) == (kind, sc)
        return
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
    proc = subprocess.run([sys.executable, "-m", "companion", "--config", str(ROOT / "configs/sitl/chain/three_link.toml"),
                           "--duration", "0.1"], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2
    assert "three_link.toml: duration_s: unknown key" in proc.stderr and "companion.toml" in proc.stderr


def test_the_scenario_checks_each_parts_rules():
    sc = load_scenario(ROOT / "configs" / "sitl" / "chain" / "three_link.toml")
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
    from sitl.scenarios.wall_push.config import load_wall_scenario

    path = ROOT / "configs" / "sitl" / "odar" / "wall_push.toml"
    sc = load_wall_scenario(path)
    assert sc.contact.force_n > 0 and sc.firmware.controller == "hybrid"
    with pytest.raises(ConfigError) as info:
        load_scenario(path)
    assert info.value.key == "contact"


@pytest.mark.parametrize("kind, table", [("wall_push", "contact"), ("pspm_jump", "teleop"), ("slung_load", "load")])
def test_a_kinds_table_without_its_kind_names_the_kind(kind, table, tmp_path):
    path = next(p for p in SITL if kind_of(p).name == kind)
    bare = tmp_path / "bare.toml"
    bare.write_text("\n".join(line for line in path.read_text().splitlines() if not line.startswith("kind =")))
    with pytest.raises(ConfigError) as info:
        load(bare)
    assert info.value.key == table and f'kind = "{kind}"' in info.value.reason


@pytest.mark.parametrize("value", ['"wall"', "3"])
def test_an_unknown_kind_is_named(value, tmp_path):
    path = tmp_path / "x.toml"
    path.write_text(f"kind = {value}\n" + (ROOT / "configs/sitl/chain/three_link.toml").read_text())
    with pytest.raises(ConfigError) as info:
        load(path)
    assert info.value.key == "kind" and "chain" in info.value.reason and "slung_load" in info.value.reason


def test_a_run_folders_scenario_loads_back_as_its_kind(tmp_path):
    """``scenario.toml`` of a run folder names its kind: ``sitl fly --config <run>/scenario.toml``
    flies the same kind again."""
    for path in (ROOT / "configs/sitl/odar/pspm_jump.toml", ROOT / "configs/sitl/chain/three_link.toml"):
        kind, sc = load(path)
        copy = tmp_path / f"{path.stem}.toml"
        copy.write_text(dump_toml(sc))
        assert load(copy) == (kind, sc)


@pytest.mark.parametrize("command, config, needle", [
    ("launch", "configs/sitl/odar/wall_push.toml", "a wall_push scenario has no fleet form"),
    ("launch", "configs/sitl/odar/pspm_jump.toml", "a pspm_jump scenario has no fleet form"),
    ("fly", "configs/sitl/odar/pspm_jump.toml --video x.mp4", "--video: a pspm_jump scenario makes no video"),
])
def test_the_command_line_refuses_what_a_kind_does_not_have(command, config, needle, tmp_path):
    args = [sys.executable, "-m", "sitl", command, "--config", *config.split(), "--out", str(tmp_path / "run")]
    proc = subprocess.run(args, capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and needle in proc.stderr, proc.stderr
    assert not (tmp_path / "run").exists()


_OUT = "--out RUN/run"


@pytest.mark.parametrize("args, needle", [
    (f"sitl fly --config configs/sitl/chain/three_link.toml --duration inf {_OUT}", "duration_s must be a finite"),
    (f"sitl launch --config configs/sitl/chain/three_link.toml --duration nan {_OUT}", "duration_s must be a finite"),
    (f"sitl fly --config configs/sitl/chain/three_link.toml --seed -1 {_OUT}", "seed must be >= 0"),
    (f"sitl fly --config configs/sitl/ground/snake.toml --duration inf {_OUT}", "duration_s: must be a finite number"),
    (f"sitl fly --config configs/sitl/ground/snake.toml --seed -3 {_OUT}", "seed must be >= 0"),
    (f"companion --config configs/hardware/three_link_rpi.toml --duration nan {_OUT}", "a duration is a finite number"),
    (f"companion --config configs/hardware/three_link_rpi.toml --duration -1 {_OUT}", "a duration is a finite number"),
    (f"sitl fly --config configs/sitl/chain/three_link.toml --view --view-port 99999 {_OUT}", "a port is 0"),
    (f"companion --config configs/hardware/three_link_rpi.toml --start-center nan,0,0 {_OUT}", "three finite numbers"),
    (f"companion --config configs/hardware/three_link_rpi.toml --start-center a,b,c {_OUT}", "three finite numbers"),
    (f"sitl.bench soak --duration nan {_OUT}", "a duration is a finite number"),
    ("sitl fault vehicle-off RUN --link 1 --restart-after nan", "a finite number of seconds >= 0"),
    # sitl view's options, checked before a server or a browser starts (--at nan raised in viser; a
    # 99999-pixel screenshot never came back)
    ("sitl view RUN --at nan --screenshot RUN/x.png", "a time in the run is a finite number"),
    ("sitl view RUN --size 99999x99999 --screenshot RUN/x.png", "each from 64 to 8192"),
    ("sitl view RUN --size 1x --screenshot RUN/x.png", "expected WIDTHxHEIGHT"),
    ("sitl view RUN --view-port 70000", "a port is 0"),
])
def test_a_number_out_of_range_on_the_command_line_is_refused_naming_it(args, needle, tmp_path):
    """Not a traceback (``--duration inf`` raised OverflowError, ``--seed -1`` numpy's ValueError, a
    view port over 65535 an OverflowError that left the process hanging), nor a companion that stops
    at once: exit code 2 and what is wrong, and no run folder."""
    command = [sys.executable, "-m", *args.replace("RUN", str(tmp_path)).split()]
    proc = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 2 and needle in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert not (tmp_path / "run").exists()

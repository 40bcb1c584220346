"""A fleet's companions run their compiled kernels unless asked for the numpy path, which the
launcher gives them alone (``SKELETON_JIT=0`` in their environment, the vehicles' untouched); the
CLI and the layout name the same choices (sitl.fleet.launcher.Fleet.start_companion)."""

from __future__ import annotations

import pytest

import sitl.__main__ as cli
from sitl.fleet.launcher import Fleet
from sitl.fleet.layout import COMPANION_KERNELS, SIM_LINKS
from sitl.scenario import load_scenario

from ..paths import THREE_LINK


class RecordingProcesses:
    """What Fleet.start_companion asks of its processes, recorded."""

    def __init__(self):
        self.started = []

    def start(self, name, argv, log_path, stdin_pipe=False, env=None):
        self.started.append((name, argv, env))


@pytest.mark.parametrize("kernels, jit", [("compiled", None), ("numpy", "0")])
def test_the_companions_path_is_theirs_alone(tmp_path, monkeypatch, kernels, jit):
    monkeypatch.delenv("SKELETON_JIT", raising=False)
    fleet = Fleet(load_scenario(THREE_LINK), tmp_path, speed=0.0, companion_kernels=kernels)
    fleet.procs, fleet.companion_config = RecordingProcesses(), tmp_path / "companion.toml"
    fleet.start_companion(0, fleet.companion_folder(0))
    (name, argv, env), = fleet.procs.started
    assert name == "companion of group 1" and argv[-2:] == ["--group", "1"]
    assert (None if env is None else env.get("SKELETON_JIT")) == jit  # (None: the launcher's own environment)


def test_an_unknown_path_is_refused(tmp_path):
    with pytest.raises(ValueError, match="companion_kernels 'fast': one of compiled, numpy"):
        Fleet(load_scenario(THREE_LINK), tmp_path, companion_kernels="fast")


def test_the_cli_offers_the_layouts_choices():
    assert cli.COMPANION_KERNELS == COMPANION_KERNELS and cli.SIM_LINKS == SIM_LINKS
    parser = cli.build_parser()
    args = parser.parse_args(["launch", "--config", str(THREE_LINK)])
    assert args.companion_kernels == "compiled"
    assert parser.parse_args(["launch", "--config", str(THREE_LINK), "--companion-kernels", "numpy"]).companion_kernels == "numpy"
    with pytest.raises(SystemExit):
        parser.parse_args(["launch", "--config", str(THREE_LINK), "--companion-kernels", "fast"])

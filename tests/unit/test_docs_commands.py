"""The docs check's command half (:mod:`tests.docs_commands`): every ``python -m`` entry point has
the parser it checks against, and a flag broken in a copy of the README is reported on its line."""

from __future__ import annotations

import argparse
import re

from ..docs_check import check_text
from ..docs_commands import entry_points, module_parser
from ..docs_names import find_definition, parse_module
from ..paths import ROOT


def test_every_entry_point_has_a_parser_builder():
    """The command check imports each entry point's ``build_parser()``: a new ``python -m`` module
    without one could not be checked."""
    expected = {"sitl", "sitl.bench", "sitl.fleet.wire", "companion", "companion.motion", "companion.vision",
                "link_firmware_sim", "link_firmware_sim.design"}
    found = entry_points()
    assert expected <= set(found), f"entry points not found: {expected - set(found)}"
    for module, path in found.items():
        tree = parse_module(path)
        assert find_definition(tree.body, "build_parser") is not None, \
            f"{path.relative_to(ROOT)} ({module}) has no build_parser()"
        assert isinstance(module_parser(module), argparse.ArgumentParser)


def test_checker_reports_a_broken_flag_in_a_copy_of_a_real_document(tmp_path):
    """The README with one flag broken: exactly that line is reported in addition to what it has today."""
    readme = ROOT / "README.md"
    text = readme.read_text()
    good = re.search(r"^python -m sitl fly --config configs/sitl/chain/three_link.toml", text, re.M)
    assert good, "no `python -m sitl fly --config configs/sitl/chain/three_link.toml` line in the README"
    line = text[:good.start()].count("\n") + 1
    broken = text[:good.start()] + good.group(0).replace("--config", "--konfig") + text[good.end():]
    before = set(check_text(text, readme))
    after = [p for p in check_text(broken, readme) if p not in before]
    assert after and all(p.startswith(f"README.md:{line}: ") for p in after), after
    assert any("unknown flag --konfig for `python -m sitl fly`" in p for p in after), after

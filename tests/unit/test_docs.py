"""The docs cannot drift silently: README.md and docs/**/*.md (not docs/bench/, which the benches
write) checked against the code by :mod:`tests.docs_check` (commands and their flags, links and
anchors, ``path.py::Name`` references, repository paths), and the checker itself on a broken and
a right snippet."""

from __future__ import annotations

import pytest

from ..docs_check import check_document, check_text
from ..docs_markdown import documents, github_slug
from ..paths import ROOT


@pytest.mark.parametrize("doc", documents(), ids=lambda p: str(p.relative_to(ROOT)))
def test_document_matches_the_code(doc):
    problems = check_document(doc)
    assert not problems, f"{len(problems)} problem(s) in {doc.relative_to(ROOT)}:\n" + "\n".join(problems)


BROKEN = """\
# Broken

```sh
python -m sitl fly --config configs/sitl/chain/three_link.toml --no-such-flag
.venv/bin/pip install -e . && .venv/bin/python -m sitl.bench nees \\
    --seeds 3 --jobz 2   # a typo after a continuation
python3 -m sitl flyy --config configs/sitl/chain/three_link.toml
python -m sitl launch --config configs/sitl/chain/three_link.toml [--sim-link tcp|udp]
python -m sitl.bench table2 --ekf papr --seeds five
python -m companion keys renew some.key
python -m sitl fly --config configs/sitl/no_such_scenario.toml
python -m sitl.nothing --x
```

See [the architecture](architecture.md#no-such-heading), [a missing page](missing.md) and
![a missing image](images/none.png), [this page](#brokn).

The trajectory is `companion/trajectory.py::NoSuchTrajectory`, the engine
companion/engine/core.py::CompanionEngine.no_such_method, the scenarios `configs/sitl/no_such.toml`
and `configs/nowhere/*.toml`. Quoted: `python -m sitl fly --no-plot`.
"""


def test_checker_reports_broken_flags_links_names_and_paths():
    problems = check_text(BROKEN, ROOT / "docs" / "snippet.md")
    text = "\n".join(problems)
    expected = [
        "docs/snippet.md:4: python -m sitl fly --config configs/sitl/chain/three_link.toml --no-such-flag: unknown flag "
        "--no-such-flag for `python -m sitl fly`",
        "docs/snippet.md:5: .venv/bin/pip install -e . && .venv/bin/python -m sitl.bench nees --seeds 3 --jobz 2: ",
        "unknown flag --jobz for `python -m sitl.bench nees` (did you mean --jobs?)",
        "docs/snippet.md:7: python3 -m sitl flyy --config configs/sitl/chain/three_link.toml: unknown subcommand 'flyy' for "
        "`python -m sitl`",
        "docs/snippet.md:8: ",
        "--sim-link 'udp' of `python -m sitl launch`: not one of tcp, unix",
        "docs/snippet.md:9: python -m sitl.bench table2 --ekf papr --seeds five: --ekf 'papr' of "
        "`python -m sitl.bench table2`: not one of paper, consistent, both",
        "--seeds 'five' of `python -m sitl.bench table2`: not an integer",
        "docs/snippet.md:10: python -m companion keys renew some.key: argument action 'renew' of "
        "`python -m companion keys`: not one of new, check, zenoh",
        "docs/snippet.md:11: ",
        "--config of `python -m sitl fly`: `configs/sitl/no_such_scenario.toml` does not exist",
        "docs/snippet.md:12: python -m sitl.nothing --x: `python -m sitl.nothing` is not an entry point",
        "docs/snippet.md:15: link to architecture.md#no-such-heading: no heading #no-such-heading in "
        "docs/architecture.md",
        "docs/snippet.md:15: link to missing.md: docs/missing.md does not exist",
        "docs/snippet.md:16: link to images/none.png: docs/images/none.png does not exist",
        "docs/snippet.md:16: link to #brokn: no heading #brokn in this file (did you mean #broken?)",
        "docs/snippet.md:18: companion/trajectory.py::NoSuchTrajectory: companion/trajectory.py defines no "
        "NoSuchTrajectory",
        "docs/snippet.md:19: companion/engine/core.py::CompanionEngine.no_such_method: companion/engine/core.py defines no "
        "CompanionEngine.no_such_method",
        "docs/snippet.md:19: `configs/sitl/no_such.toml` does not exist",
        "docs/snippet.md:20: `configs/nowhere/*.toml` does not exist (no match)",
        "docs/snippet.md:20: python -m sitl fly --no-plot: unknown flag --no-plot for `python -m sitl fly` (an "
        "abbreviation of --no-plots: spell it out)",
    ]
    for piece in expected:
        assert piece in text, f"not reported: {piece!r}\nreported:\n{text}"
    assert len(problems) == 18, text


GOOD = """\
# Good heading: with `code` and punctuation!

## Repeated
## Repeated

```sh
python3 -m venv .venv && .venv/bin/pip install -e '.[sim]' && .venv/bin/python -m sitl fly --config configs/sitl/chain/three_link.toml
python -m sitl fly --config configs/sitl/chain/three_link.toml [--duration S] [--seed N] [--no-sckf] [--out DIR]  # comment --bogus
python -m sitl launch --config configs/sitl/chain/three_link.toml [--sim-link tcp|unix] --speed 0
python -m companion --config runs/<fleet run>/companion.toml [--out DIR]
python -m companion keys new configs/hardware/keys/skeleton.key
eval "$(python -m companion dialect)"
MUJOCO_GL=egl python -m sitl.bench table2 --doc [--doc PATH | --no-doc] \\
    --seeds 2 2>&1 | tee log.txt
python -m sitl.bench <bench> --out DIR
python -m pytest tests/unit/test_docs.py::test_checker_reports_broken_flags_links_names_and_paths -q
python -m sitl.bench controllers [--controllers impedance,se3_pid]
mavproxy.py --master udp:127.0.0.1:14550 --no-such-flag-of-another-tool
```

```text
python -m sitl fly --not-checked-in-text-blocks
```

[up](../README.md), [here](#good-heading-with-code-and-punctuation), [again](#repeated-1),
[arch](architecture.md#architecture), [web](https://example.com/x#y), `configs/sitl/*/*.toml`,
`python -m sitl launch --speed 0` (partial: fine in prose), `python -m sitl.bench <bench> --doc`,
`companion/engine/core.py::CompanionEngine`, `companion/skeleton/` and `runs/<run>/log.npz`.
"""


def test_checker_accepts_what_is_right():
    assert check_text(GOOD, ROOT / "docs" / "snippet.md") == []


def test_github_slugs():
    assert github_slug("SITL batch mode") == "sitl-batch-mode"
    assert github_slug("CPG motion generation (thesis ch. 4-5)") == "cpg-motion-generation-thesis-ch-4-5"
    assert github_slug("`python -m sitl.bench` and *friends*") == "python--m-sitlbench-and-friends"
    assert github_slug("snake_case _emphasis_") == "snake_case-emphasis"

"""The docs cannot drift silently: README.md and docs/**/*.md (not docs/bench/, which the benches
write) are read and checked against the code.

* Commands: every line of a fenced shell block (```sh, ```bash, ```shell, ```console) that runs a
  project module (``python -m sitl fly ...``, also ``python3``, ``.venv/bin/python``, after ``&&``,
  ``;`` or ``|``, with ``\\`` continuations joined and ``# comments`` dropped) must parse: the
  module is an entry point, its subcommand exists and every flag is an option of the subcommand's
  argparse parser (the module's own ``build_parser()``), with a value where it needs one and one
  of its choices where it has them. ``[--flag VALUE]`` optional syntax is checked like the rest
  (``a|b`` inside the brackets: alternatives, each checked); ``<placeholders>``, ``$VARS``,
  ``$(...)`` and upper-case metavars pass as values. Other tools' commands (pip, git, mavproxy.py,
  ...) are not checked; ``$(python -m ...)`` inside them is.
* Links: every relative Markdown link or image (``[x](path)``, ``[x](path#anchor)``, reference
  definitions, HTML ``src``/``href``) names an existing file; an anchor names a heading of the
  target (GitHub's slugs). http(s) links are not fetched.
* ``path/file.py::Name`` (also ``Class.method`` and pytest's ``::Class::test``): the file exists
  and defines the name (read with ``ast``, nothing imported).
* Backticked repository paths (``configs/sitl/chain/three_link.toml``, ``companion/daemon.py``,
  globs like ``configs/sitl/*/*.toml``, ``<placeholders>`` as wildcards) exist, unless git ignores
  them (files a command creates, like ``configs/hardware/keys/skeleton.key``); so do the
  ``--config`` files of the checked commands.
* Commands quoted in the prose's inline code (```python -m sitl fly --video X```) are checked
  for unknown subcommands, flags and choices, not for what they leave out.

:func:`check_text` / :func:`check_document` return the problems as ``file:line: message`` strings
(the commands: :mod:`tests.docs_commands`; links and anchors: :mod:`tests.docs_markdown`; ``::Name``
references and paths: :mod:`tests.docs_names`); ``test_checker_reports_*`` in tests/unit/test_docs.py
and tests/unit/test_docs_commands.py feed them broken snippets to keep the checker honest.
"""

from __future__ import annotations

from pathlib import Path

from .docs_commands import SHELL_LANGS, check_commands
from .docs_markdown import anchors_of_text, check_links, split_fences
from .docs_names import check_paths, check_refs
from .paths import ROOT


def check_text(text: str, doc: Path, root: Path = ROOT) -> list[str]:
    """Every problem of a document's ``text`` (``doc``: where it lives, for relative links) as
    ``file:line: message``, in line order."""
    prose, blocks = split_fences(text)
    found = check_commands(blocks, prose)
    found += check_links(prose, doc, root, anchors_of_text(text))
    ref_lines = list(enumerate(prose, 1))
    ref_lines += [(b.start + k, line) for b in blocks if b.lang in SHELL_LANGS for k, line in enumerate(b.lines)]
    found += check_refs(ref_lines, doc, root)
    found += check_paths(prose, root)
    name = doc.relative_to(root) if doc.is_relative_to(root) else doc
    return [f"{name}:{n}: {msg}" for n, msg in sorted(found, key=lambda x: x[0])]


def check_document(path: Path, root: Path = ROOT) -> list[str]:
    return check_text(path.read_text(), path, root)

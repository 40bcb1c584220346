"""The benchmarks' Markdown result files: one header writer and one table helper for every bench.

Every ``python -m sitl.bench <name>`` run writes a Markdown report built from the same result
dict its JSON holds: a title, the command line that produced it, the UTC date, the git commit
of the code (``+dirty`` with uncommitted changes), the machine (platform, CPU model, cores,
Python and the packages that matter to that bench), then the figures as Markdown tables (each
bench's ``markdown_*`` formatter) and the console output (its ``format_*`` text). No figure is
typed by hand: the published files in ``docs/bench/`` are written by ``--doc`` and are
regenerated, never edited (``docs/bench/README.md``).

Where the report goes (:func:`add_doc_options`, :func:`doc_path`):

* by default into the run folder, as ``<run folder>/<name>.md`` beside the JSON;
* ``--doc``: to ``docs/bench/<name>.md`` (the published figures), ``--doc PATH``: to PATH;
* ``--no-doc``: nowhere.

Publishing is asked for, not the default, so that a short trial run (a test, a quick look with
fewer seeds) never overwrites the published figures.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import shlex
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Iterable, Sequence

__all__ = ["DOC_DIR", "PROG", "add_doc_options", "doc_path", "command_line", "git_commit", "cpu_model",
           "machine_info", "load_average", "md_table", "fmt", "render_doc", "write_doc"]

#: where ``--doc`` without a path writes (relative to the working directory: the repository root,
#: like the benches' ``configs/sitl/...`` defaults)
DOC_DIR = Path("docs/bench")
PROG = "python -m sitl.bench"
#: the repository this code lives in (for its git commit)
CODE_ROOT = Path(__file__).resolve().parents[2]
#: environment variables that change what a bench measures, recorded when set
RECORDED_ENV = ("SKELETON_JIT", "MUJOCO_GL", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def add_doc_options(parser: argparse.ArgumentParser, name: str) -> None:
    """``--doc [PATH]`` and ``--no-doc`` on a bench's subparser (``name``: the bench's doc name)."""
    group = parser.add_mutually_exclusive_group()
    default = DOC_DIR / f"{name}.md"
    group.add_argument(
        "--doc", nargs="?", const=str(default), default=None, metavar="PATH",
        help=f"publish the Markdown report: write it to PATH (without PATH: {default}, the generated figures "
             f"of docs/bench/README.md; never edit those by hand). Default: only {name}.md in the run folder")
    group.add_argument("--no-doc", action="store_true", help="write no Markdown report")


def doc_path(args, run_dir: Path, name: str) -> Path | None:
    """Where this run's report goes (:func:`add_doc_options`), or ``None`` for ``--no-doc``."""
    if getattr(args, "no_doc", False):
        return None
    doc = getattr(args, "doc", None)
    return Path(doc) if doc else Path(run_dir) / f"{name}.md"


def command_line(argv: Sequence[str], prog: str = PROG) -> str:
    """The command as typed: ``python -m sitl.bench`` and the arguments, shell-quoted."""
    return f"{prog} {shlex.join(list(argv))}".rstrip()


def _git(root: Path, *args: str) -> str | None:
    try:
        proc = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout if proc.returncode == 0 else None


def git_commit(root: str | Path = CODE_ROOT) -> str:
    """``git rev-parse --short HEAD`` of ``root``, ``+dirty`` if ``git status --porcelain`` lists
    anything, ``unknown`` outside a git checkout (or without git)."""
    head = _git(Path(root), "rev-parse", "--short", "HEAD")
    if not head or not head.strip():
        return "unknown"
    status = _git(Path(root), "status", "--porcelain")
    return head.strip() + ("+dirty" if status is None or status.strip() else "")


def cpu_model(cpuinfo: str | Path = "/proc/cpuinfo") -> str:
    """The CPU's model name (``/proc/cpuinfo``; ``platform.processor()`` elsewhere)."""
    try:
        for line in Path(cpuinfo).read_text(errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("model name", "Model", "Hardware") and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "not installed"


def machine_info(packages: Iterable[str] = ("numpy",)) -> dict:
    """Platform, CPU model, core count, Python, the versions of ``packages`` (distribution names) and
    the :data:`RECORDED_ENV` variables that are set."""
    info = {
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "packages": {p: _version(p) for p in packages},
    }
    env = {k: os.environ[k] for k in RECORDED_ENV if k in os.environ}
    if env:
        info["environment"] = env
    return info


def fmt(x, spec: str = ".3f", missing: str = "-") -> str:
    """``x`` formatted with ``spec``, or ``missing`` for ``None``."""
    return missing if x is None else format(x, spec)


def _cell(x) -> str:
    return str(x).replace("|", "\\|").replace("\n", " ")


def md_table(header: Sequence[str], rows: Iterable[Sequence], align: str | None = None) -> str:
    """A Markdown table. ``align``: one character per column, ``l`` or ``r`` (default: the first
    column left, the others right)."""
    header = list(header)
    align = align or "l" + "r" * (len(header) - 1)
    if len(align) != len(header):
        raise ValueError(f"align {align!r} has {len(align)} columns, the header {len(header)}")
    lines = ["| " + " | ".join(_cell(h) for h in header) + " |",
             "| " + " | ".join("---:" if a == "r" else ":---" for a in align) + " |"]
    for row in rows:
        row = list(row)
        if len(row) != len(header):
            raise ValueError(f"row {row!r} has {len(row)} cells, the header {len(header)}")
        lines.append("| " + " | ".join(_cell(c) for c in row) + " |")
    return "\n".join(lines)


def load_average() -> tuple[float, float, float] | None:
    """The 1, 5 and 15 minute load averages (``None`` where the OS has none)."""
    try:
        return os.getloadavg()
    except (AttributeError, OSError):
        return None


def render_doc(*, title: str, command: str, body: str, console: str | None = None, date: _dt.datetime | None = None,
               commit: str | None = None, machine: dict | None = None, elapsed_s: float | None = None,
               outputs: Sequence[str | Path] = (), load: Sequence[Sequence[float] | None] = ()) -> str:
    """The whole report as text: the header (title, command, date, commit, machine, run time, the
    load averages at its start and end, output files), ``body`` (the bench's Markdown tables), then
    ``console`` (what the command printed)."""
    date = date or _dt.datetime.now(_dt.timezone.utc)
    commit = commit if commit is not None else git_commit()
    machine = machine if machine is not None else machine_info()
    packages = ", ".join(f"{k} {v}" for k, v in machine.get("packages", {}).items())
    rows = [
        ("command", f"`{command}`"),
        ("date (UTC)", date.astimezone(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S")),
        ("git commit", f"`{commit}`"),
        ("platform", machine.get("platform", "unknown")),
        ("CPU", f"{machine.get('cpu', 'unknown')}, {machine.get('cores', '?')} cores"),
        ("Python", machine.get("python", "unknown")),
    ]
    if packages:
        rows.append(("packages", packages))
    if machine.get("environment"):
        rows.append(("environment", " ".join(f"`{k}={v}`" for k, v in machine["environment"].items())))
    if elapsed_s is not None:
        rows.append(("wall time of the run", f"{elapsed_s:.1f} s"))
    if load and all(x is not None for x in load):
        rows.append(("load average (1, 5, 15 min) at the start / end of the run",
                     " / ".join(", ".join(f"{x:.2f}" for x in triple) for triple in load)
                     + " (other work on the machine slows the timed figures)"))
    if outputs:
        rows.append(("outputs", ", ".join(f"`{p}`" for p in outputs)))
    parts = [
        f"# {title}",
        "",
        "Written by the command below; do not edit by hand: run it again to update this file "
        "(see the README of docs/bench/).",
        "",
        *(f"- {key}: {value}" for key, value in rows),
        "",
        body.strip(),
        "",
    ]
    if console:
        parts += ["## Console output", "", "```text", console.rstrip(), "```", ""]
    return "\n".join(parts)


def write_doc(path: str | Path, *, title: str, argv: Sequence[str], body: str, console: str | None = None,
              packages: Iterable[str] = ("numpy",), elapsed_s: float | None = None,
              outputs: Sequence[str | Path] = (), load_start: Sequence[float] | None = None) -> Path:
    """Write the report (:func:`render_doc`) to ``path``, with this machine's and checkout's
    details (the commit is read before the file is written, so the report does not dirty its own
    record); ``load_start``: the load averages when the run started (:func:`load_average`)."""
    load = (load_start, load_average()) if load_start is not None else ()
    text = render_doc(title=title, command=command_line(argv), body=body, console=console,
                      commit=git_commit(), machine=machine_info(packages), elapsed_s=elapsed_s, outputs=outputs,
                      load=load)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


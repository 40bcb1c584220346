"""What a document names in the repository: ``path/file.py::Name`` references (the file defines
the name, read with ``ast``, nothing imported) and backticked repository paths and globs (they
exist, unless git ignores them)."""

from __future__ import annotations

import ast
import glob
import re
import subprocess
from functools import lru_cache
from pathlib import Path

from .docs_markdown import PLACEHOLDER, SENTINEL, code_spans
from .paths import ROOT

#: top-level folders a backticked path must start with to be checked as a repository path
REPO_DIRS = ("companion", "link_firmware_sim", "sitl", "configs", "tests", "docs", ".ci")


def defined_names(tree: ast.AST, dotted: str) -> str | None:
    """``None`` if the module ``tree`` defines ``dotted`` (``Name``, ``Class.method``,
    ``Class.Inner.attr``), else what is missing."""
    body = tree.body
    parts = dotted.split(".")
    for k, part in enumerate(parts):
        node = find_definition(body, part)
        if node is None:
            return ".".join(parts[:k + 1])
        if k < len(parts) - 1:
            if not isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                return ".".join(parts[:k + 2])
            body = node.body
    return None


def find_definition(body: list[ast.stmt], name: str) -> ast.stmt | None:
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name == name:
            return node
        if isinstance(node, ast.Assign):
            for target in node.targets:
                for t in ast.walk(target):
                    if isinstance(t, ast.Name) and t.id == name:
                        return node
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.target.id == name:
            return node
        if isinstance(node, (ast.If, ast.Try, ast.With)):  # definitions under `if`, `try`
            inner = [*node.body, *getattr(node, "orelse", []), *getattr(node, "finalbody", [])]
            for handler in getattr(node, "handlers", []):
                inner += handler.body
            found = find_definition(inner, name)
            if found is not None:
                return found
    return None


@lru_cache(maxsize=None)
def parse_module(path: Path) -> ast.AST:
    return ast.parse(path.read_text(), str(path))


_REF = re.compile(r"(?<![\w/.-])((?:[\w.-]+/)*[\w.-]+\.py)::([A-Za-z_]\w*(?:(?:::|\.)[A-Za-z_]\w*)*)")


def check_refs(lines: list[tuple[int, str]], doc: Path, root: Path = ROOT) -> list[tuple[int, str]]:
    """``path.py::Name`` references in ``lines`` (``(line, text)``)."""
    out = []
    for n, text in lines:
        for m in _REF.finditer(text):
            rel, name = m.group(1), m.group(2).replace("::", ".")
            path = next((p for p in (root / rel, doc.parent / rel) if p.is_file()), None)
            if path is None:
                out.append((n, f"{m.group(0)}: {rel} does not exist"))
                continue
            try:
                missing = defined_names(parse_module(path), name)
            except SyntaxError as exc:
                out.append((n, f"{m.group(0)}: {rel} does not parse ({exc.msg})"))
                continue
            if missing is not None:
                out.append((n, f"{m.group(0)}: {rel} defines no {missing}"))
    return out


def _expand_braces(pattern: str) -> list[str]:
    m = re.search(r"\{([^{}]*,[^{}]*)\}", pattern)
    if not m:
        return [pattern]
    return [x for alt in m.group(1).split(",") for x in _expand_braces(pattern[:m.start()] + alt + pattern[m.end():])]


def repo_path_problem(text: str, root: Path = ROOT) -> str | None:
    """``None`` if ``text`` (a repository path, glob or ``<placeholder>`` pattern) names something
    that exists, else the problem."""
    pattern = re.sub(r"(:\d+(-\d+)?|#L\d+(-L\d+)?)$", "", text)  # file.py:12, file.py#L12
    pattern = PLACEHOLDER.sub("*", pattern).replace(SENTINEL, "*")
    for alt in _expand_braces(pattern):
        if any(c in alt for c in "*?["):
            if glob.glob(str(root / alt), recursive=True):
                return None
        elif (root / alt).exists() and (not alt.endswith("/") or (root / alt).is_dir()):
            return None
    return f"`{text}` does not exist" + (" (no match)" if any(c in pattern for c in "*?[") else "")


def looks_like_repo_path(text: str) -> bool:
    return (re.fullmatch(r"[\w.\-/*?<>{},\[\]]+(:\d+)?", text) is not None
            and text.split("/", 1)[0] in REPO_DIRS and "/" in text and "::" not in text)


def git_ignored(paths: list[str], root: Path = ROOT) -> set[str]:
    """Those of ``paths`` git ignores (files a command creates, like ``configs/hardware/keys/``):
    never in a checkout, so not a doc's drift. Empty outside a git checkout."""
    if not paths:
        return set()
    try:
        proc = subprocess.run(["git", "-C", str(root), "check-ignore", "--no-index", "--stdin"],
                              input="\n".join(paths) + "\n", capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return set()
    return set(proc.stdout.splitlines()) if proc.returncode in (0, 1) else set()


def check_paths(prose: list[str], root: Path = ROOT) -> list[tuple[int, str]]:
    found = []
    for n, span in code_spans(prose):
        if looks_like_repo_path(span):
            problem = repo_path_problem(span, root)
            if problem:
                found.append((n, span, problem))
    ignored = git_ignored(sorted({span for _, span, _ in found}), root)
    return [(n, problem) for n, span, problem in found if span not in ignored]

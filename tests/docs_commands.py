"""The project commands of the docs: every ``python -m`` line of a shell block (and every one quoted
in the prose's inline code) parsed against the entry point's own argparse parser: subcommands,
flags, their values and choices, and the ``--config`` files they name."""

from __future__ import annotations

import argparse
import difflib
import importlib
import re
import shlex
from functools import lru_cache
from pathlib import Path

from .docs_markdown import PLACEHOLDER, SENTINEL, Block, code_spans
from .docs_names import looks_like_repo_path, repo_path_problem
from .paths import ROOT

#: the packages whose ``python -m`` entry points are checked
PACKAGES = ("companion", "link_firmware_sim", "sitl")
#: the languages of the fenced blocks whose lines are shell commands
SHELL_LANGS = {"sh", "bash", "shell", "console", "zsh", "shell-session"}
#: commands that run the command after them (their own options are skipped)
WRAPPERS = {"env", "time", "nohup", "exec", "sudo", "nice", "timeout", "taskset", "chrt", "command", "xvfb-run"}


@lru_cache(maxsize=None)
def entry_points(root: Path = ROOT) -> dict[str, Path]:
    """Every ``python -m`` entry point of the packages: ``module -> file`` (``pkg/__main__.py`` runs
    as ``pkg``; a module with an ``if __name__ == "__main__"`` block runs as itself)."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root).with_suffix("")
            if path.name == "__main__.py":
                out[".".join(rel.parts[:-1])] = path
            elif path.name != "__init__.py" and re.search(r"^if __name__ == ['\"]__main__['\"]",
                                                        path.read_text(), re.M):
                out[".".join(rel.parts)] = path
    return out


@lru_cache(maxsize=None)
def module_parser(module: str) -> argparse.ArgumentParser:
    """The entry point's own parser: ``build_parser()`` of its ``__main__`` (or of the module)."""
    path = entry_points()[module]
    name = module + ".__main__" if path.name == "__main__.py" else module
    return importlib.import_module(name).build_parser()


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def _positionals(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in parser._actions if not a.option_strings and not isinstance(a, argparse._SubParsersAction)]


_ALT = "\x01"  # `a|b` inside [ ]: alternatives of one value


def _is_metavar(tok: str) -> bool:
    """A value that stands for one (not checked against choices): ``<run>``, ``$X``, ``{a,b}``,
    ``S``, ``DIR``, ``IN.npz``, ``...``, globs."""
    return (SENTINEL in tok or "$" in tok or tok.startswith("{") or tok in ("...", "…") or "*" in tok
            or re.fullmatch(r"[A-Z][A-Z0-9_]*(\.[a-z0-9]+)?", tok) is not None)


def strip_comment(line: str) -> str:
    """``line`` without its shell comment (a ``#`` that starts a word, outside quotes)."""
    quote = None
    for k, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (k == 0 or line[k - 1].isspace()):
            return line[:k].rstrip()
    return line


def _prepare(line: str) -> tuple[str, list[str]]:
    """Protect placeholders, drop the comment, resolve ``[...]`` optional syntax (brackets
    removed, `` | `` between alternatives a space, ``a|b`` kept as one alternatives token) and lift
    ``$(...)`` substitutions out as commands of their own. Returns ``(line, substitutions)``."""
    subs = []

    def lift(m):
        subs.append(m.group(1))
        return "SUBST$"

    line = PLACEHOLDER.sub(SENTINEL, strip_comment(line))
    prev = None
    while prev != line:  # innermost first
        prev = line
        line = re.sub(r"\$\(([^()]*)\)", lift, line)
    out, quote, depth = [], None, 0
    for k, ch in enumerate(line):
        if quote:
            out.append(ch)
            if ch == quote:
                quote = None
            continue
        if ch in "'\"":
            quote = ch
        elif ch == "[" and (k == 0 or line[k - 1].isspace() or line[k - 1] in "[|"):
            depth += 1
            out.append(" ")
            continue
        elif ch == "]" and depth:
            depth -= 1
            out.append(" ")
            continue
        elif ch == "|" and depth:
            spaced = (k > 0 and line[k - 1].isspace()) or (k + 1 < len(line) and line[k + 1].isspace())
            out.append(" " if spaced else _ALT)
            continue
        out.append(ch)
    return "".join(out), subs


def logical_lines(block: Block) -> list[tuple[int, str]]:
    """The block's commands as ``(line, text)``: continuations joined; in a console block with
    prompts only the prompt lines (without ``$ ``)."""
    lines = block.lines
    prompted = block.lang in ("console", "shell-session") and any(x.lstrip().startswith("$ ") for x in lines)
    out, buf, start = [], [], None
    for n, raw in enumerate(lines, block.start):
        line = raw
        if not buf:
            stripped = line.lstrip()
            if prompted:
                if not stripped.startswith("$ "):
                    continue
                line = stripped[2:]
            elif stripped.startswith("$ "):
                line = stripped[2:]
            start = n
        if line.rstrip().endswith("\\"):
            buf.append(line.rstrip()[:-1])
            continue
        buf.append(line)
        out.append((start, " ".join(buf)))
        buf = []
    if buf:
        out.append((start, " ".join(buf)))
    return out


def simple_commands(line: str) -> list[list[str]]:
    """A shell line's simple commands as token lists (split at ``&&``, ``||``, ``;``, ``|``, ``&``,
    parentheses; redirections dropped), ``$(...)`` contents included as commands of their own."""
    text, subs = _prepare(line)
    cmds = []
    for sub in subs:
        cmds += simple_commands(sub)
    lexer = shlex.shlex(text, posix=True, punctuation_chars=";&|()<>")
    lexer.whitespace_split = True
    lexer.commenters = ""
    try:
        tokens = list(lexer)
    except ValueError:  # unbalanced quotes: nothing we can check
        return cmds
    current: list[str] = []
    skip_next = False
    for tok in tokens:
        if skip_next:
            skip_next = False
            continue
        if tok and set(tok) <= set(";&|()"):
            if current:
                cmds.append(current)
            current = []
        elif tok and set(tok) <= set("<>&"):  # a redirection: drop it and its file (or descriptor)
            if current and current[-1].isdigit():
                current.pop()  # the 2 of 2>&1
            skip_next = True
        else:
            current.append(tok)
    if current:
        cmds.append(current)
    return cmds


def _is_python(tok: str) -> bool:
    return re.fullmatch(r"python(\d+(\.\d+)?)?", tok.rsplit("/", 1)[-1]) is not None


def python_module(tokens: list[str]) -> tuple[str, list[str]] | None:
    """``(module, its arguments)`` if the command runs ``python -m module``, else ``None``."""
    i = 0
    while i < len(tokens) and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", tokens[i]):
        i += 1
    if i < len(tokens) and tokens[i] in WRAPPERS:
        while i < len(tokens) and not _is_python(tokens[i]):
            i += 1
    if i >= len(tokens) or not _is_python(tokens[i]):
        return None
    i += 1
    while i < len(tokens):
        tok = tokens[i]
        if tok == "-m":
            return (tokens[i + 1], tokens[i + 2:]) if i + 1 < len(tokens) else None
        if tok.startswith("-m") and len(tok) > 2:
            return tok[2:], tokens[i + 1:]
        if tok in ("-X", "-W"):
            i += 2
        elif tok.startswith("-") and tok != "-c":
            i += 1
        else:
            return None  # a script, -c or nothing
    return None


def _alternatives(tok: str) -> list[str]:
    return [t for t in tok.split(_ALT) if t]


def _show(tok: str) -> str:
    return tok.replace(SENTINEL, "<...>").replace(_ALT, "|")


def check_module_args(module: str, args: list[str], complete: bool = True) -> list[str]:
    """What is wrong with ``python -m module args`` for the module's parser (empty: it parses).
    ``complete=False`` (a command quoted in prose): unknown subcommands, flags and choices only, not
    what is missing."""
    if module not in entry_points():
        runnable = ", ".join(sorted(entry_points()))
        return [f"`python -m {module}` is not an entry point of the project (those are: {runnable})"]
    parser = module_parser(module)
    problems: list[str] = []
    prog = f"python -m {module}"
    wants_help = any(t in ("-h", "--help") for t in args)
    level = [parser]  # the parsers whose options are valid now (several after a placeholder subcommand)
    chosen = False
    seen: set[argparse.Action] = set()
    positional_index = 0
    i = 0

    def options_of(parsers):
        opts = {}
        for p in parsers:
            opts.update(p._option_string_actions)
        return opts

    while i < len(args):
        tok = args[i]
        i += 1
        if tok in ("...", "…", ""):
            continue
        if tok.startswith("-") and tok != "-" and not re.fullmatch(r"-\d+(\.\d+)?", tok):
            if tok == "--":
                break
            name, eq, value = tok.partition("=")
            opts = options_of(level)
            action = opts.get(name)
            if action is None:
                prefixes = [o for o in opts if o.startswith(name) and name.startswith("--")]
                hint = (f" (an abbreviation of {prefixes[0]}: spell it out)" if len(prefixes) == 1 else
                        "".join(f" (did you mean {m}?)" for m in difflib.get_close_matches(name, list(opts), 1)))
                problems.append(f"unknown flag {_show(name)} for `{prog}`{hint}")
                if not eq and i < len(args) and not args[i].startswith("-"):
                    i += 1  # its value, as far as one can tell
                continue
            seen.add(action)
            nargs = action.nargs
            values: list[str] = []
            if eq:
                values = [value]
            elif nargs == 0:
                pass
            elif nargs in (None, 1) or isinstance(nargs, int):
                count = 1 if nargs is None else nargs
                while count and i < len(args) and not (args[i].startswith("-") and
                                                        not re.fullmatch(r"-\d+(\.\d+)?", args[i])):
                    values.append(args[i])
                    i += 1
                    count -= 1
                if count and complete:
                    problems.append(f"flag {name} of `{prog}` needs a value")
            elif nargs == "?":
                if i < len(args) and not args[i].startswith("-"):
                    values.append(args[i])
                    i += 1
            else:  # '*', '+', REMAINDER
                while i < len(args) and not args[i].startswith("-"):
                    values.append(args[i])
                    i += 1
                if nargs == "+" and not values and complete:
                    problems.append(f"flag {name} of `{prog}` needs a value")
            for value in values:
                for alt in _alternatives(value):
                    if _is_metavar(alt):
                        continue
                    if action.choices is not None and alt not in action.choices:
                        problems.append(f"{name} {alt!r} of `{prog}`: not one of {', '.join(map(str, action.choices))}")
                    elif action.type in (int, float):
                        try:
                            action.type(alt)
                        except ValueError:
                            kind = "an integer" if action.type is int else "a number"
                            problems.append(f"{name} {alt!r} of `{prog}`: not {kind}")
            if name == "--config":
                problems += _missing_repo_paths(values, f"{name} of `{prog}`")
            continue
        # a positional token
        sub = _subparsers(level[0]) if len(level) == 1 else None
        if sub is not None and not chosen:
            if _is_metavar(tok):  # `python -m sitl.bench <bench>`: any subcommand's options
                level = list({id(p): p for p in sub.choices.values()}.values())
            elif tok in sub.choices:
                level = [sub.choices[tok]]
                prog = f"{prog} {tok}"
            else:
                names = ", ".join(sub.choices)
                return problems + [f"unknown subcommand {tok!r} for `{prog}` (one of: {names})"]
            chosen = len(level) != 1 or _subparsers(level[0]) is None  # `campaign run`: a subcommand's own
            positional_index = 0
            seen = set()
            continue
        if len(level) != 1:
            continue
        positionals = _positionals(level[0])
        if positional_index >= len(positionals):
            problems.append(f"unexpected argument {_show(tok)!r} for `{prog}`")
            continue
        action = positionals[positional_index]
        seen.add(action)
        if action.nargs not in ("*", "+", argparse.REMAINDER):
            positional_index += 1
        if action.choices is not None:
            for alt in _alternatives(tok):
                if not _is_metavar(alt) and alt not in action.choices:
                    problems.append(f"argument {action.metavar or action.dest} {alt!r} of `{prog}`: not one of "
                                    f"{', '.join(map(str, action.choices))}")
    if wants_help or len(level) != 1 or not complete:
        return problems
    parser = level[0]
    sub = _subparsers(parser)
    if sub is not None and not chosen and sub.required:
        problems.append(f"`{prog}` needs a subcommand (one of: {', '.join(sub.choices)})")
    for action in parser._actions:
        if action in seen or isinstance(action, (argparse._SubParsersAction, argparse._HelpAction)):
            continue
        if action.option_strings and action.required:
            problems.append(f"`{prog}` needs {action.option_strings[0]}")
        elif not action.option_strings and action.nargs not in ("?", "*", argparse.REMAINDER):
            problems.append(f"`{prog}` needs its argument {action.metavar or action.dest}")
    return problems


def check_command_line(line: str, complete: bool = True) -> list[str]:
    """Problems of the project commands in one shell line."""
    out = []
    for tokens in simple_commands(line):
        found = python_module(tokens)
        if found is None:
            continue
        module, args = found
        if module.split(".")[0] not in PACKAGES:
            continue  # pytest, venv, pip, ...
        shown = " ".join(strip_comment(line).split())
        out += [f"{shown}: {p}" for p in check_module_args(module, args, complete)]
    return out


def check_commands(blocks: list[Block], prose: list[str] = ()) -> list[tuple[int, str]]:
    """Problems of the shell blocks' project commands as ``(line, message)``; also of commands quoted
    in the prose's inline code (``python -m sitl fly --video X``), there only what is wrong, not
    what is left out (a quote may be partial)."""
    out = []
    for block in blocks:
        if block.lang not in SHELL_LANGS:
            continue
        for line_no, line in logical_lines(block):
            out += [(line_no, p) for p in check_command_line(line)]
    for line_no, span in code_spans(list(prose)):
        if re.match(r"(\S*/)?python[\d.]*\s+-m\s", span):
            out += [(line_no, p) for p in check_command_line(span, complete=False)]
    return out


def _missing_repo_paths(values: list[str], what: str) -> list[str]:
    out = []
    for v in values:
        for alt in _alternatives(v):
            alt = alt.replace(SENTINEL, "<x>")
            if looks_like_repo_path(alt) and "$" not in alt:
                problem = repo_path_problem(alt)
                if problem:
                    out.append(f"{what}: {problem}")
    return out

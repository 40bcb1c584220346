"""The scenario kinds: each a registered task with its own schema and flight; one command line flies
them all (``python -m sitl fly --config FILE``; ``python -m sitl launch`` the kinds with a fleet form).

A scenario file names its kind with a top-level ``kind = "..."``; a file without one is a chain.

=============== ==================================================== ===========
kind            what it flies                                        fleet form
=============== ==================================================== ===========
``chain``       a chain of links flying its trajectory; cameras and  yes
                scripted faults are options of it (:mod:`.chain`)
``wall_push``   one ODAR pushing a wall under hybrid pose/wrench     no
                control (:mod:`.wall_push`)
``pspm_jump``   one ODAR under a scripted operator's jumps, with and no
                without PSPM (:mod:`.pspm_jump`)
``slung_load``  vehicles carrying a box by cables, its pose from     no
                their cameras (:mod:`.slung_load`)
=============== ==================================================== ===========

Each kind is a package: its schema (a :class:`~sitl.scenario.Scenario` subclass with its own
tables; the chain's is the base class itself), its flight as a :class:`~sitl.task.Task` on
:class:`~sitl.runner.BatchRunner`, and a :class:`~.kind.ScenarioKind` that says how its files load
and what flies them. Importing this package loads the schemas only (no MuJoCo, no OpenCV): a
file is checked before the simulator is imported.
"""

from __future__ import annotations

from pathlib import Path

from companion.configfile import ConfigError, load_toml

from .chain import KIND as CHAIN
from .kind import ScenarioKind
from .pspm_jump import KIND as PSPM_JUMP
from .slung_load import KIND as SLUNG_LOAD
from .wall_push import KIND as WALL_PUSH

__all__ = ["KINDS", "ScenarioKind", "kind_of", "load"]

#: every scenario kind by its ``kind`` key
KINDS: dict[str, ScenarioKind] = {k.name: k for k in (CHAIN, WALL_PUSH, PSPM_JUMP, SLUNG_LOAD)}


def kind_of(path: str | Path) -> ScenarioKind:
    """The kind a scenario file names (``kind = "..."``; none: ``chain``); a
    :class:`~companion.configfile.ConfigError` for an unreadable file or an unknown kind."""
    data = load_toml(path)
    name = data.get("kind", CHAIN.name)
    if not isinstance(name, str) or name not in KINDS:
        raise ConfigError(str(path), "kind", f"expected one of {', '.join(repr(k) for k in KINDS)}, got {name!r}")
    return KINDS[name]


def load(path: str | Path, **overrides):
    """``(kind, scenario)`` of the scenario file at ``path``, read and validated by its kind's
    schema; ``overrides`` replace top-level fields (``duration_s``, ``seed``), and ``settings=``
    (a mapping of dotted keys, :func:`companion.config.load_setup`) sets keys in the file's tables. A
    :class:`~companion.configfile.ConfigError` names the file, the key and the reason; a table of
    another kind's in a file that does not name that kind says which ``kind`` it needs."""
    kind = kind_of(path)
    try:
        return kind, kind.load(path, **overrides)
    except ConfigError as exc:
        other = next((k for k in KINDS.values() if k is not kind and exc.key in k.tables), None)
        if other is None or not exc.reason.startswith("unknown key"):
            raise
        raise ConfigError(exc.file, exc.key, f"{exc.reason}; a [{exc.key}] table belongs to a {other.name} scenario: "
                                             f"add kind = \"{other.name}\" at the top of the file") from None

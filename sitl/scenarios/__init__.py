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
``slung_load``  vehicles carrying a box by cables, its pose from     yes
                their cameras (:mod:`.slung_load`)
``snake``       the thesis's snake-like robot crawling on its CPG    no
                (:mod:`.snake`)
``pivotboard``  the thesis's pivotboard rolling on its CPG           no
                (:mod:`.pivotboard`)
=============== ==================================================== ===========

Each kind is a package: its schema (a :class:`~sitl.scenario.Scenario` subclass with its own
tables; the chain's is the base class itself), its flight as a :class:`~sitl.task.Task` on
:class:`~sitl.runner.BatchRunner`, its fleet form's part as a :class:`~sitl.fleet.task.FleetTask`
on :class:`~sitl.fleet.launcher.Fleet` (if it has one), and a :class:`~.kind.ScenarioKind` that
says how its files load and what flies them. Importing this package loads the schemas only (no MuJoCo, no OpenCV): a
file is checked before the simulator is imported.
"""

from __future__ import annotations

from pathlib import Path

from companion.configfile import ConfigError, load_toml

from .chain import KIND as CHAIN
from .kind import ScenarioKind
from .pspm_jump import KIND as PSPM_JUMP
from .pivotboard import KIND as PIVOTBOARD
from .slung_load import KIND as SLUNG_LOAD
from .snake import KIND as SNAKE
from .wall_push import KIND as WALL_PUSH

__all__ = ["KINDS", "ScenarioKind", "kind_of", "load"]

#: every scenario kind by its ``kind`` key
KINDS: dict[str, ScenarioKind] = {k.name: k for k in (CHAIN, WALL_PUSH, PSPM_JUMP, SLUNG_LOAD, SNAKE, PIVOTBOARD)}


def kind_of(path: str | Path) -> ScenarioKind:
    """The kind a scenario file names (``kind = "..."``; none: ``chain``); a
    :class:`~companion.configfile.ConfigError` for an unreadable file or an unknown kind."""
    return _kind_in(load_toml(path), path)


def _kind_in(data, path) -> ScenarioKind:
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
    data = load_toml(path)
    kind = _kind_in(data, path)
    # (before the file is read: a kind's table may be one the companion's schema holds, [load])
    given = set(data) | {key.split(".")[0] for key in overrides.get("settings") or ()}
    for other in KINDS.values():
        table = next((t for t in other.tables if other is not kind and t in given and t not in kind.tables), None)
        if table is not None:
            raise ConfigError(str(path), table, f"a [{table}] table belongs to a {other.name} scenario: add "
                                                f"kind = \"{other.name}\" at the top of the file")
    return kind, kind.load(path, **overrides)

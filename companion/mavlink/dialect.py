"""The project's MAVLink dialect, generated from ``aerial_skeleton.xml`` with pymavlink's mavgen.

Generated code is never edited or committed: :func:`load_dialect` runs mavgen at first use
(MAVLink 2, Python 3) and caches the module under ``$AERIAL_SKELETON_CACHE`` (default
``$XDG_CACHE_HOME/aerial-skeleton`` or ``~/.cache/aerial-skeleton``), keyed by a fingerprint of
the XML, the included common definitions and the pymavlink version, so editing the XML or
upgrading pymavlink regenerates it. Generation writes to a temporary file and renames it into
place, so processes starting together (a SITL fleet) never import a half-written module.

The module's bytecode is cached beside it too (the import system's own ``__pycache__`` file, a
hash-checked pyc: every import checks it against the source), even where
``PYTHONDONTWRITEBYTECODE`` keeps Python from writing bytecode (many container images set it):
compiling the 1.8 MB module is 0.23 s of every process's start-up, loading its bytecode 3 ms, and
a fleet starts eleven processes, a fault restarts some.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import logging
import os
import py_compile
import shutil
import sys
import tempfile
from functools import lru_cache
from pathlib import Path
from types import ModuleType

__all__ = ["DIALECT_XML", "cache_root", "dialect_fingerprint", "export_definitions", "load_dialect", "tool_environment"]

log = logging.getLogger(__name__)

DIALECT_XML = Path(__file__).with_name("aerial_skeleton.xml")
#: the definitions the dialect is built on: ArduPilot's ardupilotmega.xml (common.xml and the rest,
#: what MAVProxy's modules expect of a dialect, signing's RADIO among them) and what it includes
_INCLUDES = ("ardupilotmega.xml", "common.xml", "standard.xml", "minimal.xml", "uAvionix.xml", "icarous.xml",
             "loweheiser.xml", "cubepilot.xml", "csAirLink.xml")


def _pymavlink_definitions() -> Path:
    import pymavlink

    return Path(pymavlink.__file__).parent / "dialects" / "v20"


def cache_root() -> Path:
    env = os.environ.get("AERIAL_SKELETON_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "aerial-skeleton"


def dialect_fingerprint() -> str:
    """Hash of everything the generated module depends on."""
    import pymavlink

    h = hashlib.sha256()
    h.update(DIALECT_XML.read_bytes())
    defs = _pymavlink_definitions()
    for name in _INCLUDES:
        h.update((defs / name).read_bytes())
    h.update(getattr(pymavlink, "__version__", "unknown").encode())
    return h.hexdigest()[:16]


def _generate(target: Path) -> None:
    from pymavlink.generator import mavgen

    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="skeleton-mavgen-") as tmp:
        tmp = Path(tmp)
        shutil.copy(DIALECT_XML, tmp / DIALECT_XML.name)
        for name in _INCLUDES:
            shutil.copy(_pymavlink_definitions() / name, tmp / name)
        out = tmp / "aerial_skeleton.py"
        opts = mavgen.Opts(str(out), wire_protocol="2.0", language="Python3", validate=False)
        chatter = io.StringIO()
        with contextlib.redirect_stdout(chatter):  # mavgen prints its progress
            ok = mavgen.mavgen(opts, [str(tmp / DIALECT_XML.name)])
        log.debug("mavgen: %s", chatter.getvalue())
        if not ok:
            raise RuntimeError(f"mavgen failed on {DIALECT_XML}: {chatter.getvalue()[-500:]}")
        staged = target.with_suffix(f".{os.getpid()}.tmp")
        shutil.copy(out, staged)
        os.replace(staged, target)
    log.info("generated MAVLink dialect %s", target)


def export_definitions() -> Path:
    """A message-definitions folder (``v1.0/aerial_skeleton.xml`` and its includes) for pymavlink tools.

    MAVProxy, MAVExplorer and ``mavlogdump.py`` decode the dialect's messages when run with
    ``MDEF`` pointing here and ``MAVLINK_DIALECT=aerial_skeleton`` (see :func:`tool_environment`);
    pymavlink then generates its own copy of the module on first use.
    """
    root = cache_root() / "mavlink" / dialect_fingerprint() / "message_definitions"
    v1 = root / "v1.0"
    if not (v1 / DIALECT_XML.name).exists():
        v1.mkdir(parents=True, exist_ok=True)
        for name in _INCLUDES:
            shutil.copy(_pymavlink_definitions() / name, v1 / name)
        staged = v1 / f"{DIALECT_XML.name}.{os.getpid()}.tmp"
        shutil.copy(DIALECT_XML, staged)
        os.replace(staged, v1 / DIALECT_XML.name)  # last: its presence marks a complete folder
    return root


def tool_environment() -> dict[str, str]:
    """Environment for pymavlink's tools to decode this dialect (tlogs, live links)."""
    return {"MAVLINK20": "1", "MAVLINK_DIALECT": DIALECT_XML.stem, "MDEF": str(export_definitions())}


@lru_cache(maxsize=1)
def load_dialect() -> ModuleType:
    """The generated pymavlink module of the dialect (generated on first use, then cached)."""
    fingerprint = dialect_fingerprint()
    target = cache_root() / "mavlink" / fingerprint / "aerial_skeleton.py"
    if not target.exists():
        _generate(target)
    pyc = _cache_bytecode(target)
    name = f"aerial_skeleton_mavlink_{fingerprint}"
    try:
        return _import(name, target)
    except (ValueError, EOFError, TypeError) as exc:  # (marshal's errors: a pyc damaged past its header)
        if pyc is None or not pyc.exists():
            raise
        log.warning("the dialect's cached bytecode %s is damaged (%s): removed, compiling the module", pyc, exc)
        pyc.unlink(missing_ok=True)
        return _import(name, target)


def _import(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)  # (takes the pyc when it matches the source's hash)
    except BaseException:
        del sys.modules[name]
        raise
    return module


def _cache_bytecode(target: Path) -> Path | None:
    """Write ``target``'s pyc where the import system looks for it, unless one for this source and
    this Python is there (a hash-checked pyc holds no time stamp: processes that write it together
    write the same bytes, each atomically); its path, or ``None`` where none is written (no
    ``__pycache__`` path for it; a read-only cache: a warning, and every start-up compiles the
    module)."""
    try:
        pyc = Path(importlib.util.cache_from_source(str(target)))
    except NotImplementedError:  # (sys.implementation.cache_tag is None: no bytecode caching at all)
        return None
    if not _pyc_matches(pyc, target):
        try:
            py_compile.compile(str(target), cfile=str(pyc), doraise=True,
                               invalidation_mode=py_compile.PycInvalidationMode.CHECKED_HASH)
        except (OSError, py_compile.PyCompileError) as exc:
            log.warning("could not cache the MAVLink dialect's bytecode (%s): each start-up compiles it", exc)
            return None
    return pyc


def _pyc_matches(pyc: Path, source: Path) -> bool:
    """``pyc``'s header is a hash-checked pyc of this Python's bytecode for ``source``'s bytes (the
    import system's own test, done here to rewrite one that fails it, not compile at every start)."""
    try:
        with open(pyc, "rb") as f:
            head = f.read(16)
        return (len(head) == 16 and head[:4] == importlib.util.MAGIC_NUMBER
                and int.from_bytes(head[4:8], "little") == 0b11  # hash-based, checked
                and head[8:16] == importlib.util.source_hash(source.read_bytes()))
    except OSError:
        return False

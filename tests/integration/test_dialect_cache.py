"""The generated MAVLink dialect's cache: the module and its bytecode (companion.mavlink.dialect).

Each case runs ``load_dialect`` in a fresh interpreter (the function caches its module per
process) with ``PYTHONDONTWRITEBYTECODE=1``, under a cache root of its own that holds this
session's generated module (copied: no mavgen run)."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from companion.mavlink import dialect
from companion.mavlink.dialect import dialect_fingerprint, load_dialect

_LOAD = ("import logging, sys; logging.basicConfig(level=logging.WARNING); "
         "from companion.mavlink.dialect import load_dialect; D = load_dialect(); "
         "print(D.__file__); print(D.MAVLINK_MSG_ID_SKELETON_LINK_STATE)")


@pytest.fixture()
def cache(tmp_path) -> tuple[dict, Path, Path]:
    """(environment, module, its pyc path) of a cache root holding the generated module, no pyc."""
    module = tmp_path / "mavlink" / dialect_fingerprint() / "aerial_skeleton.py"
    module.parent.mkdir(parents=True)
    shutil.copy(load_dialect().__file__, module)
    env = dict(os.environ, AERIAL_SKELETON_CACHE=str(tmp_path), PYTHONDONTWRITEBYTECODE="1")
    return env, module, Path(importlib.util.cache_from_source(str(module)))


def _load(env: dict, *flags: str) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, *flags, "-c", _LOAD], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out


def test_the_dialect_loads_from_its_cached_bytecode_where_python_writes_none(cache):
    env, module, pyc = cache
    first = _load(env)
    assert first.stdout.split()[0] == str(module)
    assert dialect._pyc_matches(pyc, module)  # written, for this source, hash-checked
    head = pyc.read_bytes()[:16]
    assert head[:4] == importlib.util.MAGIC_NUMBER and int.from_bytes(head[4:8], "little") == 0b11
    written = pyc.stat().st_mtime_ns
    # the next process imports the bytecode (the import system says so under -v), writes nothing
    second = _load(env, "-v")
    assert f"{pyc} matches {module}" in second.stderr
    assert second.stdout.split()[-1] == first.stdout.split()[-1]
    assert pyc.stat().st_mtime_ns == written


def test_a_stale_or_damaged_cached_bytecode_is_replaced(cache):
    env, module, pyc = cache
    _load(env)
    good = pyc.read_bytes()
    # a header that does not match (another source's hash): rewritten before the import
    pyc.write_bytes(good[:8] + bytes(8) + good[16:])
    assert not dialect._pyc_matches(pyc, module)
    _load(env)
    assert pyc.read_bytes() == good
    # a matching header over damaged bytecode: the import fails on it; the pyc is removed, the
    # module compiled from its source (a warning), and the next start-up writes the pyc again
    pyc.write_bytes(good[:16] + b"\xff" * 64)
    out = _load(env)
    assert "cached bytecode" in out.stderr and "damaged" in out.stderr
    assert not pyc.exists()
    _load(env)
    assert pyc.read_bytes() == good


def test_a_cache_without_room_for_bytecode_still_loads(cache):
    """``__pycache__`` cannot be made (a file in its place): a warning, the module compiled."""
    env, module, pyc = cache
    pyc.parent.write_text("not a folder")
    out = _load(env)
    assert "could not cache the MAVLink dialect's bytecode" in out.stderr
    assert out.stdout.split()[0] == str(module)

"""The kernels' disk cache after an update (companion.kernels.jit.drop_stale_caches): a change in
any kernel package's source drops the cached machine code of every package, since a kernel's
cache holds the kernels it calls from other modules; an unchanged tree keeps its caches."""

from __future__ import annotations

from companion.kernels.jit import drop_stale_caches


def _tree(tmp_path):
    folders = []
    for name in ("a", "b"):
        f = tmp_path / name
        (f / "__pycache__").mkdir(parents=True)
        (f / "k.py").write_text(f"X = {name!r}\n")
        folders.append(f)
    return folders


def _caches(folders):
    for f in folders:
        for ext in ("nbi", "nbc"):
            (f / "__pycache__" / f"k.fn-1.py311.{ext}").write_bytes(b"machine code")


def test_a_changed_source_anywhere_drops_every_packages_cached_kernels(tmp_path):
    a, b = folders = _tree(tmp_path)
    assert drop_stale_caches(folders) == folders  # no fingerprint yet: nothing cached is trusted
    _caches(folders)
    assert drop_stale_caches(folders) == []  # unchanged: kept
    assert len(list((a / "__pycache__").glob("*.nb*"))) == 2
    (b / "k.py").write_text("X = 'changed'\n")  # a callee's module changes, a's does not
    assert drop_stale_caches(folders) == folders
    assert not list(a.glob("__pycache__/*.nb*")) and not list(b.glob("__pycache__/*.nb*"))
    assert drop_stale_caches([*folders, tmp_path / "missing"]) == []

"""A warm-up that takes long is compiling the kernels (a machine's first run) and says so; a quick
one (a load from numba's cache) says nothing (sitl.warm)."""

from __future__ import annotations

import logging
import time

import pytest

import sitl.warm as warm


@pytest.mark.parametrize("slow", [True, False])
def test_a_long_warm_up_says_it_is_compiling(monkeypatch, caplog, slow):
    monkeypatch.setattr(warm, "COMPILING_NOTE_S", 0.05)
    for name in ("warm_up_rotors", "warm_up_sensors"):
        monkeypatch.setattr(warm, name, (lambda: time.sleep(0.1)) if slow and name == "warm_up_rotors" else (lambda: None))
    for module in (warm._firmware_kernels, warm._companion_kernels):
        monkeypatch.setattr(module, "warm_up", lambda: 0.0)
    with caplog.at_level(logging.WARNING, logger="sitl.warm"):
        seconds = warm.warm_up_kernels()
    text = caplog.text
    assert ("compiling the simulator's kernels" in text and "kernels compiled in" in text) == slow
    assert slow == (seconds > 0.05)
    if not slow:
        assert not text

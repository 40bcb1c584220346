"""A warm-up that takes long says why (a machine's first run compiles the kernels); a quick
one (a load from numba's cache) says nothing (sitl.warm)."""

from __future__ import annotations

import logging
import time

import pytest

import sitl.warm as warm


@pytest.mark.parametrize("slow", [True, False])
def test_a_long_warm_up_says_it_is_compiling(monkeypatch, caplog, slow):
    monkeypatch.setattr(warm, "COMPILING_NOTE_S", 0.05)
    monkeypatch.setattr(warm, "warm_up_rotors", (lambda: time.sleep(0.1)) if slow else (lambda: None))
    monkeypatch.setattr(warm, "warm_up_sensors", lambda: None)
    for module in (warm._firmware_kernels, warm._companion_kernels):
        monkeypatch.setattr(module, "warm_up", lambda: 0.0)
    with caplog.at_level(logging.WARNING, logger="sitl.warm"):
        seconds = warm.warm_up_kernels()
    text = caplog.text
    assert ("a first run on this machine compiles them" in text and "kernels ready in" in text) == slow
    assert slow == (seconds > 0.05)
    if not slow:
        assert not text

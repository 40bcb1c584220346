"""A warm-up that takes long says why (a machine's first run compiles the kernels); a quick
one (a load from numba's cache) says nothing; a batch flight warms the kernels it runs and not
the fleet's or the CPG's (sitl.warm)."""

from __future__ import annotations

import logging
import time

import pytest

import companion.kernels.warm as companion_warm
import link_firmware_sim.kernels.warm as firmware_warm
import sitl.warm as warm


@pytest.mark.parametrize("slow", [True, False])
def test_a_long_warm_up_says_it_is_compiling(monkeypatch, caplog, slow):
    monkeypatch.setattr(warm, "COMPILING_NOTE_S", 0.05)
    monkeypatch.setattr(warm, "warm_up_rotors", (lambda: time.sleep(0.1)) if slow else (lambda: None))
    monkeypatch.setattr(warm, "warm_up_sensors", lambda: None)
    for module in (warm._firmware_kernels, warm._companion_kernels):
        monkeypatch.setattr(module, "warm_up", lambda **_: 0.0)
    with caplog.at_level(logging.WARNING, logger="sitl.warm"):
        seconds = warm.warm_up_kernels()
    text = caplog.text
    assert ("a first run on this machine compiles them" in text and "kernels ready in" in text) == slow
    assert slow == (seconds > 0.05)
    if not slow:
        assert not text


FLEET_ONLY = {"hil_tick_kernel", "hil_loop_kernel", "sensor_record_at", "frames_to_records", "sensor_records",
              "records_to_frames"}
CPG = {"cpg_step_kernel", "cpg_output_kernel", "body_step_kernel", "link_targets_kernel"}


@pytest.mark.parametrize("batch_only, cpg", [(True, False), (True, True), (False, True)])
def test_a_batch_flight_warms_what_it_runs(monkeypatch, batch_only, cpg):
    if not warm._firmware_kernels.ENABLED:
        pytest.skip("numba not installed: nothing is compiled")
    loaded = []
    for module in (companion_warm, firmware_warm):
        monkeypatch.setattr(module, "load", lambda kernel, *args: loaded.append(kernel.__name__))
    monkeypatch.setattr(warm, "warm_up_rotors", lambda: None)
    monkeypatch.setattr(warm, "warm_up_sensors", lambda: None)
    warm.warm_up_kernels(batch_only=batch_only, cpg=cpg)
    names = set(loaded)
    assert {"tick_kernel", "ekf_predict_kernel", "constraint_apply_batched_kernel", "feedforward_kernel"} <= names
    assert "links_tick_kernel" in names  # (every mode of this process may fly a batch)
    assert FLEET_ONLY.isdisjoint(names) if batch_only else FLEET_ONLY <= names
    assert CPG <= names if cpg else CPG.isdisjoint(names)


def test_the_fleet_warms_no_batch_tick(monkeypatch):
    if not firmware_warm.ENABLED:
        pytest.skip("numba not installed: nothing is compiled")
    loaded = []
    monkeypatch.setattr(firmware_warm, "load", lambda kernel, *args: loaded.append(kernel.__name__))
    firmware_warm.warm_up(batch=False)
    assert FLEET_ONLY <= set(loaded) and "links_tick_kernel" not in loaded and "tick_kernel" in loaded

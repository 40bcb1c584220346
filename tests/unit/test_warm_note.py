"""A warm-up that takes long says why (a machine's first run compiles the kernels); a quick
one (a load from numba's cache) says nothing; a process warms the kernels it runs: a batch
flight not the fleet's lockstep nor, unless it flies one, the CPG's; a fleet not the batch tick,
nor the companion's when its companions run the numpy path (companion.kernels.warm.compile_notice,
sitl.warm)."""

from __future__ import annotations

import logging
import time

import pytest

import companion.kernels.warm as companion_warm
import link_firmware_sim.kernels.warm as firmware_warm
import sitl.warm as warm


@pytest.mark.parametrize("slow", [True, False])
def test_a_long_warm_up_says_it_is_compiling(monkeypatch, caplog, slow):
    monkeypatch.setattr(companion_warm, "COMPILING_NOTE_S", 0.05)
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


@pytest.mark.parametrize("process, report_done", [("firmware", False), ("companion", True)])
def test_every_process_that_compiles_says_so(monkeypatch, caplog, process, report_done):
    """The notice is one helper: a vehicle or a companion daemon started on a fresh machine says
    why it is silent too (the helper as those processes call it; they log the time themselves)."""
    monkeypatch.setattr(companion_warm, "COMPILING_NOTE_S", 0.05)
    logger = logging.getLogger(f"test.{process}")
    with caplog.at_level(logging.WARNING, logger=logger.name):
        with companion_warm.compile_notice(f"the {process}'s compiled kernels", logger, report_done=report_done):
            time.sleep(0.1)
    assert f"loading the {process}'s compiled kernels; a first run" in caplog.text
    assert (f"The {process}'s compiled kernels ready in" in caplog.text) == report_done


FLEET_ONLY = {"hil_tick_kernel", "hil_loop_kernel", "sensor_record_at", "frames_to_records", "sensor_records",
              "records_to_frames"}
CPG = {"cpg_step_kernel", "cpg_output_kernel", "body_step_kernel", "link_targets_kernel"}
COMPANION = {"constraint_apply_batched_kernel", "feedforward_kernel", "joint_nis_kernel"}


@pytest.mark.parametrize("mode, cpg, companion", [("batch", False, True), ("batch", True, True), ("fleet", False, True),
                                              ("fleet", False, False), ("fleet", True, True), ("all", True, True)])
def test_a_process_warms_what_it_runs(monkeypatch, mode, cpg, companion):
    if not firmware_warm.ENABLED:
        pytest.skip("numba not installed: nothing is compiled")
    loaded = []
    for module in (companion_warm, firmware_warm):
        monkeypatch.setattr(module, "load", lambda kernel, *args: loaded.append(kernel.__name__))
    monkeypatch.setattr(warm, "warm_up_rotors", lambda: None)
    monkeypatch.setattr(warm, "warm_up_sensors", lambda: None)
    warm.warm_up_kernels(mode, cpg=cpg, companion=companion)
    names = set(loaded)
    assert {"tick_kernel", "ekf_predict_kernel", "attitude_tick_kernel"} <= names
    assert ("links_tick_kernel" in names) == (mode != "fleet")
    assert FLEET_ONLY.isdisjoint(names) if mode == "batch" else FLEET_ONLY <= names
    assert COMPANION <= names if companion else COMPANION.isdisjoint(names)  # (a fleet's numpy companions: none)
    assert CPG <= names if cpg and companion else CPG.isdisjoint(names)

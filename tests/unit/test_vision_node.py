"""The vision consumer's loop (companion.vision.node.run_node) on an injected clock: when it stops
and what it reports, without waiting on the wall clock."""

from __future__ import annotations

import json

import pytest

from companion.vision.node import run_node
from companion.vision.node_config import VisionNodeSetup, ZenohCameraSource


class SilentSource:
    """A frame source that never delivers (a publisher gone quiet) and counts its polls."""

    kind = "zenoh"
    ended = False

    def __init__(self):
        self.polls = 0
        self.closed = False

    def poll(self, timeout_s: float):
        self.polls += 1
        return []

    def close(self) -> None:
        self.closed = True


class SteppingClock:
    """Monotonic seconds that advance by ``step_s`` at every reading."""

    def __init__(self, step_s: float):
        self.t, self.step_s = 100.0, step_s

    def __call__(self) -> float:
        self.t += self.step_s
        return self.t


SETUP = VisionNodeSetup(zenoh=ZenohCameraSource(prefix="t", connect=("tcp/127.0.0.1:7447",)))


@pytest.mark.parametrize("idle_timeout_s, duration_s, ended_by, polls", [
    (5.0, None, "idle", 4),       # readings at +1 .. +5 s after the start: idle at the fifth
    (0.0, 3.0, "duration", 2),    # the duration is wall time on the same clock
    (2.0, 10.0, "idle", 1),       # whichever comes first
])
def test_the_loop_ends_on_the_clock_it_is_given(tmp_path, idle_timeout_s, duration_s, ended_by, polls):
    setup = VisionNodeSetup(zenoh=SETUP.zenoh, idle_timeout_s=idle_timeout_s)
    src = SilentSource()
    summary = run_node(setup, tmp_path, duration_s=duration_s, source=src, clock=SteppingClock(1.0))
    assert summary["ended_by"] == ended_by
    assert src.polls == polls and src.closed
    assert summary["frames_total"] == 0 and summary["frames_per_s"] == 0.0
    assert json.loads((tmp_path / "vision_summary.json").read_text())["ended_by"] == ended_by
    assert (tmp_path / "vision_frames.jsonl").read_text() == ""


@pytest.mark.parametrize("drain_s, drain_max_s, polls", [
    (3.0, 5.0, 3),   # stopped at +1 s; nothing arrives: polled at +1, +2, +3 s, done at +4 s
    (10.0, 2.0, 2),  # the bound: done 2 s after the stop whatever drain_s says
])
def test_stop_drains_a_zenoh_source_until_quiet_at_most_drain_max_s(tmp_path, drain_s, drain_max_s, polls):
    src = SilentSource()
    summary = run_node(SETUP, tmp_path, stop=lambda: True, drain_s=drain_s, drain_max_s=drain_max_s, source=src,
                       clock=SteppingClock(1.0))
    assert summary["ended_by"] == "stopped" and src.polls == polls and src.closed

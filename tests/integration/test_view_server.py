"""The view's server without a browser: hostile frames (NaN, zero quaternions, missing parts) are
drawn or hidden, never raised; the live view's pause holds the simulation until resumed."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from sitl.view.app import Replay, ViewServer
from sitl.view.frame import Poses, ViewFrame
from sitl.view.live import LiveView
from sitl.view.spec import SceneSpec
from sitl.view.timeline import Timeline

N = 3


@pytest.fixture
def view():
    v = ViewServer(SceneSpec(n=N, rotor_positions_b_m=np.zeros((8, 3)), rotor_directions_b=np.tile([0, 0, 1.0], (8, 1)),
                             load_size_m=(0.5, 0.5, 0.2), load_attach_b_m=np.zeros((N, 3)), joined=False),
                   "test", port=0)
    yield v
    v.close()


def poses(p, q):
    return Poses(np.asarray(p, dtype=float), np.asarray(q, dtype=float))


@pytest.mark.parametrize("p, q", [
    (np.full((N, 3), np.nan), np.tile([1.0, 0, 0, 0], (N, 1))),
    (np.zeros((N, 3)), np.zeros((N, 4))),
    (np.full((N, 3), 1e12), np.tile([np.inf, 0, 0, 0], (N, 1))),
    (np.array([[0, 0, 1.0], [np.nan, 0, 0], [1, 1, 1]]), np.array([[1.0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 2.0]])),
])
def test_hostile_frames_are_shown_or_hidden(view, p, q):
    hostile = poses(p, q)
    f = ViewFrame(t_s=1.0, truth=hostile, ekf=hostile, corrected=hostile, target=hostile, step_t_s=np.nan,
                  correction_from_w_m=np.asarray(p, float), correction_to_w_m=np.asarray(p, float) + 1.0,
                  link_state=np.array([255, 0, 64], dtype=np.uint8), load=poses(p[:1], q[:1]),
                  figures={"tracking_cm": np.nan})
    view.show(f)
    view.panel.append(f)
    view.panel.redraw()
    for what in ("truth", "ekf", "labels", "cables", "corrections"):
        view.scene.set_visible(what, False)
        view.scene.set_visible(what, True)


def test_a_replay_seeks_anywhere(view):
    t = np.arange(5) * 0.02
    q = np.tile([1.0, 0, 0, 0], (5, N, 1))
    replay = Replay(view, Timeline({"t": t, "p_true": np.zeros((5, N, 3)), "q_true": q}))
    try:
        for at in (-1e9, 0.03, 1e9, np.nan):
            replay.seek(at if np.isfinite(at) else 0.0)
        assert replay.t_s == 0.0
        replay.toggle()
        assert replay.playing
    finally:
        replay.close()


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now

    def sleep(self, s):
        self.now += s


def test_the_pause_holds_the_tick_until_resumed(view):
    row = {"t": 0.0, "p_true": np.zeros((N, 3)), "q_true": np.tile([1.0, 0, 0, 0], (N, 1))}
    clock = Clock()
    resumed = threading.Event()

    def sleep(s):
        clock.sleep(s)
        if clock.now > 1.0:  # a second of wall time paused: the person presses resume
            live.toggle()
            resumed.set()

    live = LiveView(view, lambda: (0.0, row, None), clock=clock, sleep=sleep)
    live.toggle()
    live.on_tick(0, 0.0)
    assert resumed.is_set() and not live.paused.is_set() and not live.held.is_set()
    held_for = clock.now
    assert held_for == pytest.approx(1.0, abs=0.06)
    live.on_tick(1, 0.001)  # between checks: nothing happens
    assert clock.now == held_for


def test_a_chosen_speed_paces_the_simulation(view):
    row = {"t": 0.0, "p_true": np.zeros((N, 3)), "q_true": np.tile([1.0, 0, 0, 0], (N, 1))}
    clock = Clock()
    live = LiveView(view, lambda: (0.0, row, None), clock=clock, sleep=clock.sleep)
    live._set_speed("2x")
    for k in range(0, 1001, live.every_ticks):
        live.on_tick(k, k * 0.001)
    assert clock.now == pytest.approx(0.5, abs=0.01)  # 1 s simulated at twice real time


def test_the_speed_to_start_with_is_the_panels_and_paces_from_the_first_tick(view):
    """``--view-speed 1x``: a flight to watch in real time from its first tick, the panel saying so."""
    row = {"t": 0.0, "p_true": np.zeros((N, 3)), "q_true": np.tile([1.0, 0, 0, 0], (N, 1))}
    clock = Clock()
    live = LiveView(view, lambda: (0.0, row, None), clock=clock, sleep=clock.sleep, speed="1x")
    assert live.speed.value == "1x"
    for k in range(0, 1001, live.every_ticks):
        live.on_tick(k, k * 0.001)
    assert clock.now == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("options, speed", [
    ({}, "max"), ({"view_speed": "1x"}, "1x"),  # fly
    ({"speed": 1.0}, "1x"), ({"speed": 0.0}, "max"), ({"speed": 3.0}, "max"),  # launch: the fleet's pace
    ({"speed": 1.0, "view_speed": "0.5x"}, "0.5x"),
])
def test_the_live_views_starting_speed(options, speed):
    import argparse

    from sitl.view.cli import live_speed

    assert live_speed(argparse.Namespace(**{"view_speed": None, **options})) == speed

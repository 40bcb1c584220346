"""A flying run in the view: its newest log rows as frames (:func:`batch_rows`), shown at a
wall-clock rate from the simulation's tick hook, with pause and a speed (:class:`LiveView`).

The tick hook reads the wall clock every :data:`CHECK_EVERY_TICKS` physics ticks between updates;
an update reads the newest rows only (never the whole log), so its cost does not grow with the
flight, and sends the scene only while a browser has the view open.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from companion.estimation.constraints import joint_error_norms

from .app import SPEEDS, ViewServer, speed_of
from .frame import ViewFrame, frame

__all__ = ["LiveView", "batch_rows", "chain_step_row", "DEFAULT_RATE_HZ"]

#: frames per wall second a live view shows by default
DEFAULT_RATE_HZ = 10.0
#: the tick hook looks at the wall clock every this many physics ticks (10 ms at 1 kHz)
CHECK_EVERY_TICKS = 10
#: the live plots are redrawn this often [wall s]
_PLOT_PERIOD_S = 1.0
#: the cameras' images are sent this often [wall s]
_IMAGE_PERIOD_S = 0.5


def _newest(lists) -> dict:
    return {k: v[-1] for k, v in lists.items() if len(v)}


def chain_step_row(engine_rows: list[tuple[list[int], dict]], n: int, d: np.ndarray) -> dict | None:
    """The newest companion step over the whole chain from each engine's newest step row (and the
    chain indices of its rows): the states it used and corrected (NaN for a link no engine has a
    row for), each engine's global-step flag, and the eq. 3 joint errors before and after."""
    rows = [(idx, r) for idx, r in engine_rows if r]
    if not rows:
        return None
    out = {"t_sckf": max(float(r["t_sckf"]) for _, r in rows),
           "global_applied": np.array([bool(r.get("global_applied", False)) for _, r in rows])}
    for key, width in (("p_ekf_sckf", 3), ("v_ekf_sckf", 3), ("q_ekf_sckf", 4), ("w_sckf", 3),
                       ("p_corr_sckf", 3), ("v_corr_sckf", 3), ("q_corr_sckf", 4)):
        full = np.full((n, width), np.nan)
        for idx, r in rows:
            if key in r:
                full[idx] = r[key]
        out[key] = full
    for when, suffix in (("before", "ekf"), ("after", "corr")):
        w = out["w_sckf"]
        pos, vel = joint_error_norms(out[f"p_{suffix}_sckf"], out[f"v_{suffix}_sckf"], out[f"q_{suffix}_sckf"], w, d)
        out[f"con_pos_{when}"], out[f"con_vel_{when}"] = pos, vel
    return out


def batch_rows(runner) -> Callable[[], tuple[float, dict, dict | None] | None]:
    """The newest ``(t, log row, chain step row)`` of batch runner ``runner`` (``None`` before its
    first log row)."""
    def newest():
        row = _newest(vars(runner.log))
        if "t" not in row:
            return None
        row["home_offset_w_m"] = runner.engines[0].targets.home_offset_w_m  # (the targets in the truth's frame)
        engines = [([lk.index for lk in e.links], _newest(e.step.log)) for e in runner.engines]
        return float(row["t"]), row, chain_step_row(engines, runner.n, runner.d)
    return newest


class LiveView:
    """Shows ``rows()`` (``(t, log row, step row)`` or ``None``) in ``view`` at ``rate_hz`` frames
    per wall second from :meth:`on_tick`, the simulation's tick hook; pauses the simulation while
    paused and paces it at the chosen speed, ``speed`` to start with (``clock``, ``sleep``: wall
    time)."""

    def __init__(self, view: ViewServer, rows: Callable, rate_hz: float = DEFAULT_RATE_HZ,
                 clock=time.monotonic, sleep=time.sleep, every_ticks: int = CHECK_EVERY_TICKS, speed: str = "max"):
        self.view, self.rows = view, rows
        self.period_s = 1.0 / rate_hz
        self.clock, self.sleep, self.every_ticks = clock, sleep, every_ticks
        gui = view.server.gui
        with gui.add_folder("Live", order=-1) as self.folder:
            self.pause_button = gui.add_button("pause")
            self.speed = gui.add_dropdown("speed", options=SPEEDS, initial_value=speed)
        self.paused = threading.Event()
        #: set while the simulation waits in a pause (after the paused frame was shown)
        self.held = threading.Event()
        self.pause_button.on_click(lambda _ev: self.toggle())
        self._speed = speed_of(self.speed.value)
        self.speed.on_update(lambda _ev: self._set_speed(self.speed.value))
        self._next_s = 0.0
        self._plot_s = 0.0
        self._pace: tuple[float, float] | None = None  # (simulated, wall) seconds the pace counts from
        self.updates = 0  # frames shown to a browser
        self._unseen = False  # the newest frame was not shown (no browser)
        self._images: dict[int, object] = {}  # camera index -> its newest image not shown yet
        self._image_s = 0.0

    def close(self) -> None:
        """The live controls out of the panel (the run is over)."""
        self.paused.clear()
        self.folder.remove()

    def toggle(self) -> None:
        if self.paused.is_set():
            self.paused.clear()
            self.pause_button.label = "pause"
        else:
            self.paused.set()
            self.pause_button.label = "resume"

    def _set_speed(self, choice: str) -> None:
        self._speed = speed_of(choice)
        self._anchor(None)

    def _anchor(self, t: float | None) -> None:
        self._pace = None if t is None else (t, self.clock())

    def on_tick(self, k: int, t: float) -> None:
        """The tick hook (every ``every_ticks`` physics ticks it looks): an update when one is due,
        the pause, the pace."""
        if k % self.every_ticks:
            return
        now = self.clock()
        if self.paused.is_set():
            self.update()
            self.held.set()
            while self.paused.is_set():
                if self._unseen and self.view.watched():  # a browser opened the view during the pause
                    self.update()
                self.sleep(0.05)
            self.held.clear()
            self._anchor(None)
            now = self.clock()
        speed = self._speed
        if speed != float("inf"):
            if self._pace is None:
                self._anchor(t)
            ahead = (t - self._pace[0]) / speed - (now - self._pace[1])
            if ahead > 0:
                self.sleep(ahead)
                now = self.clock()
        if now >= self._next_s:
            self._next_s = now + self.period_s
            self.update()

    def on_camera_frame(self, captured) -> None:
        """A batch flight's camera frame (:class:`~sitl.cameras.rig.CapturedFrame`): kept until the
        next update shows it in its camera's frustum."""
        self._images[captured.camera_index] = captured.frame.image

    def update(self) -> ViewFrame | None:
        """The newest rows' frame: its figures added to the plots' history and, while a browser
        has the view open, shown (the scene, the plots, the cameras' images); ``None``: no row yet."""
        newest = self.rows()
        if newest is None:
            return None
        f = frame(*newest)
        self.view.panel.append(f)
        self._unseen = not self.view.watched()
        if self._unseen:  # nobody looks: nothing to send (a browser that opens gets the next update)
            return f
        self.view.show(f)
        self.updates += 1
        now = self.clock()
        if self._images and now >= self._image_s:
            self._image_s = now + _IMAGE_PERIOD_S
            images, self._images = self._images, {}
            for index, image in images.items():
                self.view.scene.set_camera_image(index, image)
        if now >= self._plot_s:
            self._plot_s = now + _PLOT_PERIOD_S
            self.view.panel.redraw()
        return f

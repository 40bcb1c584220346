"""The view's server (:class:`ViewServer`: viser on a local port, the scene and the panel) and the
replay of a finished run (:class:`Replay`: a time slider, play/pause and a speed).

viser serves its web client from the files of the installed package: the page needs no internet,
and an SSH tunnel (``ssh -L 8080:localhost:8080 HOST``) shows a view started on another machine.
"""

from __future__ import annotations

import atexit
import logging
import threading
import time

import numpy as np

from .frame import ViewFrame
from .panel import Panel
from .scene import Scene
from .spec import SceneSpec
from .timeline import Timeline

__all__ = ["ViewServer", "Replay", "DEFAULT_PORT", "SPEEDS", "INSTALL_HINT", "speed_of"]

_log = logging.getLogger(__name__)

DEFAULT_PORT = 8080
#: the speed control's choices (times real time; ``max``: as fast as the run goes)
SPEEDS = ("max", "8x", "4x", "2x", "1x", "0.5x", "0.25x")
INSTALL_HINT = "pip install 'aerial-skeleton-stack[view]' (or pip install viser)"


def speed_of(choice: str) -> float:
    """Times real time of a :data:`SPEEDS` choice (``inf`` for ``max``)."""
    return float("inf") if choice == "max" else float(choice.rstrip("x"))


class ViewServer:
    """A viser server on ``host:port`` (0: a free port) with the scene of ``spec`` and the shared
    panel, titled ``title``."""

    def __init__(self, spec: SceneSpec, title: str, host: str = "127.0.0.1", port: int = DEFAULT_PORT):
        import viser  # (the view extra; ImportError names it)

        logging.getLogger("websockets").setLevel(logging.WARNING)  # (a line per browser connection)
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.scene = Scene(self.server, spec)
        self.panel = Panel(self.server, self.scene, title)
        self._aim: np.ndarray | None = None  # where the camera looks

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}"

    def watched(self) -> bool:
        """Whether a browser has the view open."""
        return bool(self.server.get_clients())

    def aim(self, f: ViewFrame) -> bool:
        """Point the camera at frame ``f``'s links (from behind and above, far enough to see the
        whole chain): the camera a browser starts with, and, when the links have moved out of the
        last aim (a take-off), every open browser's too. False when ``f`` has no link pose."""
        p = f.truth.p_w_m[f.truth.known]
        if not len(p):
            return False
        center = p.mean(axis=0)
        reach = max(float(np.ptp(p, axis=0).max()), self.scene.spec.link_length_m) + 1.0
        if self._aim is not None and np.linalg.norm(center - self._aim) < 0.4 * reach:
            return True
        self._aim = center
        position = center + reach * np.array([-0.45, -0.8, 0.4])
        self.server.initial_camera.look_at = tuple(center)
        self.server.initial_camera.position = tuple(position)
        for client in self.server.get_clients().values():
            client.camera.look_at = tuple(center)
            client.camera.position = tuple(position)
        return True

    def show(self, f: ViewFrame) -> None:
        """The scene and the panel at frame ``f`` (the camera follows the links when they leave its view)."""
        self.aim(f)
        self.scene.show(f)
        self.panel.show_frame(f)

    def close(self, wait: bool = True) -> None:
        """Stop serving. ``wait=False`` at the end of a process: its daemon threads end with it, instead
        of a clean stop that waits (seconds) for each connected browser to close its connection."""
        if wait:
            self.server.stop()
        else:
            atexit.unregister(self.server.stop)


def _decode(jpeg: bytes) -> np.ndarray | None:
    """An RGB image of JPEG bytes (OpenCV); ``None`` for bytes that are not one."""
    import cv2

    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR) if jpeg else None
    return None if image is None else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


class Replay:
    """A finished run in ``view``: a time slider over ``timeline``, play/pause and a speed; a
    thread advances the time while playing (``clock``: wall seconds)."""

    #: updates per wall second while playing
    RATE_HZ = 30.0

    def __init__(self, view: ViewServer, timeline: Timeline, start_s: float | None = None, clock=time.monotonic):
        self.view, self.timeline, self.clock = view, timeline, clock
        gui = view.server.gui
        t0 = timeline.start_s if start_s is None else min(max(start_s, timeline.start_s), timeline.end_s)
        self.t_s = t0
        with gui.add_folder("Replay", order=-1):
            step = max((timeline.end_s - timeline.start_s) / 5000.0, 0.02)
            self.slider = gui.add_slider("time [s]", min=timeline.start_s, max=max(timeline.end_s, timeline.start_s + step),
                                         step=step, initial_value=t0)
            self.play = gui.add_button("play", icon=None)
            self.speed = gui.add_dropdown("speed", options=SPEEDS[1:], initial_value="1x")
        self.playing = False
        self._shown: dict[int, int] = {}  # camera -> the frame number its frustum shows
        self._moving = False  # the slider moved by the thread, not a person
        self.slider.on_update(self._on_slider)
        self.play.on_click(lambda _ev: self.toggle())
        view.panel.set_series(timeline.series())
        self.seek(t0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="replay", daemon=True)
        self._thread.start()

    def toggle(self) -> None:
        """Play from where the slider is, or pause; at the end, play starts from the beginning."""
        if not self.playing and self.t_s >= self.timeline.end_s:
            self.seek(self.timeline.start_s)
        self.playing = not self.playing
        self.play.label = "pause" if self.playing else "play"

    def seek(self, t_s: float) -> None:
        self.t_s = min(max(float(t_s), self.timeline.start_s), self.timeline.end_s)
        self.view.show(self.timeline.frame(self.t_s))
        for cam, (number, jpeg) in self.timeline.images_at(self.t_s).items():
            if self._shown.get(cam) != number:
                self._shown[cam] = number
                image = _decode(jpeg)
                if image is not None:
                    self.view.scene.set_camera_image(cam, image)

    def _on_slider(self, _ev) -> None:
        if not self._moving:
            self.seek(self.slider.value)

    def _run(self) -> None:
        last = self.clock()
        while not self._stop.wait(1.0 / self.RATE_HZ):
            now = self.clock()
            if self.playing:
                self.seek(self.t_s + (now - last) * speed_of(self.speed.value))
                self._moving = True
                try:
                    self.slider.value = self.t_s
                finally:
                    self._moving = False
                if self.t_s >= self.timeline.end_s:
                    self.playing = False
                    self.play.label = "play"
            last = now

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

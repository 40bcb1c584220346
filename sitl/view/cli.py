"""The view on the command line: ``python -m sitl view RUN_DIR`` and the ``--view`` of ``fly`` and
``launch`` (:func:`add_live_args`, :func:`live`)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

from companion.cli import finite_number

from .app import DEFAULT_PORT, INSTALL_HINT, SPEEDS

__all__ = ["add_live_args", "add_view_parser", "live", "live_speed", "serve_until_interrupted", "EXIT_BAD_INPUT"]

EXIT_BAD_INPUT = 2
#: the largest screenshot side [px] (headless Chromium allocates the whole window)
MAX_SCREENSHOT_PX = 8192


def _port(text: str) -> int:
    """argparse type of a TCP port: 0 (any free one) to 65535."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"{value}: a port is 0 (any free one) to 65535")
    return value


def _time(text: str) -> float:
    """argparse type of a time in the run [s]: a finite number."""
    return finite_number(text, lambda v: True, "a time in the run is a finite number of seconds")


def _address(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--view-host", default="127.0.0.1", metavar="HOST",
                   help=f"address the {what} listens on (default 127.0.0.1; 0.0.0.0 for other machines; an SSH "
                        "tunnel needs neither: ssh -L 8080:localhost:8080 HOST)")
    p.add_argument("--view-port", type=_port, default=DEFAULT_PORT, metavar="PORT",
                   help=f"its port (default {DEFAULT_PORT}; the next free one if taken; 0: any free port)")


def add_live_args(p: argparse.ArgumentParser) -> None:
    """``--view``, its address and its starting speed, for ``fly`` and ``launch``."""
    p.add_argument("--view", action="store_true",
                   help="show the run in the browser 3D view as it flies (http://127.0.0.1:8080; pause and speed in "
                        "its panel); when the run is done the view replays it until Ctrl-C")
    p.add_argument("--view-speed", choices=SPEEDS, default=None, metavar="SPEED",
                   help=f"the live view's pace to start with, one of {', '.join(SPEEDS)} (the panel changes it): 1x "
                        "to watch a flight in real time (default: max for fly, a fleet's --speed for launch)")
    _address(p, "view")


def live_speed(args) -> str:
    """The live view's starting pace (:data:`~.app.SPEEDS`): ``--view-speed``, else a fleet's
    ``--speed`` when the panel has it (what the fleet flies at; 0: ``max``), else ``max``."""
    if getattr(args, "view_speed", None):
        return args.view_speed
    pace = getattr(args, "speed", None)
    choice = "max" if not pace else f"{pace:g}x"
    return choice if choice in SPEEDS else "max"


def serve_until_interrupted(message: str | None = None, stop: threading.Event | None = None) -> None:
    """Print ``message`` (to stderr) and wait until Ctrl-C or SIGTERM (or ``stop``); the signals are
    taken before the message says so, and a second signal while stopping changes nothing."""
    stop = stop or threading.Event()
    handler = lambda *_: stop.set()  # noqa: E731
    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        if message:
            print(message, file=sys.stderr, flush=True)
        while not stop.wait(0.2):
            pass
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def _hint_viser() -> bool:
    try:
        import viser  # noqa: F401
    except ImportError:
        print(f"error: the view needs viser; {INSTALL_HINT}", file=sys.stderr)
        return False
    return True


@contextmanager
def live(args, title: str, out_dir: Path):
    """With ``args.view``: a live view of every simulation started in the block (a batch runner or
    the fleet's harness); yields a function that, after the run, replays the run folder given to
    it until Ctrl-C. Without: yields a function that does nothing. ``out_dir``: the run folder
    (a fleet's vehicles and companions write their logs there as they fly)."""
    if not getattr(args, "view", False):
        yield lambda _out_dir: None
        return
    if not _hint_viser():
        raise SystemExit(EXIT_BAD_INPUT)
    from sitl.watch import watching

    from .app import ViewServer
    from .live import LiveView, batch_rows
    from .spec import spec_of_scenario

    state: dict = {}

    def attach(sim) -> None:
        if hasattr(sim, "consumers"):  # a batch flight's cameras: their frames in the frustums
            if "live" in state:
                sim.consumers.append(state["live"].on_camera_frame)
            return
        if "view" not in state:
            state["view"] = ViewServer(spec_of_scenario(sim.scenario), title, args.view_host, args.view_port)
            print(f"view: {state['view'].url}", file=sys.stderr, flush=True)
        if hasattr(sim, "engines"):
            rows = batch_rows(sim)
        else:
            from .fleet_rows import fleet_rows

            rows = fleet_rows(sim, Path(out_dir))
        if "live" not in state:
            state["live"] = LiveView(state["view"], rows, speed=live_speed(args))
        state["live"].rows = rows  # (a kind that flies twice: the second flight's)
        sim.tick_hooks.append(state["live"].on_tick)

    def replay_after(out_dir) -> None:
        view = state.get("view")
        if view is None:
            return
        from .app import Replay
        from .timeline import RunUnreadable, open_run

        try:
            timeline, _ = open_run(out_dir)
        except RunUnreadable as exc:
            print(f"view: {exc}", file=sys.stderr)
            return
        state["live"].close()
        replay = Replay(view, timeline, start_s=timeline.end_s)
        serve_until_interrupted(f"view: the run is done; {view.url} replays it until Ctrl-C")
        replay.close()

    try:
        with watching(attach):
            yield replay_after
    finally:
        if "view" in state:
            state["view"].close(wait=False)


def add_view_parser(sub) -> None:
    """The ``view`` subcommand."""
    p = sub.add_parser("view", help="replay a run folder (batch or fleet) in the browser 3D view",
                       description="Serve the 3D view of a finished run (its log.npz) on localhost, with a time slider, "
                                   "play/pause and a speed; open the printed address in a browser.")
    p.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="a run folder of python -m sitl fly or launch")
    _address(p, "view")
    p.add_argument("--at", type=_time, metavar="S", help="start at S simulated seconds (default: the start)")
    p.add_argument("--play", action="store_true", help="start playing at once")
    p.add_argument("--screenshot", metavar="PNG", type=Path,
                   help="instead of serving: open the view in headless Chromium, save a screenshot (PNG, or JPEG for "
                        "a .jpg name) and exit")
    p.add_argument("--size", default="1280x800", metavar="WxH", help="the screenshot's size (default 1280x800)")
    p.set_defaults(func=cmd_view)


def cmd_view(args) -> int:
    if not _hint_viser():
        return EXIT_BAD_INPUT
    from .app import Replay, ViewServer
    from .timeline import RunUnreadable, open_run

    try:
        try:
            size = tuple(int(v) for v in args.size.lower().split("x"))
        except ValueError:
            size = ()
        if len(size) != 2 or min(size) < 64 or max(size) > MAX_SCREENSHOT_PX:
            raise ValueError(f"--size {args.size}: expected WIDTHxHEIGHT, each from 64 to {MAX_SCREENSHOT_PX}")
        timeline, spec = open_run(args.run_dir)
    except (RunUnreadable, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    view = ViewServer(spec, Path(args.run_dir).resolve().name, args.view_host, args.view_port)
    replay = Replay(view, timeline, start_s=args.at)
    try:
        if args.screenshot is not None:
            return _screenshot(view, args.screenshot, size, replay.timeline.frame(replay.t_s).truth.p_w_m)
        if args.play:
            replay.toggle()
        serve_until_interrupted(f"view: {view.url} (Ctrl-C to quit)")
        return 0
    finally:
        replay.close()
        view.close(wait=False)


def _screenshot(view, path: Path, size: tuple[int, int], p_w_m) -> int:
    """Open ``view`` in headless Chromium, wait until its scene holds a node at each link's pose
    ``p_w_m`` (n, 3), save a screenshot to ``path``."""
    import numpy as np

    from .browser import BrowserUnavailable, HeadlessBrowser
    from .probe import DISMISS_NOTICES, OBSERVE_SCENES, links_shown_js

    shown = p_w_m[np.isfinite(p_w_m).all(axis=1)]
    try:
        with HeadlessBrowser(width=size[0], height=size[1]) as browser:
            browser.add_init_script(OBSERVE_SCENES)
            browser.open(view.url)
            browser.wait_for(f"{links_shown_js(shown)} >= {len(shown)}", timeout_s=60.0)
            browser.evaluate(DISMISS_NOTICES)
            image = browser.settled_screenshot("jpeg" if path.suffix.lower() in (".jpg", ".jpeg") else "png")
    except (BrowserUnavailable, TimeoutError, RuntimeError) as exc:
        print(f"error: screenshot: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(image)
    print(f"wrote {path}")
    return 0

"""The 3D view as a person uses it: ``python -m sitl view`` on a short flight opened in headless
Chromium, a live view of a batch flight paused and looked at, and the run's MCAP read back."""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from sitl.view.browser import HeadlessBrowser
from sitl.view.probe import NEXT_FRAMES, OBSERVE_SCENES, links_shown_js

pytestmark = pytest.mark.browser
ROOT = Path(__file__).resolve().parents[2]
THREE_LINK = ROOT / "configs/sitl/chain/three_link.toml"
FLIGHT_S = 9.0



@pytest.fixture(scope="module")
def flown(tmp_path_factory, browser_binary) -> Path:
    """A short three-link batch flight's run folder, flown by the command line."""
    out = tmp_path_factory.mktemp("view") / "run"
    proc = subprocess.run([sys.executable, "-m", "sitl", "fly", "--config", str(THREE_LINK), "--duration", str(FLIGHT_S),
                           "--out", str(out), "--quiet", "--no-plots"], cwd=ROOT, capture_output=True, text=True,
                          timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def _start_view(run_dir: Path, *extra: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "sitl", "view", str(run_dir), "--view-port", "0", *extra], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seen = []
    for line in proc.stdout:
        seen.append(line)
        m = re.search(r"view: (http://\S+)", line)
        if m:
            return proc, m.group(1)
    proc.wait(timeout=10)
    raise AssertionError(f"sitl view printed no address (exit {proc.returncode}):\n{''.join(seen)[-3000:]}")


def _stop(proc: subprocess.Popen) -> int:
    proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()


def _assert_not_blank(png: bytes, width: int, height: int) -> None:
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (height, width, 3)
    scene = img[:, : int(width * 0.6)]  # the 3D part (the panel is on the right)
    assert len(np.unique(scene.reshape(-1, 3), axis=0)) > 50, "the scene looks blank"
    b, g, r = (scene[..., c].astype(int) for c in range(3))
    blue = (b > r + 60) & (b > g + 30)  # the links' bodies (flying: blue)
    assert blue.sum() > 50, "no link body in the picture"


def _log(run_dir: Path) -> dict[str, np.ndarray]:
    with np.load(run_dir / "log.npz") as npz:
        return {k: npz[k] for k in npz.files}


def test_replay_in_chromium(flown, browser_binary):
    log = _log(flown)
    at = 6.0
    k = int(np.searchsorted(log["t"], at, side="right")) - 1
    n = log["p_true"].shape[1]
    proc, url = _start_view(flown, "--at", str(at))
    try:
        with HeadlessBrowser(browser_binary, width=1024, height=640) as browser:
            browser.add_init_script(OBSERVE_SCENES)
            browser.open(url)
            shown = browser.wait_for(f"{links_shown_js(log['p_true'][k])} === {n} && {n}", timeout_s=60)
            assert shown == n
            # nothing stands where no link is: a shifted chain is not found
            assert browser.evaluate(links_shown_js(log["p_true"][k] + [0.0, 0.0, 5.0])) == 0
            text = browser.evaluate("document.body.innerText")
            assert f"t = {log['t'][k]:.2f} s" in text and "1: flying" in text
            browser.evaluate(NEXT_FRAMES)
            _assert_not_blank(browser.screenshot(), 1024, 640)
    finally:
        assert _stop(proc) == 0


def test_the_screenshot_command_waits_for_the_scene_to_be_drawn(flown, browser_binary, tmp_path):
    """``sitl view RUN --screenshot``: the picture once the page has stopped changing (software
    WebGL on a slow machine drew the scene faded in, near white, a second after it arrived)."""
    shot = tmp_path / "shot.png"
    proc = subprocess.run([sys.executable, "-m", "sitl", "view", str(flown), "--at", "6", "--view-port", "0",
                           "--screenshot", str(shot), "--size", "1024x640"], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "SKELETON_CHROMIUM": browser_binary})
    assert proc.returncode == 0, proc.stderr[-3000:]
    _assert_not_blank(shot.read_bytes(), 1024, 640)


def test_run_mcap_matches_the_log(flown):
    log = _log(flown)
    with open(flown / "run.mcap", "rb") as stream:
        summary = make_reader(stream).get_summary()
    counts = {ch.topic: summary.statistics.channel_message_counts[ch.id] for ch in summary.channels.values()}
    n, rows, steps = log["p_true"].shape[1], len(log["t"]), len(log["t_sckf"])
    stride = max(1, math.ceil(1.0 / (float(np.median(np.diff(log["t"]))) * 50.0) - 1e-9))
    want = {"/tf": rows, "/scene": len(range(0, rows, stride)), "/companion/step": steps}
    for i in range(1, n + 1):
        want |= {f"/link{i}/{kind}": rows for kind in ("truth", "ekf", "target", "thrust", "state")}
        want |= {f"/link{i}/{kind}": steps for kind in ("state_in", "corrected", "correction")}
    assert counts == want


def test_view_of_a_folder_without_a_log(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "sitl", "view", str(tmp_path)], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2
    assert "no log.npz" in proc.stderr


def test_live_view_pauses_the_flight(compiled_kernels, browser_binary):
    """A batch flight with a live view: paused from the panel's state, the browser shows the
    links where the paused flight's newest log row has them; resumed, the flight ends."""
    from sitl.runner import BatchRunner
    from sitl.scenarios import load
    from sitl.view.app import ViewServer
    from sitl.view.live import LiveView, batch_rows
    from sitl.view.spec import spec_of_scenario

    _, sc = load(THREE_LINK, duration_s=FLIGHT_S)
    runner = BatchRunner(sc)
    view = ViewServer(spec_of_scenario(sc), "live test", port=0)
    live = LiveView(view, batch_rows(runner))
    runner.tick_hooks.append(live.on_tick)
    reached = threading.Event()
    until = [0.0]
    runner.tick_hooks.append(lambda k, t: reached.set() if t >= until[0] else None)
    live.toggle()  # paused before the first tick: the flight waits at its first firmware tick
    flight = threading.Thread(target=runner.run, args=(sc.duration_s,), daemon=True)
    try:
        flight.start()
        with HeadlessBrowser(browser_binary, width=800, height=600) as browser:
            browser.add_init_script(OBSERVE_SCENES)
            browser.open(view.url)
            for _ in range(2):  # paused and looked at, resumed for a second of flight, paused again
                assert live.held.wait(60)
                p = np.asarray(runner.log.p_true[-1])
                assert browser.wait_for(f"{links_shown_js(p)} === {len(p)}", timeout_s=60)
                assert flight.is_alive()
                until[0], _ = runner.log.t[-1] + 1.0, reached.clear()
                live.toggle()
                assert reached.wait(60)
                live.toggle()
            assert live.updates >= 2
        live.toggle()
        flight.join(timeout=120)
        assert not flight.is_alive()
        assert runner.sim_s == pytest.approx(FLIGHT_S)
    finally:
        if live.paused.is_set():
            live.toggle()
        flight.join(timeout=120)
        view.close()

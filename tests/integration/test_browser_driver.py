"""The headless-Chromium driver (:mod:`sitl.view.browser`) on a page served on loopback: it opens the
page, waits for a JavaScript condition, has a WebGL context on the CPU, takes a screenshot of the
window's size showing what WebGL drew, collects the console, and leaves no process behind; a
binary that is missing or will not start is :class:`BrowserUnavailable`.

Skipped without Chromium, unless SKELETON_REQUIRE_BROWSER=1 (CI): then a missing browser fails."""

from __future__ import annotations

import functools
import subprocess
import tempfile
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest

from sitl.view.browser import BrowserUnavailable, HeadlessBrowser, JavaScriptError

pytestmark = pytest.mark.browser

WIDTH, HEIGHT = 640, 480
#: a WebGL canvas cleared to pure red in the top-left corner, then a status line once it is drawn
PAGE = """<!doctype html>
<html><body style="margin:0;background:#fff">
<canvas id="gl" width="200" height="100" style="display:block"></canvas>
<p id="status">drawing</p>
<script>
  const gl = document.getElementById('gl').getContext('webgl2', {preserveDrawingBuffer: true});
  gl.clearColor(1, 0, 0, 1);
  gl.clear(gl.COLOR_BUFFER_BIT);
  console.log('cleared', 200, 100);
  requestAnimationFrame(() => { document.getElementById('status').textContent = 'drawn'; });
</script>
</body></html>
"""



@pytest.fixture
def served(tmp_path) -> str:
    """The URL of PAGE served by http.server on an ephemeral loopback port."""
    (tmp_path / "index.html").write_text(PAGE)

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(tmp_path)))
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/index.html"
    server.shutdown()
    server.server_close()


def _running(profile: str) -> str:
    """``pgrep -af`` lines of processes still running with ``profile`` as their profile dir."""
    return subprocess.run(["pgrep", "-af", f"user-data-dir={profile}"], capture_output=True, text=True).stdout


def test_opens_waits_evaluates_and_screenshots_a_webgl_page(browser_binary, served):
    with HeadlessBrowser(browser_binary, width=WIDTH, height=HEIGHT, timeout_s=20) as browser:
        profile = browser._profile
        browser.open(served)
        assert browser.wait_for("document.getElementById('status').textContent === 'drawn'", timeout_s=10)
        assert browser.evaluate("!!document.createElement('canvas').getContext('webgl2')"), browser.console()
        assert browser.evaluate("Promise.resolve([innerWidth, innerHeight])") == [WIDTH, HEIGHT]
        with pytest.raises(JavaScriptError, match="ReferenceError"):
            browser.evaluate("no_such_function()")
        with pytest.raises(TimeoutError, match="never_true"):
            browser.wait_for("window.never_true", timeout_s=0.3)
        png = browser.screenshot()
        assert any("cleared 200 100" in line for line in browser.console()), browser.console()
        assert _running(profile), "no Chromium process found by its profile dir while it runs"

    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and image is not None
    assert image.shape == (HEIGHT, WIDTH, 3)
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 1, "the screenshot is one colour"
    assert tuple(image[50, 100]) == (0, 0, 255), f"not WebGL's red inside the canvas: {image[50, 100]} (BGR)"
    assert tuple(image[300, 600]) == (255, 255, 255), "not the page's white outside the canvas"

    assert not _running(profile), f"Chromium still running after close():\n{_running(profile)}"
    assert not Path(profile).exists()
    with pytest.raises(RuntimeError, match="closed"):
        browser.evaluate("1")
    browser.close()  # twice is fine


def test_a_settled_screenshot_waits_until_the_page_stops_changing(browser_binary, served):
    """A page that fades in (as the 3D view does, slowly in software WebGL): a screenshot taken at
    once shows it half drawn; the settled one shows it drawn."""
    fade = """document.body.style.background = 'rgb(255,255,255)';
        window.fadeStep = 0;
        window.fadeTimer = setInterval(() => {
          const v = Math.max(0, 255 - 40 * ++window.fadeStep);
          document.body.style.background = `rgb(${v},${v},${v})`;
          if (v === 0) clearInterval(window.fadeTimer);
        }, 250);"""
    with HeadlessBrowser(browser_binary, width=WIDTH, height=HEIGHT, timeout_s=20) as browser:
        browser.open(served)
        browser.evaluate(fade)
        early = cv2.imdecode(np.frombuffer(browser.screenshot(), np.uint8), cv2.IMREAD_COLOR)
        settled = cv2.imdecode(np.frombuffer(browser.settled_screenshot(interval_s=0.5), np.uint8),
                               cv2.IMREAD_COLOR)
    assert early[300, 600].min() > 0  # (not black yet: the fade takes 7 steps of 0.25 s)
    assert tuple(settled[300, 600]) == (0, 0, 0)


def test_a_binary_that_is_missing_or_will_not_start_is_unavailable(tmp_path, monkeypatch):
    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))  # where the profile and stderr file go
    with pytest.raises(BrowserUnavailable, match="apt-get install chromium"):
        HeadlessBrowser(str(tmp_path / "no-such-chromium"), timeout_s=5)
    with pytest.raises(BrowserUnavailable, match="exited with code 1"):
        HeadlessBrowser("/bin/false", timeout_s=5)
    assert not list(temp.iterdir()), "a failed start left its profile or stderr file behind"

"""Headless Chromium driven over the Chrome DevTools Protocol (CDP), for tests and documentation.

:class:`HeadlessBrowser` starts Debian's Chromium headless with a fresh temporary profile and
``--remote-debugging-port=0``, reads the port Chromium picked from ``<profile>/DevToolsActivePort``,
and talks to one page target over its websocket (``websockets``' sync client): open a URL and wait
for its load event, evaluate JavaScript, poll until a JavaScript condition holds, take a PNG
screenshot, and collect the page's console messages and uncaught exceptions. Every wait is bounded;
:meth:`HeadlessBrowser.close` kills Chromium's whole process group and removes the profile.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from contextlib import suppress
from pathlib import Path
from typing import Any

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

__all__ = ["CHROMIUM_FLAGS", "BrowserUnavailable", "HeadlessBrowser", "JavaScriptError", "find_chromium",
           "require_browser"]

#: command-line flags Chromium is started with (plus window size, profile dir and debugging port)
CHROMIUM_FLAGS: tuple[str, ...] = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-default-apps", "--mute-audio", "--hide-scrollbars",
    # WebGL (three.js) on the CPU: ANGLE's SwiftShader asked for, not left to Chromium's deprecated automatic fallback
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
)
#: executables looked up on PATH, in order, when $SKELETON_CHROMIUM is not set
_NAMES = ("chromium", "chromium-browser", "google-chrome")
_INSTALL = "install Chromium (Debian: sudo apt-get install chromium) or set SKELETON_CHROMIUM to its path"
#: urllib without proxies from the environment: the DevTools endpoint is on loopback
_HTTP = urllib.request.build_opener(urllib.request.ProxyHandler({}))


class BrowserUnavailable(RuntimeError):
    """No Chromium binary, or it would not start (the message says how to install it)."""


class JavaScriptError(RuntimeError):
    """An expression given to :meth:`HeadlessBrowser.evaluate` threw; the message is the JS exception."""


def find_chromium() -> str | None:
    """$SKELETON_CHROMIUM when set, else the first of chromium, chromium-browser, google-chrome on PATH."""
    chosen = os.environ.get("SKELETON_CHROMIUM")
    if chosen:
        return chosen
    return next((path for path in map(shutil.which, _NAMES) if path), None)


def require_browser() -> str:
    """The Chromium binary :func:`find_chromium` finds, if it is an executable; else :class:`BrowserUnavailable`."""
    binary = find_chromium()
    if binary is None:
        raise BrowserUnavailable(f"no Chromium found (looked for {', '.join(_NAMES)} on PATH): {_INSTALL}")
    if shutil.which(binary) is None:
        raise BrowserUnavailable(f"SKELETON_CHROMIUM={binary} is not an executable: {_INSTALL}")
    return binary


class HeadlessBrowser:
    """One headless Chromium with one page of ``width`` x ``height`` CSS pixels (device scale 1);
    ``timeout_s`` bounds the start and every DevTools call. A context manager (or call :meth:`close`)."""

    def __init__(self, binary: str | None = None, width: int = 1280, height: int = 800, timeout_s: float = 30.0):
        self.width, self.height, self.timeout_s = width, height, timeout_s
        self._binary = binary or require_browser()
        self._ids = itertools.count(1)
        self._console: list[str] = []
        self._loaded = self._crashed = False
        self._ws = None
        self._proc: subprocess.Popen | None = None
        self._profile = tempfile.mkdtemp(prefix="skeleton-chromium-")
        self._stderr = open(f"{self._profile}.stderr", "w+b")  # a file: it never fills up
        try:
            self._start()
        except BaseException:
            self.close()
            raise

    def _start(self) -> None:
        args = [self._binary, *CHROMIUM_FLAGS, f"--window-size={self.width},{self.height}",
                f"--user-data-dir={self._profile}", "--remote-debugging-port=0", "about:blank"]
        try:
            self._proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                          stderr=self._stderr, start_new_session=True, preexec_fn=_die_with_parent)
        except OSError as exc:
            raise BrowserUnavailable(f"cannot run {self._binary!r} ({exc}): {_INSTALL}") from exc
        port_file = Path(self._profile, "DevToolsActivePort")
        deadline = time.monotonic() + self.timeout_s
        while True:
            lines = port_file.read_text().split() if port_file.exists() else []
            if len(lines) >= 2:
                break
            if self._proc.poll() is not None:
                raise BrowserUnavailable(f"{self._binary} exited with code {self._proc.returncode} before "
                                         f"it listened: {_INSTALL}{self._stderr_tail()}")
            if time.monotonic() > deadline:
                raise BrowserUnavailable(f"{self._binary} did not open its DevTools port within "
                                         f"{self.timeout_s:g} s{self._stderr_tail()}")
            time.sleep(0.05)
        base = f"http://127.0.0.1:{int(lines[0])}"
        with _HTTP.open(f"{base}/json/list", timeout=self.timeout_s) as reply:
            pages = [t for t in json.load(reply) if t.get("type") == "page"]
        if not pages:
            request = urllib.request.Request(f"{base}/json/new?about:blank", method="PUT")
            with _HTTP.open(request, timeout=self.timeout_s) as reply:
                pages = [json.load(reply)]
        # no message size limit (screenshots are megabytes), no proxy from the environment
        self._ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=self.timeout_s, proxy=None)
        for domain in ("Page", "Runtime", "Log", "Inspector"):
            self._call(f"{domain}.enable")
        self._call("Emulation.setDeviceMetricsOverride",
                   {"width": self.width, "height": self.height, "deviceScaleFactor": 1, "mobile": False})

    def __enter__(self) -> HeadlessBrowser:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _stderr_tail(self, chars: int = 2000) -> str:
        """The end of Chromium's stderr (its D-Bus complaints left out), for error messages."""
        try:
            self._stderr.flush()
            text = Path(self._stderr.name).read_text(errors="replace")
        except (OSError, ValueError):
            return ""
        text = "\n".join(line for line in text.splitlines() if "dbus" not in line.lower())[-chars:]
        return f"\nChromium's stderr:\n{text}" if text.strip() else ""

    def _call(self, method: str, params: dict | None = None, timeout_s: float | None = None) -> dict:
        """Send one CDP command and read messages (buffering events) until its response arrives."""
        if self._ws is None or self._crashed:
            raise RuntimeError("the page's renderer crashed" if self._crashed else "the browser is closed")
        message_id = next(self._ids)
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        try:
            self._ws.send(json.dumps({"id": message_id, "method": method, "params": params or {}}))
            while True:
                message = self._receive(deadline, method)
                if message.get("id") == message_id:
                    if "error" in message:
                        raise RuntimeError(f"{method}: {message['error'].get('message', message['error'])}")
                    return message.get("result", {})
        except ConnectionClosed as exc:
            raise RuntimeError(f"the browser closed its DevTools connection during {method} "
                               f"(crashed or closed?){self._stderr_tail()}") from exc

    def _receive(self, deadline: float, waiting_for: str) -> dict:
        """The next message before ``deadline``; events among them are recorded on the way."""
        remaining = deadline - time.monotonic()
        try:
            message = json.loads(self._ws.recv(timeout=max(remaining, 0.0)))
        except TimeoutError:
            raise TimeoutError(f"no answer from the browser to {waiting_for}{self._stderr_tail()}") from None
        self._event(message)
        if self._crashed:
            raise RuntimeError(f"the page's renderer crashed (waiting for {waiting_for}){self._stderr_tail()}")
        return message

    def _event(self, message: dict) -> None:
        method, params = message.get("method"), message.get("params", {})
        if method == "Page.loadEventFired":
            self._loaded = True
        elif method == "Inspector.targetCrashed":
            self._crashed = True
            self._console.append("the page's renderer crashed")
        elif method == "Runtime.consoleAPICalled":
            words = [str(a.get("value", a.get("description", a.get("type", "")))) for a in params.get("args", [])]
            self._console.append(f"console.{params.get('type', 'log')}: {' '.join(words)}")
        elif method == "Runtime.exceptionThrown":
            self._console.append(f"uncaught: {_exception_text(params.get('exceptionDetails', {}))}")
        elif method == "Log.entryAdded":  # failed loads, violations: what the console shows besides console.*
            e = params.get("entry", {})
            self._console.append(f"{e.get('source')}.{e.get('level')}: {e.get('text', '')} {e.get('url', '')}".rstrip())

    def add_init_script(self, source: str) -> None:
        """Run the JavaScript ``source`` in every page opened from now on, before the page's own scripts."""
        self._call("Page.addScriptToEvaluateOnNewDocument", {"source": source})

    def open(self, url: str) -> None:
        """Navigate the page to ``url`` and wait (``timeout_s``) for its load event."""
        self._loaded = False
        deadline = time.monotonic() + self.timeout_s
        result = self._call("Page.navigate", {"url": url})
        if result.get("errorText"):
            raise RuntimeError(f"cannot open {url}: {result['errorText']}")
        while not self._loaded:
            self._receive(deadline, f"the load event of {url}")

    def evaluate(self, expression: str, timeout_s: float | None = None) -> Any:
        """The value of the JavaScript ``expression`` in the page, promises awaited, as JSON carries it
        (``undefined`` is None); :class:`JavaScriptError` with the exception's text when it throws."""
        result = self._call("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                 "awaitPromise": True}, timeout_s)
        if "exceptionDetails" in result:
            raise JavaScriptError(f"{expression!r} threw: {_exception_text(result['exceptionDetails'])}")
        value = result.get("result", {})
        return value.get("value", value.get("unserializableValue"))

    def wait_for(self, expression: str, timeout_s: float = 30.0, interval_s: float = 0.1) -> Any:
        """Evaluate ``expression`` every ``interval_s`` until its value is truthy, and return that value.
        While it throws it counts as not yet; :class:`TimeoutError` naming it after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        last = None
        while True:
            remaining = deadline - time.monotonic()
            try:
                value = self.evaluate(expression, timeout_s=max(remaining, 0.5))
                if value:
                    return value
                last = f"last value {value!r}"
            except JavaScriptError as exc:
                last = str(exc)
            if time.monotonic() + interval_s > deadline:
                recent = "\n".join(self._console[-10:])
                raise TimeoutError(f"{expression!r} not true within {timeout_s:g} s ({last})"
                                   + (f"\nconsole:\n{recent}" if recent else ""))
            time.sleep(interval_s)

    def screenshot(self, image_format: str = "png", quality: int = 85) -> bytes:
        """The page's viewport (``width`` x ``height`` pixels) as ``png`` or ``jpeg`` (``quality`` 1-100) bytes."""
        if image_format not in ("png", "jpeg"):
            raise ValueError(f"image format {image_format!r}: png or jpeg")
        params = {"format": image_format} | ({"quality": int(quality)} if image_format == "jpeg" else {})
        return base64.b64decode(self._call("Page.captureScreenshot", params)["data"])

    def settled_screenshot(self, image_format: str = "png", quality: int = 85, interval_s: float = 0.5,
                           timeout_s: float = 20.0) -> bytes:
        """:meth:`screenshot` once the page has stopped changing: two captures ``interval_s`` apart
        alike, pixel for pixel (a scene fading in, software WebGL on a slow machine still drawing),
        or the last one after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        last = self.screenshot()
        while time.monotonic() < deadline:
            time.sleep(interval_s)
            now = self.screenshot()
            if now == last:
                break
            last = now
        return last if image_format == "png" else self.screenshot(image_format, quality)

    def console(self) -> list[str]:
        """The console messages, uncaught exceptions and log entries (failed loads) seen so far."""
        return list(self._console)

    def close(self) -> None:
        """Close the connection, kill Chromium's process group, remove the profile; safe to call twice."""
        if self._ws is not None:
            with suppress(Exception):
                self._ws.close()
            self._ws = None
        if self._proc is not None:
            _kill_group(self._proc)
            self._proc = None
        if not self._stderr.closed:
            self._stderr.close()
            Path(self._stderr.name).unlink(missing_ok=True)
        shutil.rmtree(self._profile, ignore_errors=True)


def _die_with_parent() -> None:
    """In the child before it runs Chromium (Linux): killed when the thread that started it ends,
    so that a test or command killed without cleaning up leaves no browser behind."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def _exception_text(details: dict) -> str:
    """A CDP ``ExceptionDetails`` as one line: the exception's description, else the text and place."""
    described = details.get("exception", {}).get("description")
    return described or f"{details.get('text', 'exception')} at line {details.get('lineNumber', '?')}"


def _kill_group(proc: subprocess.Popen, wait_s: float = 5.0) -> None:
    """SIGKILL the process group ``proc`` leads (Chromium's renderer, GPU and utility processes with
    it) and wait, at most ``wait_s``, until none of them runs. Zombies count as gone: they are dead,
    and reaping the orphans is left to PID 1, which may take its time."""
    with suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    deadline = time.monotonic() + wait_s
    try:
        proc.wait(timeout=wait_s)
    except subprocess.TimeoutExpired:
        return
    while _group_running(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.02)


def _group_running(pgid: int) -> bool:
    """Whether a process of group ``pgid`` is still running (not a zombie), from /proc."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with suppress(OSError, IndexError):
            state, _parent, group = stat.read_text().rsplit(")", 1)[1].split()[:3]
            if int(group) == pgid and state not in ("Z", "X"):
                return True
    return False

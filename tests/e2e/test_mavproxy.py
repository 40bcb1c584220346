"""Stock MAVProxy (the test extra's) against a signed three-link fleet, as the fleet manual tells a
user to connect: the launcher's printed ``signing key`` line typed at MAVProxy's prompt, with the
dialect's environment from ``python -m companion dialect``.

With the key: every vehicle's parameter list completes, an integer parameter is set and read back,
a vehicle arms and disarms on the ground, and a GPS failure is injected with MAVProxy's `long`
command once SYS_FAILURE_EN allows it. Without it: the telemetry is readable (it is signed, not
encrypted) but nothing is answered. Neither session prints a traceback."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from link_firmware_sim.vehicle.params import PARAMS

from ..paths import ROOT


pytest.importorskip("MAVProxy")

SIGNED = ROOT / "configs" / "sitl" / "chain" / "three_link_signed.toml"
MAVPROXY = Path(sys.executable).with_name("mavproxy.py")


class _Session:
    """A process driven at its prompt: lines in on stdin, its output read line by line as it comes."""

    def __init__(self, argv: list[str], env: dict, cwd: Path):
        # Ctrl-C acts as in a terminal even where this process was started with SIGINT ignored (a
        # background job of a shell without job control), which its children would inherit
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, env=env, cwd=cwd, start_new_session=True,
                                     preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        self.lines: list[str] = []
        self._new = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            with self._new:
                self.lines.append(line.rstrip("\n"))
                self._new.notify_all()

    def send(self, line: str) -> int:
        """Type ``line``; returns the output's length, from where :meth:`expect` looks for the answer."""
        with self._new:
            mark = len(self.lines)
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        return mark

    def expect(self, pattern: str, timeout_s: float, since: int = 0) -> re.Match | None:
        """The first output line from ``since`` on matching ``pattern`` within ``timeout_s``, or ``None``."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout_s
        seen = since
        with self._new:
            while True:
                for line in self.lines[seen:]:
                    found = regex.search(line)
                    if found:
                        return found
                seen = len(self.lines)
                left = deadline - time.monotonic()
                if left <= 0 or self.proc.poll() is not None:
                    return None
                self._new.wait(min(left, 0.5))

    def output(self) -> str:
        with self._new:
            return "\n".join(self.lines)

    def close(self, sig: int = signal.SIGTERM, timeout_s: float = 20.0, eof: bool = False) -> str:
        """Stop the process: with ``eof``, first the end of its input (Ctrl-D at MAVProxy's prompt:
        it unloads its modules and exits; it does not stop on SIGTERM. Its own log writer thread
        may raise as it exits, so a session's output is checked before it is closed), then ``sig``
        (it alone: it stops what it started), then its whole process group
        with SIGKILL if it is not gone after ``timeout_s`` (first SIGABRT: a Python process started
        with PYTHONFAULTHANDLER=1 writes where each of its threads was); its output."""
        if eof and self.proc.poll() is None:
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=timeout_s)
            except (OSError, subprocess.TimeoutExpired):
                pass
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.send_signal(signal.SIGABRT)
                try:
                    self.proc.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    pass
                try:
                    os.killpg(self.proc.pid, signal.SIGKILL)  # (what it started too)
                except ProcessLookupError:
                    pass
                self.proc.wait()
        self._reader.join(timeout=5)
        return self.output()


def _dialect_environment() -> dict:
    """The environment ``eval "$(python -m companion dialect)"`` sets, over this one."""
    env = dict(os.environ)
    printed = subprocess.run([sys.executable, "-m", "companion", "dialect"], capture_output=True, text=True, check=True,
                             cwd=ROOT).stdout
    for line in printed.splitlines():
        if line.startswith("export "):
            key, value = line[len("export "):].split("=", 1)
            env[key] = value
    return env


def _mavproxy(port: int, state_dir: Path, env: dict) -> _Session:
    state_dir.mkdir(parents=True, exist_ok=True)
    return _Session([sys.executable, str(MAVPROXY), f"--master=udpin:127.0.0.1:{port}", "--dialect=aerial_skeleton",
                     f"--state-basedir={state_dir}"], env, state_dir)


def test_mavproxy_on_a_signed_fleet_as_the_manual_says(tmp_path, fleet_ports):
    assert MAVPROXY.exists(), f"{MAVPROXY}: MAVProxy's script (pip install -e '.[test]')"
    gcs_port = fleet_ports.gcs_port
    out = tmp_path / "run"
    fleet = _Session([sys.executable, "-m", "sitl", "launch", "--config", str(SIGNED), "--no-companion", "--speed", "1",
                      "--duration", "600", "--quiet", "--no-plots", *fleet_ports.cli_args, "--out",
                      str(out)], dict(os.environ, PYTHONFAULTHANDLER="1"), ROOT)
    sessions: list[_Session] = []
    try:
        typed = fleet.expect(r"^\s*(signing key \S+)\s*$", 120)
        assert typed, fleet.output()[-3000:]
        assert fleet.expect(r"lockstep started", 60), fleet.output()[-3000:]
        env = _dialect_environment()

        # Without the key: the signed telemetry is readable, nothing is answered.
        stranger = _mavproxy(gcs_port, tmp_path / "mavproxy-nokey", env)
        sessions.append(stranger)
        assert stranger.expect(r"Detected vehicle [123]:1", 60), stranger.output()[-2000:]
        mark = stranger.send("param fetch")
        assert stranger.expect(r"Requested parameter list", 10, mark)
        # (a keyed session's answers come within a second; 5 s of silence is no answer)
        assert stranger.expect(r"Received \d+ parameters", 5, mark) is None, stranger.output()[-2000:]
        mark = stranger.send("arm throttle")
        assert stranger.expect(r"COMMAND_ACK|ARMED", 5, mark) is None, stranger.output()[-2000:]
        assert "Traceback" not in stranger.output()
        stranger.close(eof=True)

        # With the key, typed as the launcher printed it.
        gcs = _mavproxy(gcs_port, tmp_path / "mavproxy", env)
        sessions.append(gcs)
        assert gcs.expect(r"Detected vehicle [123]:1", 60), gcs.output()[-2000:]
        mark = gcs.send(typed.group(1))
        assert gcs.expect(r"Setup signing key", 10, mark), gcs.output()[-2000:]
        for vehicle in (1, 2, 3):
            mark = gcs.send(f"vehicle {vehicle}")
            assert gcs.expect(rf"Set vehicle {vehicle}\b", 10, mark), gcs.output()[-2000:]
            mark = gcs.send("param fetch")
            got = gcs.expect(r"Received (\d+) parameters", 30, mark)
            assert got and int(got.group(1)) == len(PARAMS), gcs.output()[-2000:]
        # An integer parameter on vehicle 3, set and read back (the vehicle echoes and keeps it)
        for value in (0, 1):
            mark = gcs.send(f"param set SKL_SAT_SCALE {value}")
            mark = gcs.send("param fetch SKL_SAT_SCALE")
            assert gcs.expect(r"Requested parameter SKL_SAT_SCALE", 10, mark)
            deadline = time.monotonic() + 15
            while time.monotonic() < deadline:
                mark = gcs.send("param show SKL_SAT_SCALE")
                shown = gcs.expect(r"SKL_SAT_SCALE\s+(-?\d+(?:\.\d+)?)", 5, mark)  # (a prompt may follow)
                if shown and float(shown.group(1)) == value:
                    break
            else:
                pytest.fail(f"SKL_SAT_SCALE never read back as {value}:\n{gcs.output()[-2000:]}")
            stored = json.loads((out / "link3" / "link3_params.json").read_text())
            assert stored["SKL_SAT_SCALE"] == value
        mark = gcs.send("arm throttle")
        assert gcs.expect(r"COMPONENT_ARM_DISARM: ACCEPTED", 15, mark), gcs.output()[-2000:]
        assert gcs.expect(r"(?:^|> )ARMED", 15, mark), gcs.output()[-2000:]
        mark = gcs.send("disarm")
        assert gcs.expect(r"COMPONENT_ARM_DISARM: ACCEPTED", 15, mark), gcs.output()[-2000:]
        assert gcs.expect(r"DISARMED", 15, mark), gcs.output()[-2000:]
        # Failure injection the PX4 way, with MAVProxy's generic `long` command: denied until
        # SYS_FAILURE_EN is set, then GPS off accepted (and announced), then cleared
        mark = gcs.send("long INJECT_FAILURE 4 1 0")
        assert gcs.expect(r"COMMAND_ACK: INJECT_FAILURE: DENIED", 10, mark), gcs.output()[-2000:]
        gcs.send("param set SYS_FAILURE_EN 1")  # (MAVProxy sends it from its idle loop: wait for it)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            mark = gcs.send("param show SYS_FAILURE_EN")
            shown = gcs.expect(r"SYS_FAILURE_EN\s+(-?\d+(?:\.\d+)?)", 5, mark)
            if shown and float(shown.group(1)) == 1:
                break
        else:
            pytest.fail(f"SYS_FAILURE_EN never read back as 1:\n{gcs.output()[-2000:]}")
        mark = gcs.send("long INJECT_FAILURE 4 1 0")
        assert gcs.expect(r"COMMAND_ACK: INJECT_FAILURE: ACCEPTED", 10, mark), gcs.output()[-2000:]
        assert gcs.expect(r"Failure injection: gps off", 10, mark), gcs.output()[-2000:]
        mark = gcs.send("long INJECT_FAILURE 4 0 0")
        assert gcs.expect(r"COMMAND_ACK: INJECT_FAILURE: ACCEPTED", 10, mark), gcs.output()[-2000:]
        mark = gcs.send("status SKELETON_LINK_STATE")  # the dialect's own message, decoded
        assert gcs.expect(r"SKELETON_LINK_STATE \{time_usec", 10, mark), gcs.output()[-2000:]
        text = gcs.output()
        assert "Traceback" not in text and "fence breach" not in text, text[-3000:]
        gcs.close(eof=True)
    finally:
        for session in sessions:
            session.close(eof=True)
        fleet.close(signal.SIGINT, timeout_s=120.0)  # (Ctrl-C: the launcher stops the fleet and writes its logs)
    assert fleet.proc.returncode == 130, fleet.output()[-3000:]
    # the vehicles refused the unkeyed session's commands, and say so
    ports = json.loads((out / "link1" / "link1_ports.json").read_text())
    gcs_side = next(v for k, v in ports.items() if k.startswith(f"udpout://127.0.0.1:{gcs_port}"))
    assert gcs_side["rejected_unsigned"] > 0 and gcs_side["signed"] > 0, gcs_side

"""Fault requests at run time: the fleet's fault socket and its client (``python -m sitl fault``).

A running fleet listens on a UNIX datagram socket in its run folder, ``RUN_DIR/faults.sock``
(mode 0600: only its user can ask). A request is one datagram of UTF-8 JSON, an object with
``kind``, ``target`` and optionally ``restart_after_s`` and ``at_s``
(:meth:`~sitl.fleet.faults.HarnessFault.from_request`); the reply, to the sender's address, is
a JSON object with ``accepted`` and either the fault's timeline or an ``error``. The fleet reads
the socket between firmware ticks, at most every :data:`POLL_S` of wall time, at most
:data:`BATCH` datagrams at a time, so no request can stall the lockstep. A datagram that is not
such an object (too long, not UTF-8, not JSON) gets an error reply and is counted (``malformed``),
as is a refused request (``refused``).
"""

from __future__ import annotations

import json
import os
import socket
import time
import uuid
from pathlib import Path

__all__ = ["POLL_S", "MAX_BYTES", "FaultSocket", "send_request"]

#: wall time between two reads of the socket [s]
POLL_S = 0.02
#: datagrams read at a time
BATCH = 8
#: the longest request [bytes]
MAX_BYTES = 4096


class FaultSocket:
    """The fleet's end (see the module docstring), bound at ``path``."""

    def __init__(self, path: Path):
        self.path = Path(path)
        if self.path.exists() or self.path.is_symlink():
            self.path.unlink()
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        old = os.umask(0o177)  # created 0600
        try:
            self.sock.bind(str(self.path))
        finally:
            os.umask(old)
        self.sock.setblocking(False)
        self.counts = {"accepted": 0, "refused": 0, "malformed": 0}
        self._next_s = 0.0

    def serve(self, handle, t_s: float) -> None:
        """Read the requests waiting (at most every :data:`POLL_S`), hand each parsed one to
        ``handle(request, t_s)``, which returns the reply, and send the replies."""
        now = time.monotonic()
        if now < self._next_s:
            return
        self._next_s = now + POLL_S
        for _ in range(BATCH):
            try:
                data, addr = self.sock.recvfrom(MAX_BYTES + 1)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            try:
                if len(data) > MAX_BYTES:
                    raise ValueError(f"a request is at most {MAX_BYTES} bytes")
                request = json.loads(data.decode("utf-8"))
            except (UnicodeDecodeError, ValueError) as exc:
                self.counts["malformed"] += 1
                reply = {"accepted": False, "error": f"not a JSON request: {exc}"[:300]}
            else:
                reply = handle(request, t_s)
                self.counts["accepted" if reply.get("accepted") else "refused"] += 1
            if addr:
                try:
                    self.sock.sendto(json.dumps(reply).encode(), addr)
                except OSError:
                    pass  # the asker is gone: the fault is played all the same

    def close(self) -> None:
        self.sock.close()
        try:
            self.path.unlink()
        except OSError:
            pass


def send_request(path: Path, request: dict, timeout_s: float = 10.0) -> dict:
    """Send ``request`` to the fault socket at ``path`` and return the fleet's reply.
    ``ConnectionError`` when no fleet listens there, ``TimeoutError`` without a reply."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind(f"\0skeleton-fault-{os.getpid()}-{uuid.uuid4().hex[:12]}")  # (abstract: nothing to remove)
        try:
            sock.sendto(json.dumps(request).encode(), str(path))
        except (FileNotFoundError, ConnectionRefusedError) as exc:
            raise ConnectionError(f"no running fleet listens on {path} ({exc.strerror})") from None
        sock.settimeout(timeout_s)
        try:
            data = sock.recv(65536)
        except socket.timeout:
            raise TimeoutError(f"no reply from {path} within {timeout_s:g} s") from None
        return json.loads(data.decode("utf-8"))
    finally:
        sock.close()

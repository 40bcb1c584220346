"""A serial-device transport for MAVLink ports (a Pixhawk's USB or TELEM2 port by id).

It survives the device: one that is missing, fails to open or errors (a USB autopilot
rebooting) leaves the transport disconnected, and it tries to reopen the device every
``retry_s`` seconds on the clock it is given.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import time
from collections.abc import Callable

from .transport import Transport

__all__ = ["SerialTransport"]

log = logging.getLogger(__name__)


class SerialTransport(Transport):
    """A serial device, e.g. a Pixhawk's USB or TELEM2 port by id.

    A missing device, one that fails to open, or one that errors (a USB autopilot rebooting) is
    not fatal: the port logs what and where, stays disconnected (reads return nothing, writes
    are dropped) and tries to reopen the device every ``retry_s`` seconds of ``clock`` (monotonic
    seconds).
    """

    def __init__(self, device: str, baud: int, retry_s: float = 1.0, clock: Callable[[], float] = time.monotonic):
        import serial  # pyserial: only hardware links need it

        self._serial = serial
        self.device = device
        self.baud = baud
        self.retry_s = retry_s
        self.clock = clock
        self.port = None
        self._next_try = 0.0
        self._reported = False
        self._open()

    def _open(self) -> None:
        now = self.clock()
        if now < self._next_try:
            return
        self._next_try = now + self.retry_s
        try:
            if not os.path.exists(self.device):
                raise OSError(errno.ENOENT, "no such device")
            self.port = self._serial.Serial(self.device, baudrate=self.baud, timeout=0, write_timeout=0.1)
        except (self._serial.SerialException, OSError) as exc:
            if not self._reported:
                log.warning("serial %s (%d baud): cannot open: %s; retrying every %.0f s", self.device, self.baud,
                            getattr(exc, "strerror", None) or exc, self.retry_s)
                self._reported = True
            return
        log.info("serial %s open at %d baud", self.device, self.baud)
        self._reported = False

    def _lost(self, exc: Exception) -> None:
        log.warning("serial %s: %s; reopening", self.device, exc)
        try:
            self.port.close()
        except (self._serial.SerialException, OSError):
            pass
        self.port = None
        self._next_try = self.clock() + self.retry_s

    def fileno(self) -> int:
        return self.port.fileno() if self.port is not None else -1

    def recv_all(self) -> bytes:
        if self.port is None:
            self._open()
            return b""
        try:
            n = self.port.in_waiting
            data = self.port.read(n) if n else b""
        except (self._serial.SerialException, OSError) as exc:
            self._lost(exc)
            return b""
        if not n and not data and self._hung_up():
            self._lost(OSError(errno.EIO, "device hung up"))
        return data

    def _hung_up(self) -> bool:
        """select() said readable but nothing is waiting: the device went away."""
        ready, _, _ = select.select([self.port.fileno()], [], [], 0)
        return bool(ready)

    def send(self, data: bytes) -> None:
        if self.port is None:
            return
        try:
            self.port.write(data)
        except self._serial.SerialTimeoutException:
            pass  # a congested link: drop, like UDP
        except (self._serial.SerialException, OSError) as exc:
            self._lost(exc)

    def close(self) -> None:
        if self.port is not None:
            self.port.close()
            self.port = None

    @property
    def connected(self) -> bool:
        return self.port is not None

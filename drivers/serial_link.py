"""A serial connection with timeouts on every read, typed errors and reconnects.

Opens its port with pyserial's ``serial_for_url``, so the same code drives
``/dev/ttyUSB0``, a pseudo-terminal and ``sim://NAME``. Every wait goes through
the injected clock.
"""

from __future__ import annotations

import contextlib

import serial
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.drivers.errors import DeviceGone, DeviceTimeout


class SerialLink:
    def __init__(
        self,
        url: str,
        *,
        device: str,
        baudrate: int = 115200,
        bytesize: int = 8,
        parity: str = "N",
        stopbits: float = 1,
        timeout_s: float = 1.0,
        clock: Clock = SYSTEM_CLOCK,
    ) -> None:
        self.url = url
        self.device = device
        self.settings = {
            "baudrate": baudrate,
            "bytesize": bytesize,
            "parity": parity,
            "stopbits": stopbits,
        }
        self.timeout_s = timeout_s
        self.clock = clock
        self._port: serial.SerialBase | None = None
        self._buf = bytearray()

    # -- connection ------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def open(self) -> None:
        self.close()
        try:
            # A device path is opened exclusively (flock on POSIX): a second program on the same
            # port fails at once with "port busy" instead of both reading each other's replies.
            extra = {} if "://" in self.url else {"exclusive": True}
            self._port = serial.serial_for_url(
                self.url, timeout=self.timeout_s, write_timeout=self.timeout_s, **self.settings, **extra
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            self._port = None
            raise DeviceGone(f"cannot open {self.url}: {exc}", device=self.device) from exc
        self._buf.clear()

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()

    def reconnect(self, *, attempts: int = 10, interval_s: float = 0.5) -> None:
        """Reopen the port, waiting for it to come back (a replugged adapter)."""
        last: Exception | None = None
        for _ in range(attempts):
            try:
                self.open()
                return
            except DeviceGone as exc:
                last = exc
                self.clock.sleep(interval_s)
        raise DeviceGone(f"{self.url} did not come back: {last}", device=self.device)

    def _require(self, command: str | None) -> serial.SerialBase:
        if self._port is None:
            raise DeviceGone("port is not open", device=self.device, command=command)
        return self._port

    # -- I/O -------------------------------------------------------------------------
    def write(self, data: bytes, *, command: str | None = None) -> None:
        port = self._require(command)
        try:
            port.write(data)
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise DeviceGone(f"write failed: {exc}", device=self.device, command=command) from exc

    def _fill(self, remaining: float, command: str | None) -> None:
        port = self._require(command)
        try:
            port.timeout = max(remaining, 0.0)
            waiting = port.in_waiting
            chunk = port.read(max(1, waiting))
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise DeviceGone(f"read failed: {exc}", device=self.device, command=command) from exc
        self._buf += chunk

    def read_until(
        self, terminator: bytes = b"\n", *, timeout: float | None = None, command: str | None = None
    ) -> bytes:
        """Bytes up to and including ``terminator``; DeviceTimeout if it does not come."""
        timeout = self.timeout_s if timeout is None else timeout
        deadline = self.clock.monotonic() + timeout
        while True:
            idx = self._buf.find(terminator)
            if idx >= 0:
                end = idx + len(terminator)
                out = bytes(self._buf[:end])
                del self._buf[:end]
                return out
            remaining = deadline - self.clock.monotonic()
            if remaining <= 0:
                partial = bytes(self._buf)
                raise DeviceTimeout(
                    f"no {terminator!r} within {timeout:.3g} s (got {partial!r})",
                    device=self.device,
                    command=command,
                )
            self._fill(remaining, command)

    def read_exact(
        self, n: int, *, timeout: float | None = None, command: str | None = None
    ) -> bytes:
        timeout = self.timeout_s if timeout is None else timeout
        deadline = self.clock.monotonic() + timeout
        while len(self._buf) < n:
            remaining = deadline - self.clock.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(
                    f"{len(self._buf)} of {n} bytes within {timeout:.3g} s",
                    device=self.device,
                    command=command,
                )
            self._fill(remaining, command)
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def read_available(self, *, command: str | None = None) -> bytes:
        """Whatever has arrived, without waiting."""
        port = self._require(command)
        try:
            n = port.in_waiting
            if n:
                port.timeout = 0
                self._buf += port.read(n)
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise DeviceGone(f"read failed: {exc}", device=self.device, command=command) from exc
        out = bytes(self._buf)
        self._buf.clear()
        return out

    def drain_input(self) -> None:
        self._buf.clear()
        if self._port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                self._port.reset_input_buffer()

    def __enter__(self) -> SerialLink:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

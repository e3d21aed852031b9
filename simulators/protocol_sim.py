"""pyserial URL handler for ``sim://NAME``: an in-process simulated device.

pyserial finds this module through ``serial.protocol_handler_packages`` (the
``m2s2hil.simulators`` package adds itself on import), so drivers open a simulated
device with the same ``serial.serial_for_url`` call that opens ``/dev/ttyUSB0``.
Reads wait on the device's clock: with a virtual clock a timeout costs no wall time.
"""

from __future__ import annotations

import urllib.parse

from m2s2hil.simulators import registry
from m2s2hil.simulators.device import PortVanished
from serial.serialutil import PortNotOpenError, SerialBase, SerialException


class Serial(SerialBase):
    BAUDRATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)

    def __init__(self, *args, **kwargs) -> None:
        self._device = None
        super().__init__(*args, **kwargs)

    # -- life cycle ------------------------------------------------------------------
    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        self._device = self._lookup(self.portstr)
        if not self._device.present:
            raise SerialException(f"could not open port {self.portstr}: device not present")
        self.is_open = True

    def close(self) -> None:
        self.is_open = False
        self._device = None

    @staticmethod
    def _lookup(url: str):
        parts = urllib.parse.urlsplit(url)
        if parts.scheme != "sim":
            raise SerialException(f"expected sim://NAME, got {url!r}")
        name = parts.netloc or parts.path.lstrip("/")
        try:
            return registry.lookup(name)
        except KeyError as exc:
            raise SerialException(str(exc)) from None

    def _reconfigure_port(self, *args, **kwargs) -> None:
        pass  # settings are irrelevant to an in-process device

    # -- I/O -------------------------------------------------------------------------
    def _dev(self):
        if not self.is_open or self._device is None:
            raise PortNotOpenError()
        return self._device

    @property
    def in_waiting(self) -> int:
        try:
            return self._dev().pending()
        except PortVanished as exc:
            raise SerialException(str(exc)) from exc

    def write(self, data) -> int:
        dev = self._dev()
        data = bytes(data)
        try:
            dev.receive(data)
        except PortVanished as exc:
            raise SerialException(str(exc)) from exc
        return len(data)

    def read(self, size: int = 1) -> bytes:
        dev = self._dev()
        clock = dev.clock
        timeout = self._timeout
        deadline = None if timeout is None else clock.monotonic() + timeout
        buf = bytearray()
        try:
            while len(buf) < size:
                buf += dev.take(size - len(buf))
                if len(buf) >= size or timeout == 0:
                    break
                now = clock.monotonic()
                due = dev.next_due()
                if deadline is not None and now >= deadline:
                    break
                if due is None:
                    if deadline is None:
                        raise SerialException(f"{self.portstr}: blocking read with nothing to come")
                    clock.sleep(deadline - now)
                else:
                    wait = due - now
                    if deadline is not None:
                        wait = min(wait, deadline - now)
                    clock.sleep(max(wait, 0.0))
        except PortVanished as exc:
            raise SerialException(str(exc)) from exc
        return bytes(buf)

    def reset_input_buffer(self) -> None:
        dev = self._dev()
        try:
            dev.take()
        except PortVanished as exc:
            raise SerialException(str(exc)) from exc

    def reset_output_buffer(self) -> None:
        self._dev()

    @property
    def out_waiting(self) -> int:
        return 0

    def cancel_read(self) -> None:
        pass

    def cancel_write(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    def _update_break_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True

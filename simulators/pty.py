"""Serve simulated devices on pseudo-terminals, in real time.

Each device gets a pty pair; the slave path (``/dev/pts/N``) is what a serial client
opens, with pyserial or any third-party library. The slave end stays open here so
the master does not see EIO when a client closes. A thread per device moves bytes
between the master end and the device.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import tty

from m2s2hil.simulators.device import PortVanished, SimDevice


class PtyServer:
    def __init__(self, device: SimDevice) -> None:
        self.device = device
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tty.setraw(self._master)
        self.path = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"pty-{device.name}", daemon=True)

    def start(self) -> PtyServer:
        self._thread.start()
        return self

    def _run(self) -> None:
        dev = self.device
        while not self._stop.is_set():
            due = dev.next_due()
            now = dev.clock.monotonic()
            wait = 0.05 if due is None else min(0.05, max(0.0, due - now))
            try:
                ready, _, _ = select.select([self._master], [], [], wait)
            except (OSError, ValueError):
                return
            if ready:
                try:
                    data = os.read(self._master, 4096)
                except OSError:
                    return
                with contextlib.suppress(PortVanished):
                    dev.receive(data)  # an unplugged device hears nothing
            try:
                out = dev.take()
            except PortVanished:
                continue
            if out:
                try:
                    os.write(self._master, out)
                except OSError:
                    return

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> PtyServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

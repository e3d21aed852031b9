"""The base of every simulated serial device.

A simulated device is driven by bytes: the transport hands it what the host wrote
(:meth:`SimDevice.receive`) and collects what it answers (:meth:`SimDevice.take`).
Replies are scheduled on the device's clock, so a reply can be late and motion can
take time; the transport decides how to wait (virtual clock in-process, real time on
a pseudo-terminal). Generic faults (dropped, garbled, late replies, a vanishing
port) are applied here, once for all devices.
"""

from __future__ import annotations

import heapq
import itertools
import threading
from typing import Any

from m2s2hil.simulators.fault_injection import FaultPlan


class PortVanished(OSError):
    """The simulated port is gone (unplugged): like a USB-serial adapter pulled out."""


class SimDevice:
    """Subclasses implement :meth:`on_bytes` and answer with :meth:`send`."""

    #: Default serial settings the device expects (informational; sim:// ignores them).
    baudrate = 115200

    def __init__(self, name: str, clock: Any, faults: FaultPlan | None = None) -> None:
        self.name = name
        self.clock = clock
        self.faults = faults if faults is not None else FaultPlan()
        self._out: list[tuple[float, int, bytes]] = []
        self._seq = itertools.count()
        self._absent_until: float | None = None
        self.lock = threading.RLock()
        self.received = bytearray()  # everything the host wrote, for tests

    # -- host side (called by transports) --------------------------------------------
    @property
    def present(self) -> bool:
        with self.lock:
            if self._absent_until is None:
                return True
            if self.clock.monotonic() >= self._absent_until:
                self._absent_until = None
                self.on_reconnect()
                return True
            return False

    def receive(self, data: bytes) -> None:
        """Bytes written by the host."""
        with self.lock:
            if not self.present:
                raise PortVanished(f"{self.name}: port vanished")
            params = self.faults.take("vanish")
            if params is not None:
                self.vanish(float(params.get("duration_s", 1.0)))
                raise PortVanished(f"{self.name}: port vanished")
            self.received += data
            self.on_bytes(data)

    def take(self, limit: int | None = None) -> bytes:
        """Bytes whose time has come, at most ``limit``."""
        with self.lock:
            if not self.present:
                raise PortVanished(f"{self.name}: port vanished")
            self.poll(self.clock.monotonic())
            now = self.clock.monotonic()
            out = bytearray()
            while self._out and self._out[0][0] <= now:
                due, seq, chunk = self._out[0]
                if limit is not None and len(out) + len(chunk) > limit:
                    room = limit - len(out)
                    if room > 0:
                        out += chunk[:room]
                        self._out[0] = (due, seq, chunk[room:])
                    break
                heapq.heappop(self._out)
                out += chunk
            return bytes(out)

    def pending(self) -> int:
        """How many bytes are due now."""
        with self.lock:
            self.poll(self.clock.monotonic())
            now = self.clock.monotonic()
            return sum(len(c) for due, _, c in self._out if due <= now)

    def next_due(self) -> float | None:
        with self.lock:
            times = [self._out[0][0]] if self._out else []
            ev = self.next_event()
            if ev is not None:
                times.append(ev)
            return min(times) if times else None

    def vanish(self, duration_s: float) -> None:
        """Unplug the port for ``duration_s`` of the device's clock."""
        with self.lock:
            self._absent_until = self.clock.monotonic() + duration_s
            self._out.clear()
            self.on_disconnect()

    # -- device side -----------------------------------------------------------------
    def send(self, data: bytes, delay: float = 0.0, *, reply: bool = True) -> None:
        """Schedule ``data`` for the host. ``reply`` marks answers that faults may hit."""
        if reply:
            if self.faults.take("drop_reply") is not None:
                return
            g = self.faults.take("garble")
            if g is not None:
                data = _garble(data, g)
            late = self.faults.take("late_reply")
            if late is not None:
                delay += float(late.get("delay_s", 2.0))
        with self.lock:
            heapq.heappush(self._out, (self.clock.monotonic() + delay, next(self._seq), data))

    def on_bytes(self, data: bytes) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def poll(self, now: float) -> None:
        """Time-based behaviour (motion finishing, alarms); called before every read."""

    def next_event(self) -> float | None:
        """When :meth:`poll` will next have something to do, if it knows."""
        return None

    def on_disconnect(self) -> None:
        """The port vanished: reset volatile state as the real device would."""

    def on_reconnect(self) -> None:
        """The port came back (a freshly powered device may greet the host here)."""


def _garble(data: bytes, params: dict[str, Any]) -> bytes:
    # Deterministic corruption: flip high bits so printable text becomes non-ASCII.
    if not data:
        return data
    out = bytearray(data)
    step = max(1, len(out) // int(params.get("bytes", 3)))
    for i in range(0, len(out), step):
        out[i] ^= 0xA5
    return bytes(out)

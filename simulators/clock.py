"""A virtual clock for in-process simulations.

Time only moves when someone sleeps on it (or calls :meth:`advance`), so a sweep
that would take an hour on the bench runs in seconds while every duration it
reports is the simulated one. It satisfies ``m2s2hil.drivers.clock.Clock``
structurally. Simulators served in real time (pseudo-terminals) use the one real-time
clock, ``m2s2hil.drivers.clock.SystemClock``.
"""

from __future__ import annotations

import threading
import time


class VirtualClock:
    def __init__(self, start: float = 0.0, epoch: float | None = None) -> None:
        self._now = float(start)
        self._epoch = time.time() if epoch is None else float(epoch)
        self._lock = threading.Lock()

    def monotonic(self) -> float:
        with self._lock:
            return self._now

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.advance(seconds)
        else:
            # Yield the GIL so other threads (pipeline stages) make progress.
            time.sleep(0)

    def advance(self, seconds: float) -> None:
        with self._lock:
            self._now += max(0.0, float(seconds))

    def wall(self) -> float:
        return self._epoch + self.monotonic()

"""The clock every wait goes through.

Drivers never call ``time.sleep`` or ``time.monotonic`` directly: they take a
``Clock``. On the bench that is :class:`SystemClock`, the one real-time clock (simulators
served on pseudo-terminals run on it too); in-process simulations pass the simulators'
virtual clock, so a long sweep runs in seconds of wall time.
"""

from __future__ import annotations

import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """Monotonic time in seconds and a way to wait."""

    def monotonic(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...

    def wall(self) -> float:
        """Seconds since the epoch, for timestamps in records."""
        ...


class SystemClock:
    """Real time: ``time.monotonic`` for waits, ``time.time`` for records."""

    def monotonic(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def wall(self) -> float:
        return time.time()


SYSTEM_CLOCK = SystemClock()

"""Long operator actions in progress (a snapshot, darks, the white reference, the phase check, an
export): each may run once at a time, and a client can see what runs and since when.

Without this a second click on *Snapshot* queued behind the first one on the rig's device lock
and ran again once the first was done; now it gets :class:`~.errors.Conflict` (409) at once,
naming what runs and for how long. The console polls :meth:`BusyActions.items` (``GET /rig/axes``
``busy``, ``GET /busy``) to disable its buttons while they run.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from .errors import Conflict


@dataclass
class Busy:
    key: str  # e.g. "snapshot", "export:<session>:zarr"
    what: str  # in words: "a snapshot"
    started: float = field(default_factory=time.monotonic)
    started_wall: float = field(default_factory=time.time)
    detail: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"key": self.key, "what": self.what, "since_s": round(time.monotonic() - self.started, 1),
                "started": self.started_wall, "detail": dict(self.detail)}


class BusyActions:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._running: dict[str, Busy] = {}

    def start(self, key: str, what: str, **detail: Any) -> Busy:
        """Claim ``key``; :class:`Conflict` when it already runs. Give it back with :meth:`end`."""
        with self._lock:
            cur = self._running.get(key)
            if cur is not None:
                ago = time.monotonic() - cur.started
                raise Conflict(f"{cur.what} is already running (started {ago:.1f} s ago): "
                               "wait for it to finish")
            b = self._running[key] = Busy(key, what, detail=detail)
            return b

    def end(self, busy: Busy) -> None:
        with self._lock:
            if self._running.get(busy.key) is busy:
                del self._running[busy.key]

    @contextlib.contextmanager
    def claim(self, key: str, what: str, **detail: Any) -> Iterator[Busy]:
        b = self.start(key, what, **detail)
        try:
            yield b
        finally:
            self.end(b)

    def items(self) -> list[dict[str, Any]]:
        with self._lock:
            return [b.to_dict() for b in self._running.values()]

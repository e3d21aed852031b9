"""Where manual moves were last sent, per axis, so that relative jogs add up.

A jog is relative: an operator who clicks +10° and then +1° means 11°. Taken from the read-back,
the second jog would start from wherever the axis happens to be while the first move still runs
(near its start), and the first jog would be lost. So a jog starts from the target of the last
manual move still in force, and from the read-back only when there is none: before the first
move, and after anything that may leave the axis elsewhere than its target — a stop (of the
axis, or the emergency stop), homing, setting an origin, a move the device refused, or a
session (which moves the axes itself). Manual requests are serialised by the rig guard's device
lock (:meth:`~.rig_guard.RigGuard.manual_access`), so jogs sent together end at their sum; a
sum beyond the soft limits is refused (422) and leaves the target as it was.
"""

from __future__ import annotations

import threading
from collections.abc import Callable


class MoveTargets:
    """The target of the last manual move per axis, until something makes it stale."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._targets: dict[str, float] = {}

    def base(self, role: str, read_back: Callable[[], float]) -> float:
        """Where a relative move of ``role`` starts: the pending target, else the read-back."""
        with self._lock:
            pending = self._targets.get(role)
        return float(read_back()) if pending is None else pending

    def commanded(self, role: str, target_deg: float) -> None:
        """A move to ``target_deg`` was sent (the device accepted it)."""
        with self._lock:
            self._targets[role] = float(target_deg)

    def pending(self, role: str) -> float | None:
        with self._lock:
            return self._targets.get(role)

    def forget(self, role: str | None = None) -> None:
        """The axis (every axis with None) may not stand at its target: read it back next time."""
        with self._lock:
            if role is None:
                self._targets.clear()
            else:
                self._targets.pop(role, None)

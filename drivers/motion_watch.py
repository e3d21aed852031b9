"""How long a motion may take: planned from the move, extended while it progresses.

A fixed timeout fails a slow or heavy rig that is still moving, and waits far too long
for one that stalled. Instead every wait on motion (a verified move, a stop, a park at
teardown) plans the motion's duration from its trapezoidal profile (distance, top
speed, acceleration: the rig file's, lowered to the controller's own limits where it
has them), adds a margin, and then keeps waiting for as long as the read-back position
still progresses. The wait fails only when the axis stops short (the read-back check
after it) or stalls: no progress of at least ``min_progress`` for ``stall_window_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from m2s2hil.drivers.clock import Clock

#: Planned duration x this, plus the reply slack, before a motion counts as overdue (logged).
PLAN_MARGIN = 1.5
#: No progress for this long (s) is a stall, unless the driver is given another window.
STALL_WINDOW_S = 2.0


def trapezoid_s(distance: float, speed: float, accel: float) -> float:
    """Duration of a rest-to-rest move over ``distance`` with top ``speed`` and ``accel``:
    accelerate, cruise, decelerate, or a triangle when the move is too short to reach
    top speed."""
    d = abs(distance)
    if d == 0 or speed <= 0 or accel <= 0:
        return 0.0
    if d <= speed * speed / accel:
        return 2.0 * math.sqrt(d / accel)
    return d / speed + speed / accel


def braking_s(speed: float, accel: float) -> float:
    """Time to decelerate from ``speed`` to rest."""
    return speed / accel if speed > 0 and accel > 0 else 0.0


@dataclass
class ProgressWatch:
    """Watches the read-back of one motion.

    With a ``target`` progress is the remaining distance shrinking; without one (a stop,
    whose rest point is not known exactly) any change of position counts.
    """

    clock: Clock
    planned_s: float
    slack_s: float
    stall_window_s: float
    min_progress: float
    target: float | None = None
    #: Planned duration x this (plus the slack) before the motion counts as overdue.
    margin: float = PLAN_MARGIN

    def __post_init__(self) -> None:
        now = self.clock.monotonic()
        self.started = now
        self.deadline = now + self.margin * self.planned_s + self.slack_s
        self._mark_t = now
        self._mark: float | None = None  # the remaining distance (or position) at the last progress
        self.last: float | None = None

    def update(self, position: float) -> bool:
        """Record a read-back; True when it progressed since the last mark."""
        self.last = position
        value = abs(self.target - position) if self.target is not None else position
        if self._mark is None:
            self._mark = value
            return False
        moved = (self._mark - value) if self.target is not None else abs(value - self._mark)
        if moved >= self.min_progress:
            self._mark, self._mark_t = value, self.clock.monotonic()
            return True
        return False

    @property
    def stalled(self) -> bool:
        return self.clock.monotonic() - self._mark_t >= self.stall_window_s

    @property
    def overdue(self) -> bool:
        return self.clock.monotonic() > self.deadline

    @property
    def elapsed(self) -> float:
        return self.clock.monotonic() - self.started

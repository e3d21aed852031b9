"""Pieces both motion simulators share: trapezoidal moves timed on the clock, a log of
the recent path, and replies that stay in order.

A move is computed, not stepped: :class:`Segment` knows where it is at any time ``t``
from its start time and a :class:`Trapezoid` speed profile, so a virtual clock can
jump over a long move and the position is still exact. :class:`PathLog` keeps the last
few motion changes so the position at a moment just past can be asked after the fact.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


class Trapezoid:
    """A 1-D move of ``length`` from speed ``v0`` to rest: accelerate, cruise, decelerate.

    Both motion controllers the rig drives move this way, so the simulators time moves with
    it and the plan's duration model (``m2s2hil.plan.estimate.move_time_s``) calls
    :func:`rest_to_rest_s`, this profile's duration, rather than a formula of its own:

    - GRBL 1.1h: a block's acceleration and nominal rate are ``$120..$122`` / ``$110..$112``
      limited by every axis on the line (``limit_value_by_axis_maximum`` in
      [src:planner.c ``plan_buffer_line``]); a block planned into an empty buffer enters at
      rest and the last block of the buffer is planned to exit at rest
      [src:planner.c ``planner_recalculate``]; the stepper's segment generator then runs
      each block as a trapezoid (accelerate, cruise, decelerate) or, when the block is too
      short to reach its nominal rate, a triangle [src:stepper.c ``st_prep_buffer``, ramp
      types ``RAMP_ACCEL``/``RAMP_CRUISE``/``RAMP_DECEL``]. Jogs (``$J=``) go through the
      same planner [GRBL v1.1 wiki "Grbl v1.1 Jogging"]. ([src:FILE]: gnea/grbl v1.1h.)
    - Zaber ASCII: ``accel`` is "the acceleration and deceleration used when changing
      speeds" and ``maxspeed`` the speed a ``move abs|rel`` travels at
      [Zaber ASCII Protocol Manual, settings ``accel`` and ``maxspeed``,
      https://www.zaber.com/protocol-manual#topic_setting_accel]: a trapezoid, a triangle for
      a short move (the simulator uses the same ``accel`` for both; firmware 7's separate
      ``motion.accelonly``/``motion.decelonly`` are not simulated).

    What the simulation leaves out: GRBL's junction blending (``$11`` junction deviation)
    between consecutive blocks; the engine sends one axis's block at a time and waits for
    it, so a block always starts and ends at rest, except a turntable block queued right
    behind a tilt block, whose 90° junction GRBL would cross at about
    sqrt(a·$11·sin(θ/2)/(1 − sin(θ/2))) ≈ 1 unit/s (saving some 15 ms on this rig's
    settings, a few times a build). GRBL's 100 Hz acceleration ticks
    [src:config.h ``ACCELERATION_TICKS_PER_SECOND``] are integrated exactly here.
    """

    def __init__(self, length: float, v_max: float, accel: float, v0: float = 0.0) -> None:
        if length < 0 or v_max <= 0 or accel <= 0 or v0 < 0:
            raise ValueError(f"bad profile: length={length} v_max={v_max} accel={accel} v0={v0}")
        self.length = length
        self.v0 = v0
        if length == 0:
            self.vp = self.a1 = self.t1 = self.t2 = self.t3 = self.d1 = self.d2 = 0.0
            self.a3 = accel
            return
        if v0 * v0 / (2 * accel) >= length:
            # Already too fast to stop in time: brake harder (only a hold's own braking lands here).
            self.vp, self.a1, self.t1, self.d1, self.t2, self.d2 = v0, 0.0, 0.0, 0.0, 0.0, 0.0
            self.a3 = v0 * v0 / (2 * length)
            self.t3 = v0 / self.a3
            return
        vp = min(v_max, math.sqrt((2 * accel * length + v0 * v0) / 2))
        self.vp = vp
        self.a1 = accel if vp >= v0 else -accel
        self.a3 = accel
        self.t1 = abs(vp - v0) / accel
        self.d1 = abs(vp * vp - v0 * v0) / (2 * accel)
        d3 = vp * vp / (2 * accel)
        self.d2 = max(0.0, length - self.d1 - d3)
        # A denormal length can underflow vp to 0: then there is no cruise phase to time.
        self.t2 = self.d2 / vp if vp > 0 else 0.0
        self.t3 = vp / accel

    @property
    def duration(self) -> float:
        return self.t1 + self.t2 + self.t3

    def distance(self, t: float) -> float:
        if t <= 0:
            return 0.0
        if t < self.t1:
            return self.v0 * t + 0.5 * self.a1 * t * t
        t -= self.t1
        if t < self.t2:
            return self.d1 + self.vp * t
        t -= self.t2
        if t < self.t3:
            return min(self.length, self.d1 + self.d2 + self.vp * t - 0.5 * self.a3 * t * t)
        return self.length

    def speed(self, t: float) -> float:
        if t < 0 or t >= self.duration:
            return 0.0
        if t < self.t1:
            return self.v0 + self.a1 * t
        t -= self.t1
        if t < self.t2:
            return self.vp
        return max(0.0, self.vp - self.a3 * (t - self.t2))

    def time_at(self, s: float) -> float:
        """When the move has covered ``s`` (clamped to the move)."""
        if s <= 0:
            return 0.0
        if s >= self.length:
            return self.duration
        if s < self.d1:
            return _solve(0.5 * self.a1, self.v0, -s)
        if s < self.d1 + self.d2:
            return self.t1 + (s - self.d1) / self.vp
        rest = s - self.d1 - self.d2
        return self.t1 + self.t2 + _solve(-0.5 * self.a3, self.vp, -rest)


def rest_to_rest_s(length: float, v_max: float, accel: float) -> float:
    """Duration of a move of ``length`` from rest to rest at ``v_max`` and ``accel`` (see
    :class:`Trapezoid`): ``length/v_max + v_max/accel`` when it reaches ``v_max``
    (``length >= v_max²/accel``), else the triangle ``2·sqrt(length/accel)``."""
    return Trapezoid(abs(length), v_max, accel).duration


def _solve(a: float, b: float, c: float) -> float:
    """Smallest non-negative root of a t^2 + b t + c = 0."""
    if abs(a) < 1e-15:
        return -c / b
    disc = max(0.0, b * b - 4 * a * c)
    roots = sorted(r for r in ((-b - math.sqrt(disc)) / (2 * a), (-b + math.sqrt(disc)) / (2 * a)) if r >= 0)
    return roots[0] if roots else 0.0


@dataclass
class Segment:
    """A straight move through machine space starting at clock time ``t0``."""

    start: tuple[float, ...]
    end: tuple[float, ...]
    t0: float
    profile: Trapezoid
    stop_after: float | None = None  # a stall: the motion freezes after this distance
    kind: str = "run"

    @classmethod
    def between(
        cls,
        start: tuple[float, ...],
        end: tuple[float, ...],
        t0: float,
        *,
        v_max: float,
        accel: float,
        v0: float = 0.0,
        kind: str = "run",
    ) -> Segment:
        length = math.dist(start, end)
        return cls(start, end, t0, Trapezoid(length, v_max, accel, v0), kind=kind)

    @property
    def length(self) -> float:
        return self.profile.length

    @property
    def unit(self) -> tuple[float, ...]:
        if self.length == 0:
            return tuple(0.0 for _ in self.start)
        return tuple((e - s) / self.length for s, e in zip(self.start, self.end, strict=True))

    @property
    def t_end(self) -> float:
        if self.stop_after is not None:
            return self.t0 + self.profile.time_at(self.stop_after)
        return self.t0 + self.profile.duration

    def covered(self, t: float) -> float:
        s = self.profile.distance(t - self.t0)
        return s if self.stop_after is None else min(s, self.stop_after)

    def position(self, t: float) -> tuple[float, ...]:
        s = self.covered(t)
        if s >= self.length:
            return self.end
        return tuple(p + u * s for p, u in zip(self.start, self.unit, strict=True))

    def speed(self, t: float) -> float:
        if self.stop_after is not None and t >= self.t_end:
            return 0.0
        return self.profile.speed(t - self.t0)


class PathLog:
    """The recent path of a simulated axis: pieces "from time ``t`` on, the axis is at ``at(t)``".

    A simulator notes a piece whenever its motion changes (a move starts, ends, is braked
    or cut short), so :meth:`at` answers for any moment since the oldest piece kept: a
    camera renders a frame once its exposure is over, when the move it saw may already
    have ended. Earlier moments get the oldest piece's answer; a moment ahead of the last
    change gets the motion as planned at that change (later commands are not foreseen).
    """

    def __init__(self, keep: int = 16) -> None:
        self._pieces: deque[tuple[float, Callable[[float], Any]]] = deque(maxlen=keep)
        self._key: tuple[Any, ...] | None = None

    def note(self, t: float, key: tuple[Any, ...], at: Callable[[float], Any]) -> None:
        """From ``t`` on the axis follows ``at``; ignored while ``key`` is unchanged (items
        compared by identity or equality), so it can be called after every event."""
        old = self._key
        if old is not None and len(old) == len(key) and all(
                a is b or a == b for a, b in zip(old, key, strict=True)):
            return
        self._key = key
        if self._pieces:
            t = max(t, self._pieces[-1][0])  # pieces stay in time order
            if self._pieces[-1][0] == t:
                self._pieces.pop()  # the previous piece lasted no time at all
        self._pieces.append((t, at))

    def at(self, t: float) -> Any:
        if not self._pieces:
            raise LookupError("no motion noted yet")
        for t_from, fn in reversed(self._pieces):
            if t_from <= t:
                return fn(t)
        return self._pieces[0][1](t)


class InOrderReplies:
    """Mixin for a SimDevice: a reply never overtakes an earlier one.

    The base class may delay one reply (the ``late_reply`` fault); a serial device
    still sends its bytes in order, so every later reply waits behind it.
    """

    _last_due: float = 0.0

    def send(self, data: bytes, delay: float = 0.0, *, reply: bool = True) -> None:
        now = self.clock.monotonic()  # type: ignore[attr-defined]
        delay = max(delay, self._last_due - now)
        out: list[Any] = self._out  # type: ignore[attr-defined]
        before = len(out)
        super().send(data, delay, reply=reply)  # type: ignore[misc]
        if len(out) > before:
            newest = max(out, key=lambda entry: entry[1])
            self._last_due = max(self._last_due, newest[0])

    def forget_order(self) -> None:
        """After the port vanished nothing is queued any more."""
        self._last_due = 0.0

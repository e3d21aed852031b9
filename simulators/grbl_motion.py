"""The planner and the axes of the simulated GRBL 1.1h, and the controller state they drive.

Motion lines go into a 15-block planner. Motion is a trapezoid per block (no junction
blending: every block starts and ends at rest), limited per axis by ``$110..$112``
(units/min) and ``$120..$122`` (units/s^2), computed from the clock: the position at
time t, not stepped. ``!`` brakes to Hold:1, then Hold:0 at rest; ``~`` resumes towards
the same target; ``!`` during a jog and 0x85 cancel the jog. Homing drives each homed
axis straight to its switch (physical 0) at ``$25`` and sets MPos 0 there.

The model writes nothing on the wire: :meth:`GrblMotion.advance` returns what ended the
motion (an alarm struck, homing finished) and the controller answers it. Positions here
are MPos; the physical position is MPos + an offset that homing zeroes and a power cycle
shifts (the position is lost). Faults drawn here (``self.faults`` of the simulator):
``slow_motion``, ``stall``, ``hang``, ``alarm`` per move, ``hold_stuck`` per feed hold.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from m2s2hil.protocols.grbl import AXES, GrblAlarm
from m2s2hil.simulators.fault_injection import FaultPlan
from m2s2hil.simulators.grbl_settings import GrblAxisSettings, GrblEeprom
from m2s2hil.simulators.motion_kit import PathLog, Segment, Trapezoid

PLANNER_BLOCKS = 15


@dataclass(frozen=True)
class Block:
    target: tuple[float, ...]
    feed: float | None  # units/min; None = rapid
    kind: str  # "run" | "jog"


@dataclass(frozen=True)
class AlarmStruck:
    """An alarm stopped the motion. ``planner_full``: it struck while the planner was full,
    so a complete waiting line is inside its ``mc_line`` [src:motion_control.c]."""

    code: GrblAlarm
    planner_full: bool = False


@dataclass(frozen=True)
class Homed:
    """The homing cycle reached the switches: ``$H`` gets its ``ok``."""


class GrblMotion:
    """Planner, moves and ``state`` (Idle, Run, Hold, Jog, Home, Alarm: the firmware's
    ``sys.state``; the controller sets Alarm and Idle, the motion the others)."""

    def __init__(
        self, eeprom: GrblEeprom, per_axis: Sequence[GrblAxisSettings], faults: FaultPlan, now: float
    ) -> None:
        self._eeprom = eeprom
        self._faults = faults
        self.homing_axes = tuple(ax.homing for ax in per_axis)
        self._offset = [ax.start for ax in per_axis]  # physical = MPos + offset
        self.rest: tuple[float, ...] = (0.0, 0.0, 0.0)
        self.state = "Alarm" if eeprom.settings[22] else "Idle"
        self.clear()
        self._path = PathLog()  # physical positions over the recent motion changes
        self.note(now)

    def clear(self) -> None:
        """Forget the planned and running motion (a reset); the axes stay at ``rest``."""
        self._queue: deque[Block] = deque()
        self.segment: Segment | None = None
        self._current: Block | None = None
        self._pending_alarm: tuple[float, GrblAlarm] | None = None
        self.hold_done = False
        self._slow = 1.0  # the current motion's slow_motion factor
        self._hung = False  # the current segment froze part-way but still reports Run
        self._hold_stuck = False  # the current hold never reports Hold:0

    def halt(self, now: float) -> None:
        """A soft reset: the steppers stop where they are."""
        self.rest = self.position(now)
        self.clear()

    def power_cycle(self, now: float) -> None:
        """The board lost power: MPos restarts at 0 where the axes stand."""
        pos = self.position(now)
        self._offset = [p + o for p, o in zip(pos, self._offset, strict=True)]
        self.rest = (0.0, 0.0, 0.0)
        self.clear()
        self.state = "Alarm" if self._eeprom.settings[22] else "Idle"

    # -- where the axes are --------------------------------------------------------------
    def position(self, now: float) -> tuple[float, ...]:
        return self.segment.position(now) if self.segment is not None else self.rest

    def physical(self, now: float) -> tuple[float, ...]:
        return tuple(p + o for p, o in zip(self.position(now), self._offset, strict=True))

    def physical_at(self, t: float) -> tuple[float, ...]:
        """The physical position at a moment just past (see :class:`PathLog`)."""
        return tuple(self._path.at(t))

    def speed(self, now: float) -> float:
        seg = self.segment
        if seg is None or (self._hung and seg.covered(now) >= (seg.stop_after or 0.0)):
            return 0.0  # a hung move stands at its freezing point
        return seg.speed(now)

    def state_text(self) -> str:
        if self.state == "Hold":
            return f"Hold:{0 if self.hold_done else 1}"
        return self.state

    def note(self, t: float) -> None:
        """Log the motion from ``t`` on (a no-op unless segment, rest or offset changed)."""
        seg, off = self.segment, tuple(self._offset)
        if seg is None:
            rest = tuple(r + o for r, o in zip(self.rest, off, strict=True))
            self._path.note(t, (None, rest), lambda _t: rest)
        else:
            self._path.note(seg.t0, (seg, off), lambda t_: tuple(
                p + q for p, q in zip(seg.position(t_), off, strict=True)))

    # -- the planner -----------------------------------------------------------------------
    def planned_blocks(self) -> int:
        return len(self._queue) + (self._current is not None)

    def planner_full(self) -> bool:
        return self.planned_blocks() >= PLANNER_BLOCKS

    def pending(self) -> bool:
        """Anything planned or moving (a G10 waits for this to end)."""
        return self.segment is not None or self._current is not None or bool(self._queue)

    def planned_end(self) -> tuple[float, ...]:
        """Where the planned motion ends: the start of the next block."""
        if self._queue:
            return self._queue[-1].target
        if self._current is not None:
            return self._current.target
        return self.rest

    @property
    def soft_limit_braking(self) -> bool:
        """Braking before ALARM:2; the offending line waits for its ok."""
        return self.segment is not None and self.segment.kind == "softlimit"

    def plan(self, block: Block, now: float) -> None:
        """A G0/G1 or jog block into the planner; it starts at once if the axes are free
        (a run block not while held)."""
        self._queue.append(block)
        if self.segment is None and (block.kind == "jog" or self.state in ("Idle", "Run")):
            self._start_next(now)

    def outside_travel(self, target: tuple[float, ...]) -> bool:
        """Soft limits (``$20=1``): the travel follows a HOMING_FORCE_SET_ORIGIN build,
        ``[-$13x, 0]``, or ``[0, $13x]`` for an axis whose ``$23`` direction bit is set."""
        settings = self._eeprom.settings
        if not settings[20]:
            return False
        for i, v in enumerate(target):
            travel = settings[130 + i]
            positive = int(settings[23]) >> i & 1
            lo, hi = (0.0, travel) if positive else (-travel, 0.0)
            if v < lo - 1e-9 or v > hi + 1e-9:
                return True
        return False

    def soft_limit(self, now: float) -> bool:
        """A G0/G1 target outside the travel [src:limits.c limits_soft_check]: the planner is
        dropped; True if the axes were moving and now brake under control (a feed hold) before
        the alarm, False if the alarm is due now."""
        self._queue.clear()
        if self.segment is not None and self.state == "Run":
            self._brake(now, "softlimit")
            self.state, self.hold_done = "Hold", False
            return True
        self.segment, self._current = None, None
        return False

    # -- time --------------------------------------------------------------------------
    def next_event(self) -> float | None:
        times = []
        if self.segment is not None and not self._hung:
            times.append(self.segment.t_end)
        if self._pending_alarm is not None:
            times.append(self._pending_alarm[0])
        return min(times) if times else None

    def advance(self, now: float) -> AlarmStruck | Homed | None:
        """Run the motion up to ``now``; returns what ended it if an alarm or homing did."""
        while True:
            seg = self.segment
            alarm = self._pending_alarm
            if seg is not None and alarm is not None and alarm[0] <= now and alarm[0] <= seg.t_end:
                struck = AlarmStruck(alarm[1], self.planner_full())
                self._pending_alarm = None
                self.rest = seg.position(alarm[0])
                self.segment, self._current = None, None
                self._queue.clear()
                self.note(alarm[0])
                return struck
            if seg is None or seg.t_end > now or self._hung:
                return None
            t = seg.t_end
            self.rest = seg.position(t)
            self.segment = None
            ended: AlarmStruck | Homed | None = None
            if alarm is not None and alarm[0] > t:
                self._pending_alarm = None  # the move ended (stalled) before the alarm point
            if seg.kind == "hold":
                self.hold_done = not self._hold_stuck
            elif seg.kind == "softlimit":
                # The controlled stop is over: now the critical alarm [src:limits.c].
                self._queue.clear()
                self._current = None
                ended = AlarmStruck(GrblAlarm.SOFT_LIMIT)
            elif seg.kind == "jogcancel":
                self._queue.clear()
                self._current = None
                self.state = "Idle"
            elif seg.kind == "home":
                self._finish_homing()
                ended = Homed()
            else:
                self._start_next(t)
            self.note(t)
            if ended is not None:
                return ended

    def _limits(
        self, start: tuple[float, ...], end: tuple[float, ...], feed: float | None
    ) -> tuple[float, float]:
        """(rate units/min, accel units/s^2) along the line, limited by every axis on it."""
        settings = self._eeprom.settings
        seg = Segment.between(start, end, 0.0, v_max=1.0, accel=1.0)
        rate = accel = float("inf")
        for i, u in enumerate(seg.unit):
            if abs(u) > 1e-12:
                rate = min(rate, settings[110 + i] / abs(u))
                accel = min(accel, settings[120 + i] / abs(u))
        if feed is not None:
            rate = min(rate, feed)
        return rate, accel

    def _start_next(self, t: float) -> None:
        while self._queue:
            block = self._queue.popleft()
            rate, accel = self._limits(self.rest, block.target, block.feed)
            if rate == float("inf") or rate <= 0:
                self.rest = block.target
                continue  # zero-length block
            slow = self._faults.take("slow_motion")
            self._slow = float(slow.get("factor", 5.0)) if slow is not None else 1.0
            seg = Segment.between(
                self.rest, block.target, t, v_max=rate / 60.0 / self._slow, accel=accel / self._slow**2,
                kind=block.kind,
            )
            stall = self._faults.take("stall")
            if stall is not None:
                seg.stop_after = float(stall.get("fraction", 0.5)) * seg.length
            hang = self._faults.take("hang")
            if hang is not None:
                seg.stop_after = float(hang.get("fraction", 0.5)) * seg.length
                self._hung = True
            fault = self._faults.take("alarm")
            if fault is not None:
                when = t + float(fault.get("at", 0.5)) * seg.profile.duration
                self._pending_alarm = (when, GrblAlarm(int(fault.get("code", 1))))
            self.segment, self._current = seg, block
            self.state = "Jog" if block.kind == "jog" else "Run"
            return
        self.segment, self._current = None, None
        if self.state in ("Run", "Jog"):
            self.state = "Idle"

    # -- real-time commands ----------------------------------------------------------------
    def _brake(self, now: float, kind: str) -> None:
        """Replace the current segment by its deceleration to rest."""
        seg = self.segment
        assert seg is not None
        pos, v = seg.position(now), self.speed(now)
        self._hung = False
        _, accel = self._limits(seg.start, seg.end, None)
        accel /= self._slow**2
        length = v * v / (2 * accel) if v > 0 else 0.0
        end = tuple(p + u * length for p, u in zip(pos, seg.unit, strict=True))
        self.segment = Segment(pos, end, now, Trapezoid(length, max(v, 1e-9), accel, v0=v), kind=kind)
        self._pending_alarm = None

    def feed_hold(self, now: float) -> None:
        if self.state == "Jog":
            self.jog_cancel(now)
        elif self.state == "Run" and self.segment is not None:
            assert self._current is not None
            self._queue.appendleft(self._current)  # resume heads for the same target
            self._brake(now, "hold")
            self.state, self.hold_done = "Hold", False
            self._hold_stuck = self._faults.take("hold_stuck") is not None

    def cycle_start(self, now: float) -> None:
        if self.state == "Hold" and self.hold_done:
            self.state, self.hold_done = "Run", False
            self._start_next(now)

    def jog_cancel(self, now: float) -> None:
        if self.state != "Jog":
            return
        self._queue.clear()
        if self.segment is not None:
            self._brake(now, "jogcancel")
        else:
            self.state = "Idle"

    # -- homing --------------------------------------------------------------------------
    def start_homing(self, now: float) -> bool:
        """``$H`` (with ``$22=1``); True if every homed axis already sits on its switch."""
        target = tuple(-self._offset[i] if self.homing_axes[i] else self.rest[i] for i in range(len(AXES)))
        rate, accel = self._limits(self.rest, target, self._eeprom.settings[25])
        self.state = "Home"
        if rate == float("inf"):
            self._finish_homing()
            return True
        seg = Segment.between(self.rest, target, now, v_max=rate / 60.0, accel=accel, kind="home")
        self.segment = seg
        fault = self._faults.take("alarm")
        if fault is not None:
            self._pending_alarm = (now + 0.5 * seg.profile.duration, GrblAlarm.HOMING_FAIL_APPROACH)
        return False

    def _finish_homing(self) -> None:
        rest = list(self.rest)
        for i, homed in enumerate(self.homing_axes):
            if homed:
                self._offset[i] = 0.0
                rest[i] = 0.0
        self.rest = tuple(rest)
        self.state = "Idle"

"""A GRBL 1.1 motion controller as a simulated serial device.

Sources (cited as [config], [iface], [src:FILE] below and in docs/simulators.md):
[config] the GRBL v1.1 wiki page "Grbl v1.1 Configuration" (the ``$$`` settings);
[iface] the GRBL v1.1 wiki page "Grbl v1.1 Interface" (replies, push messages, reports);
[src:FILE] the firmware source, gnea/grbl v1.1h, ``grbl/FILE``.

Factory state: the settings table of ``DEFAULTS_GENERIC`` [src:defaults.h] (the build a
stock Arduino GRBL 1.1h carries): homing, soft and hard limits off (``$22=0``, ``$20=0``,
``$21=0``), 250 steps/mm, 500 mm/min maximum rates, 10 mm/s² accelerations, 200 mm
travel, status reports in machine position (``$10=1``). Anything can be changed through
the constructor (``settings=``, per-axis :class:`GrblAxisSettings`, ``version=``).

What it does as the firmware does (byte level, replies strictly in order):
- real-time bytes (``?`` ``!`` ``~`` 0x18 0x85) act at once and never enter the
  receive buffer; everything else goes into a 127-byte receive buffer. Bytes that
  arrive with the buffer full are LOST, as on the firmware (counted in
  :attr:`GrblSimulator.rx_overflow` so a test can see it).
- lines are executed when they complete; motion lines go into a 15-block planner
  and are answered ``ok`` when planned. With the planner full, lines wait in the
  receive buffer, so character counting matters.
- motion is a trapezoid per block (no junction blending: every block starts and ends
  at rest), limited per axis by ``$110..$112`` (units/min) and ``$120..$122``
  (units/s^2), computed from the clock: the position at time t, not stepped.
- ``!`` decelerates to Hold:1 then Hold:0, ``~`` resumes (ignored until the hold is
  complete); ``!`` during a jog and 0x85 cancel the jog.
- 0x18 soft reset: ``ALARM:3`` first if it was moving (ALARM:6 while homing), then an
  ``ok`` for a line the firmware was still executing (the line that hit the soft limit,
  or a motion line blocked on a full planner: its ``mc_line`` returns into the main loop,
  which reports ``ok`` before bailing out [src:protocol.c, motion_control.c]), then the
  banner ``Grbl 1.1h ['$' for help]`` and, when the controller is in alarm,
  ``[MSG:'$H'|'$X' to unlock]`` [src:main.c, protocol.c]. The alarm state survives.
- ``$22=1`` boots locked in Alarm (HOMING_INIT_LOCK, on in the stock config.h);
  ``$H`` homes, ``$X`` unlocks; with ``$22=0`` ``$H`` answers ``error:5`` (setting
  disabled) [src:system.c].
- soft limits (``$20=1``, needs ``$22=1``): a G0/G1 target outside the travel makes the
  firmware feed-hold to a controlled stop if it is moving, then raise the critical
  ``ALARM:2`` and ``[MSG:Reset to continue]``; the offending line gets its ``ok`` only
  after the reset [src:limits.c limits_soft_check]. A jog target outside is
  ``error:15``. The travel follows a HOMING_FORCE_SET_ORIGIN build: ``[-$13x, 0]``, or
  ``[0, $13x]`` for an axis whose ``$23`` direction bit is set.
- after ``ALARM:1``/``ALARM:2`` (the only critical alarms [src:protocol.c]) everything
  but 0x18 is ignored, ``?`` included (GRBL 1.1's critical-event loop is empty).
- a failed homing (``ALARM:8``/``ALARM:9``) is not critical: the firmware resets itself
  (mc_reset), so ``ALARM:9`` is followed by the ``ok`` of ``$H`` [src:system.c], the
  banner and ``[MSG:'$H'|'$X' to unlock]``.
- work coordinates: ``G10 L2``/``G10 L20`` write G54..G59 offsets, kept across resets and
  power cycles as the firmware keeps them in EEPROM; a G10 waits until motion has
  finished (FORCE_BUFFER_SYNC_DURING_EEPROM_WRITE, on in the stock config.h). ``$#``
  reports them; status reports give MPos or WPos (= MPos − WCO) per ``$10`` bit 0 and
  ``WCO:`` every 10 reports (30 while moving) [iface].

Simplifications: homing drives each homed axis straight to its switch (physical 0)
at ``$25``, from either side, and sets MPos 0 there; no pull-off or locate phase. An
axis configured without a switch (``GrblAxisSettings.homing=False``) is left out of the
homing cycle, as a firmware built with other HOMING_CYCLE masks would. Only G54 can be
the active system; G92 and tool offsets are not simulated. ``$C``, ``$SLP``, arcs,
dwell are not simulated (``error:3``/``error:20``).
No banner at construction (a board that booted before the host opened the port);
a vanished port is a power cycle: position is lost (MPos 0 where the axis stands),
and the banner greets the host when the port comes back.

For the simulated world, :meth:`GrblSimulator.axis_position` also answers for a moment
just past (``at=``): a camera renders a frame after its exposure, so it asks where the
axis was during it (the recent path is kept in a :class:`PathLog`).

Faults (``self.faults``): ``stall`` (``fraction``, default 0.5) stops the next move
part-way and reports Idle there; ``alarm`` (``code`` default 1, ``at`` default 0.5 of
the move) raises that alarm mid-move (during ``$H``: ALARM:9, then a reset). For a slow or
stuck rig: ``slow_motion`` (``factor``, default 5) runs the next move (each move with
``count = -1``) that many times slower than ``$11x``/``$12x`` say (speeds / factor,
accelerations / factor²: a heavier load, a weaker drive), its hold braking too; ``hang``
(``fraction``, default 0.5) freezes the next move part-way while the controller still
reports Run (the axis makes no progress); ``hold_stuck`` makes the next feed hold never
complete: the axis brakes to rest but the report stays ``Hold:1``, so only a soft reset
ends it (ALARM:3, as a reset during ``Hold:1`` does [iface]).
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from m2s2hil.protocols.grbl import (
    AXES,
    CRITICAL_ALARMS,
    MSG_RESET_TO_CONTINUE,
    MSG_RESTORING_DEFAULTS,
    MSG_UNLOCK,
    MSG_UNLOCKED,
    RX_BUFFER_SIZE,
    RX_BUFFER_USABLE,
    Alarm,
    Banner,
    BuildInfo,
    BuildOptions,
    DeviceLine,
    DeviceLineSplitter,
    Error,
    Event,
    Feedback,
    GrblAlarm,
    GrblError,
    Message,
    Ok,
    Setting,
    StartupBlock,
    StatusReport,
    format_event,
    is_realtime,
)
from m2s2hil.simulators.device import SimDevice
from m2s2hil.simulators.fault_injection import FaultPlan
from m2s2hil.simulators.grbl_gcode import CoordWrite, GcodeError, Modal, Motion, parse_block
from m2s2hil.simulators.motion_kit import InOrderReplies, PathLog, Segment, Trapezoid

PLANNER_BLOCKS = 15
_SETTING_WRITE = re.compile(r"\$(\d+(?:\.\d*)?)=(.*)")
_G10 = re.compile(rb"G0*10(?![0-9.])")
#: The coordinate tables ``$#`` lists, in its order [iface]: G54..G59, G28, G30.
COORD_TABLES = (54, 55, 56, 57, 58, 59, 28, 30)


@dataclass(frozen=True)
class GrblAxisSettings:
    """One axis; the defaults are DEFAULTS_GENERIC of GRBL 1.1h [src:defaults.h]."""

    max_rate: float = 500.0  # $11x, units/min (DEFAULT_X_MAX_RATE)
    accel: float = 10.0  # $12x, units/s^2 (DEFAULT_X_ACCELERATION = 10*60*60 mm/min^2)
    max_travel: float = 200.0  # $13x, units (DEFAULT_X_MAX_TRAVEL)
    steps_per_unit: float = 250.0  # $10x (DEFAULT_X_STEPS_PER_MM)
    homing: bool = True  # a home switch is fitted and the axis takes part in $H (when $22=1)
    start: float = 0.0  # physical position at power-up, units from the home switch


#: GRBL 1.1h factory settings without the per-axis ones, DEFAULTS_GENERIC [src:defaults.h],
#: numbered as in [config]: $0 step pulse 10 us, $1 idle delay 25 ms, $2..$6 invert masks 0,
#: $10=1 status reports MPos, $11 junction deviation 0.010 mm, $12 arc tolerance 0.002 mm,
#: $13=0 mm, $20=0 soft limits off, $21=0 hard limits off, $22=0 homing off, $23=0 homing
#: direction mask, $24 homing feed 25 mm/min, $25 homing seek 500 mm/min, $26 debounce
#: 250 ms, $27 pull-off 1 mm, $30/$31 spindle 1000/0 rpm, $32=0 laser mode off.
FACTORY_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0,
    30: 1000, 31: 0, 32: 0,
}  # fmt: skip
BASE_SETTINGS = FACTORY_SETTINGS  # the name older callers import


@dataclass(frozen=True)
class _Block:
    target: tuple[float, ...]
    feed: float | None  # units/min; None = rapid
    kind: str  # "run" | "jog"


class GrblSimulator(InOrderReplies, SimDevice):
    def __init__(
        self,
        name: str,
        clock: Any,
        *,
        axes: Mapping[str, GrblAxisSettings] | None = None,
        settings: Mapping[int, float] | None = None,
        faults: FaultPlan | None = None,
        version: str = "1.1h",
        build: str = "20190830",
    ) -> None:
        super().__init__(name, clock, faults)
        axes = dict(axes or {})
        unknown = set(axes) - set(AXES)
        if unknown:
            raise ValueError(f"GRBL has axes X, Y, Z; got {sorted(unknown)}")
        per_axis = [axes.get(a, GrblAxisSettings()) for a in AXES]
        self.settings: dict[int, float] = dict(FACTORY_SETTINGS)
        for i, ax in enumerate(per_axis):
            self.settings[100 + i] = ax.steps_per_unit
            self.settings[110 + i] = ax.max_rate
            self.settings[120 + i] = ax.accel
            self.settings[130 + i] = ax.max_travel
        unknown_settings = set(settings or {}) - set(self.settings)
        if unknown_settings:
            raise ValueError(f"GRBL 1.1 has no setting(s) {sorted(unknown_settings)}")
        self.settings.update(settings or {})
        self._defaults = dict(self.settings)
        self.homing_axes = tuple(ax.homing for ax in per_axis)
        self.version, self.build = version, build
        self.rx_overflow = 0  # bytes lost to a full receive buffer
        self.build_text = ""
        self.startup_blocks = {0: "", 1: ""}
        # Work coordinate tables, machine units; EEPROM on the board, so they survive resets.
        self.coord_data: dict[int, list[float]] = {n: [0.0, 0.0, 0.0] for n in COORD_TABLES}
        self._offset = [ax.start for ax in per_axis]  # physical = MPos + offset
        self._rest: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._state = "Alarm" if self.settings[22] else "Idle"
        self._reset_volatile()
        self._path = PathLog()  # physical positions over the recent motion changes
        self._note(clock.monotonic())

    def _reset_volatile(self) -> None:
        self._rx = bytearray()
        self._splitter = DeviceLineSplitter()
        self._queue: deque[_Block] = deque()
        self._segment: Segment | None = None
        self._current: _Block | None = None
        self._pending_alarm: tuple[float, GrblAlarm] | None = None
        self._modal = Modal()
        self._critical = False
        self._hold_done = False
        self._soft_limit_stop = False  # braking before ALARM:2; the line waits for its ok
        self._owed_ok = False  # a line still executing when a critical alarm struck
        self._slow = 1.0  # the current motion's slow_motion factor
        self._hung = False  # the current segment froze part-way but still reports Run
        self._hold_stuck = False  # the current hold never reports Hold:0
        self._wco_counter = 0
        self._ov_counter = 0

    # -- inspection (tests, the simulated world) -------------------------------------
    def axis_position(self, letter: str, at: float | None = None) -> float:
        """Where the axis physically is, in machine units from its home switch: now, or at
        clock time ``at`` (any moment since the last 16 motion changes; see :class:`PathLog`)."""
        i = AXES.index(letter.upper())
        with self.lock:
            now = self.clock.monotonic()
            self._advance(now)
            if at is None:
                return self._position(now)[i] + self._offset[i]
            return self._path.at(float(at))[i]

    def machine_position(self) -> tuple[float, ...]:
        """MPos as the controller would report it now."""
        with self.lock:
            now = self.clock.monotonic()
            self._advance(now)
            return self._position(now)

    @property
    def state(self) -> str:
        with self.lock:
            self._advance(self.clock.monotonic())
            return self._state_text()

    # -- SimDevice hooks -------------------------------------------------------------
    def on_bytes(self, data: bytes) -> None:
        now = self.clock.monotonic()
        self._advance(now)
        for b in data:
            if is_realtime(b):
                self._realtime(b, now)
            elif len(self._rx) < RX_BUFFER_USABLE:
                self._rx.append(b)
                if b in (0x0A, 0x0D):
                    self._process_lines(now)
            else:
                self.rx_overflow += 1
        self._note(now)

    def poll(self, now: float) -> None:
        self._advance(now)

    def next_event(self) -> float | None:
        times = []
        if self._segment is not None and not self._hung:
            times.append(self._segment.t_end)
        if self._pending_alarm is not None:
            times.append(self._pending_alarm[0])
        return min(times) if times else None

    def on_disconnect(self) -> None:
        # USB-powered board unplugged: it loses power, position and everything volatile.
        now = self.clock.monotonic()
        pos = self._position(now)
        self._offset = [p + o for p, o in zip(pos, self._offset, strict=True)]
        self._rest = (0.0, 0.0, 0.0)
        self._reset_volatile()
        self._state = "Alarm" if self.settings[22] else "Idle"
        self.forget_order()
        self._note(now)

    def on_reconnect(self) -> None:
        self._greet()

    # -- time --------------------------------------------------------------------------
    def _position(self, now: float) -> tuple[float, ...]:
        return self._segment.position(now) if self._segment is not None else self._rest

    def _speed(self, now: float) -> float:
        seg = self._segment
        if seg is None or (self._hung and seg.covered(now) >= (seg.stop_after or 0.0)):
            return 0.0  # a hung move stands at its freezing point
        return seg.speed(now)

    def _note(self, t: float) -> None:
        """Log the motion from ``t`` on (a no-op unless segment, rest or offset changed)."""
        seg, off = self._segment, tuple(self._offset)
        if seg is None:
            rest = tuple(r + o for r, o in zip(self._rest, off, strict=True))
            self._path.note(t, (None, rest), lambda _t, p=rest: p)
        else:
            self._path.note(seg.t0, (seg, off), lambda t_, s=seg, o=off: tuple(
                p + q for p, q in zip(s.position(t_), o, strict=True)))

    def _advance(self, now: float) -> None:
        while True:
            seg = self._segment
            alarm = self._pending_alarm
            if seg is not None and alarm is not None and alarm[0] <= now and alarm[0] <= seg.t_end:
                self._pending_alarm = None
                self._owed_ok = self._owed_ok or self._line_blocked()
                self._rest = seg.position(alarm[0])
                self._segment, self._current = None, None
                self._queue.clear()
                self._alarm(alarm[1])
                self._note(alarm[0])
                continue
            if seg is None or seg.t_end > now or self._hung:
                break
            t = seg.t_end
            self._rest = seg.position(t)
            self._segment = None
            if alarm is not None and alarm[0] > t:
                self._pending_alarm = None  # the move ended (stalled) before the alarm point
            if seg.kind == "hold":
                self._hold_done = not self._hold_stuck
            elif seg.kind == "softlimit":
                # The controlled stop is over: now the critical alarm [src:limits.c].
                self._queue.clear()
                self._current = None
                self._soft_limit_stop = False
                self._alarm(GrblAlarm.SOFT_LIMIT)
            elif seg.kind == "jogcancel":
                self._queue.clear()
                self._current = None
                self._state = "Idle"
            elif seg.kind == "home":
                self._finish_homing()
            else:
                self._start_next(t)
            self._note(t)
        self._process_lines(now)
        self._note(now)

    def _limits(
        self, start: tuple[float, ...], end: tuple[float, ...], feed: float | None
    ) -> tuple[float, float]:
        """(rate units/min, accel units/s^2) along the line, limited by every axis on it."""
        seg = Segment.between(start, end, 0.0, v_max=1.0, accel=1.0)
        rate = accel = float("inf")
        for i, u in enumerate(seg.unit):
            if abs(u) > 1e-12:
                rate = min(rate, self.settings[110 + i] / abs(u))
                accel = min(accel, self.settings[120 + i] / abs(u))
        if feed is not None:
            rate = min(rate, feed)
        return rate, accel

    def _start_next(self, t: float) -> None:
        while self._queue:
            block = self._queue.popleft()
            rate, accel = self._limits(self._rest, block.target, block.feed)
            if rate == float("inf") or rate <= 0:
                self._rest = block.target
                continue  # zero-length block
            slow = self.faults.take("slow_motion")
            self._slow = float(slow.get("factor", 5.0)) if slow is not None else 1.0
            seg = Segment.between(
                self._rest, block.target, t, v_max=rate / 60.0 / self._slow, accel=accel / self._slow**2,
                kind=block.kind,
            )
            stall = self.faults.take("stall")
            if stall is not None:
                seg.stop_after = float(stall.get("fraction", 0.5)) * seg.length
            hang = self.faults.take("hang")
            if hang is not None:
                seg.stop_after = float(hang.get("fraction", 0.5)) * seg.length
                self._hung = True
            fault = self.faults.take("alarm")
            if fault is not None:
                when = t + float(fault.get("at", 0.5)) * seg.profile.duration
                self._pending_alarm = (when, GrblAlarm(int(fault.get("code", 1))))
            self._segment, self._current = seg, block
            self._state = "Jog" if block.kind == "jog" else "Run"
            return
        self._segment, self._current = None, None
        if self._state in ("Run", "Jog"):
            self._state = "Idle"

    # -- real-time bytes ---------------------------------------------------------------
    def _realtime(self, b: int, now: float) -> None:
        if b == 0x18:
            self._soft_reset(now)
        elif self._critical:
            return  # only a reset gets through
        elif b == 0x3F:
            self._send_status(now)
        elif b == 0x21:
            self._feed_hold(now)
        elif b == 0x7E:
            self._cycle_start(now)
        elif b == 0x85:
            self._jog_cancel(now)
        # other extended real-time bytes (overrides, door) are ignored

    def _brake(self, now: float, kind: str) -> None:
        """Replace the current segment by its deceleration to rest."""
        seg = self._segment
        assert seg is not None
        pos, v = seg.position(now), self._speed(now)
        self._hung = False
        _, accel = self._limits(seg.start, seg.end, None)
        accel /= self._slow**2
        length = v * v / (2 * accel) if v > 0 else 0.0
        end = tuple(p + u * length for p, u in zip(pos, seg.unit, strict=True))
        self._segment = Segment(pos, end, now, Trapezoid(length, max(v, 1e-9), accel, v0=v), kind=kind)
        self._pending_alarm = None

    def _feed_hold(self, now: float) -> None:
        if self._state == "Jog":
            self._jog_cancel(now)
        elif self._state == "Run" and self._segment is not None:
            assert self._current is not None
            self._queue.appendleft(self._current)  # resume heads for the same target
            self._brake(now, "hold")
            self._state, self._hold_done = "Hold", False
            self._hold_stuck = self.faults.take("hold_stuck") is not None

    def _cycle_start(self, now: float) -> None:
        if self._state == "Hold" and self._hold_done:
            self._state, self._hold_done = "Run", False
            self._start_next(now)

    def _jog_cancel(self, now: float) -> None:
        if self._state != "Jog":
            return
        self._queue.clear()
        if self._segment is not None:
            self._brake(now, "jogcancel")
        else:
            self._state = "Idle"

    def _soft_reset(self, now: float) -> None:
        moving = self._state in ("Run", "Jog", "Home") or (self._state == "Hold" and not self._hold_done)
        homing = self._state == "Home"
        owed = self._owed_ok or self._soft_limit_stop or homing or self._line_blocked()
        self._rest = self._position(now)
        self._reset_volatile()
        if moving:
            self._state = "Alarm"
            code = GrblAlarm.HOMING_FAIL_RESET if homing else GrblAlarm.RESET_DURING_MOTION
            self._push(Alarm(code))
        elif self._state != "Alarm":
            self._state = "Idle"
        if owed:
            # The interrupted line returns to the main loop, which reports it before it
            # notices the abort [src:protocol.c protocol_main_loop].
            self._reply(Ok())
        self._greet()

    def _line_blocked(self) -> bool:
        """A complete line waits while the planner is full: the firmware is inside its
        ``mc_line``, waiting for room (the simulator keeps the line in the buffer)."""
        return self._planner_full() and (b"\n" in self._rx or b"\r" in self._rx)

    def _greet(self) -> None:
        self._reply(Banner(self.version))
        if self._state == "Alarm":
            self._push(Message(MSG_UNLOCK))

    # -- alarms --------------------------------------------------------------------------
    def _alarm(self, code: GrblAlarm) -> None:
        self._state = "Alarm"
        self._push(Alarm(code))
        if code in CRITICAL_ALARMS:
            self._critical = True
            self._push(Message(MSG_RESET_TO_CONTINUE))
        elif code in (GrblAlarm.HOMING_FAIL_PULLOFF, GrblAlarm.HOMING_FAIL_APPROACH):
            # A failed homing cycle resets the controller itself (mc_reset): $H still returns
            # STATUS_OK, so its ok comes before the banner [src:limits.c, system.c].
            self._reset_volatile()
            self._reply(Ok())
            self._greet()

    def _outside_travel(self, target: tuple[float, ...]) -> bool:
        if not self.settings[20]:
            return False
        for i, v in enumerate(target):
            travel = self.settings[130 + i]
            positive = int(self.settings[23]) >> i & 1
            lo, hi = (0.0, travel) if positive else (-travel, 0.0)
            if v < lo - 1e-9 or v > hi + 1e-9:
                return True
        return False

    # -- lines -----------------------------------------------------------------------------
    def _planner_full(self) -> bool:
        return len(self._queue) + (self._current is not None) >= PLANNER_BLOCKS

    def _motion_pending(self) -> bool:
        return self._segment is not None or self._current is not None or bool(self._queue)

    def _process_lines(self, now: float) -> None:
        while (
            not self._critical
            and not self._soft_limit_stop
            and self._state != "Home"
            and not self._planner_full()
        ):
            ends = [i for i in (self._rx.find(b"\n"), self._rx.find(b"\r")) if i >= 0]
            if not ends:
                return
            cut = min(ends) + 1
            chunk = bytes(self._rx[:cut])
            if self._motion_pending() and _G10.search(chunk.upper().replace(b" ", b"")):
                return  # an EEPROM write waits for the motion to finish [src:settings.c]
            del self._rx[:cut]
            for line in self._splitter.feed(chunk):
                self._execute(line, now)

    def _execute(self, line: DeviceLine, now: float) -> None:
        text = line.text
        if line.overflow:
            self._error(GrblError.LINE_OVERFLOW)
        elif not text:
            self._reply(Ok())
        elif text.startswith("$"):
            self._system(text, now)
        elif self._state in ("Alarm", "Jog"):
            self._error(GrblError.LOCKED)
        else:
            self._gcode(text, now)

    def _planned_end(self) -> tuple[float, ...]:
        if self._queue:
            return self._queue[-1].target
        if self._current is not None:
            return self._current.target
        return self._rest

    def work_offset(self) -> tuple[float, ...]:
        """WCO: the active (G54) offset; G92 and tool offsets are not simulated."""
        return tuple(self.coord_data[54])

    def _gcode(self, text: str, now: float) -> None:
        try:
            modal, motion = parse_block(text, self._modal, self._planned_end(), offset=self.work_offset())
        except GcodeError as exc:
            self._error(exc.code)
            return
        self._modal = modal
        if isinstance(motion, CoordWrite):
            table = self.coord_data[53 + (motion.system or 1)]
            for i, v in motion.offsets.items():
                table[i] = v
            self._wco_counter = 0  # the next report carries the new WCO [src:report.c]
            self._reply(Ok())
            return
        if motion is not None:
            if self._outside_travel(motion.target):
                self._owed_ok = True  # answered only after the reset [src:limits.c]
                if self._segment is not None and self._state == "Run":
                    # Moving: a controlled stop first (a feed hold), then the alarm.
                    self._queue.clear()
                    self._brake(now, "softlimit")
                    self._state, self._hold_done, self._soft_limit_stop = "Hold", False, True
                    return
                self._segment, self._current = None, None
                self._queue.clear()
                self._alarm(GrblAlarm.SOFT_LIMIT)
                return
            self._queue.append(_Block(motion.target, motion.feed, "run"))
            if self._segment is None and self._state in ("Idle", "Run"):
                self._start_next(now)
        self._reply(Ok())

    def _jog(self, text: str, now: float) -> None:
        if self._state not in ("Idle", "Jog"):
            self._error(GrblError.NOT_IDLE)
            return
        try:
            _, motion = parse_block(
                text[3:], self._modal, self._planned_end(), jog=True, offset=self.work_offset()
            )
        except GcodeError as exc:
            self._error(exc.code)
            return
        assert isinstance(motion, Motion)
        if self._outside_travel(motion.target):
            self._error(GrblError.JOG_TRAVEL_EXCEEDED)
            return
        self._queue.append(_Block(motion.target, motion.feed, "jog"))
        if self._segment is None:
            self._start_next(now)
        self._reply(Ok())

    def _system(self, text: str, now: float) -> None:
        if text == "$":
            self._reply(
                Feedback("HLP", "$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x"), Ok()
            )
        elif text.startswith("$J="):
            self._jog(text, now)
        elif text == "$$":
            if self._state in ("Run", "Hold"):
                self._error(GrblError.NOT_IDLE)
            else:
                self._reply(*(Setting(n, v) for n, v in sorted(self.settings.items())), Ok())
        elif text == "$G":
            m = self._modal
            feed = m.feed / 25.4 if m.inches else m.feed
            gc = f"G{m.motion} G54 G17 G{20 if m.inches else 21} G{90 if m.absolute else 91} G94 M5 M9 T0"
            self._reply(Feedback("GC", f"{gc} F{feed:g} S0"), Ok())
        elif text == "$X":
            if self._state == "Alarm":
                self._state = "Idle"
                self._reply(Message(MSG_UNLOCKED), Ok())
            else:
                self._reply(Ok())
        elif self._state not in ("Idle", "Alarm"):
            self._error(GrblError.NOT_IDLE)
        elif text == "$H":
            self._home(now)
        elif text == "$#":
            zero = "0.000,0.000,0.000"
            lines = [Feedback(f"G{n}", ",".join(f"{v:.3f}" for v in self.coord_data[n]))
                     for n in COORD_TABLES]
            self._reply(
                *lines, Feedback("G92", zero), Feedback("TLO", "0.000"), Feedback("PRB", f"{zero}:0"), Ok()
            )
        elif text == "$I":
            opts = BuildOptions("V", PLANNER_BLOCKS, RX_BUFFER_SIZE)
            self._reply(BuildInfo(f"{self.version}.{self.build}", self.build_text), opts, Ok())
        elif text.startswith("$I="):
            self.build_text = text[3:]
            self._reply(Ok())
        elif text == "$N":
            self._reply(*(StartupBlock(i, b) for i, b in sorted(self.startup_blocks.items())), Ok())
        elif re.fullmatch(r"\$N[01]=.*", text):
            self.startup_blocks[int(text[2])] = text[4:]
            self._reply(Ok())
        elif text in ("$RST=$", "$RST=#", "$RST=*"):
            if text[5] in "$*":
                self.settings = dict(self._defaults)
            if text[5] in "#*":
                self.coord_data = {n: [0.0, 0.0, 0.0] for n in COORD_TABLES}
            if text[5] == "*":  # everything GRBL keeps in EEPROM: startup lines and $I text too
                self.startup_blocks = {0: "", 1: ""}
                self.build_text = ""
            # "[MSG:Restoring defaults]", ok, then the firmware resets itself [src:system.c].
            self._reply(Message(MSG_RESTORING_DEFAULTS), Ok())
            self._soft_reset(now)
        else:
            self._write_setting(text)

    def _write_setting(self, text: str) -> None:
        m = _SETTING_WRITE.fullmatch(text)
        if m is None:
            self._error(GrblError.INVALID_STATEMENT)
            return
        try:
            number, value = int(float(m.group(1))), float(m.group(2))
        except ValueError:
            self._error(GrblError.BAD_NUMBER_FORMAT)
            return
        if number not in self.settings:
            self._error(GrblError.INVALID_STATEMENT)
        elif value < 0:
            self._error(GrblError.NEGATIVE_VALUE)
        elif number == 20 and value and not self.settings[22]:
            self._error(GrblError.SOFT_LIMITS_NEED_HOMING)
        else:
            self.settings[number] = value
            self._reply(Ok())

    # -- homing --------------------------------------------------------------------------
    def _home(self, now: float) -> None:
        if not self.settings[22]:
            self._error(GrblError.HOMING_DISABLED)
            return
        target = tuple(-self._offset[i] if self.homing_axes[i] else self._rest[i] for i in range(len(AXES)))
        rate, accel = self._limits(self._rest, target, self.settings[25])
        self._state = "Home"
        if rate == float("inf"):
            self._finish_homing()
            return
        seg = Segment.between(self._rest, target, now, v_max=rate / 60.0, accel=accel, kind="home")
        self._segment = seg
        fault = self.faults.take("alarm")
        if fault is not None:
            self._pending_alarm = (now + 0.5 * seg.profile.duration, GrblAlarm.HOMING_FAIL_APPROACH)

    def _finish_homing(self) -> None:
        rest = list(self._rest)
        for i, homed in enumerate(self.homing_axes):
            if homed:
                self._offset[i] = 0.0
                rest[i] = 0.0
        self._rest = tuple(rest)
        self._state = "Idle"
        self._reply(Ok())

    # -- replies ---------------------------------------------------------------------------
    def _state_text(self) -> str:
        if self._state == "Hold":
            return f"Hold:{0 if self._hold_done else 1}"
        return self._state

    def _send_status(self, now: float) -> None:
        pos = self._position(now)
        mask = int(self.settings[10])
        busy = self._segment is not None
        speed = self._speed(now) * 60.0
        wco = ov = None
        if self._wco_counter > 0:
            self._wco_counter -= 1
        else:
            self._wco_counter = (30 if busy else 10) - 1
            self._ov_counter = self._ov_counter or 1  # overrides on the next report
            wco = self.work_offset()
        if self._ov_counter > 0:
            self._ov_counter -= 1
        else:
            self._ov_counter = (20 if busy else 10) - 1
            ov = (100, 100, 100)
        state, _, sub = self._state_text().partition(":")
        report = StatusReport(
            state=state,
            substate=int(sub) if sub else None,
            mpos=pos if mask & 1 else None,
            wpos=None if mask & 1 else tuple(p - o for p, o in zip(pos, self.work_offset(), strict=True)),
            buffer=(
                PLANNER_BLOCKS - len(self._queue) - (self._current is not None),
                RX_BUFFER_USABLE - len(self._rx),
            )
            if mask & 2
            else None,
            feed=round(speed, 3),
            spindle=0.0,
            wco=wco,
            overrides=ov,
        )
        self._reply(report)

    def _reply(self, *events: Event) -> None:
        self.send(b"".join(format_event(e) for e in events))

    def _push(self, event: Event) -> None:
        # Unsolicited messages: not a reply the generic reply faults should eat.
        self.send(format_event(event), reply=False)

    def _error(self, code: GrblError) -> None:
        self._reply(Error(code))


def grbl_sim_for(
    name: str,
    axes: Mapping[str, Any],
    clock: Any,
    world: Any,
    faults: FaultPlan | None,
    options: Mapping[str, Any] | None = None,
) -> GrblSimulator:
    """The simulator for the GRBL device ``name`` of a rig configuration.

    ``axes`` maps roles to ``AxisConfig`` objects (``axis`` = letter); each role is
    attached to ``world`` (if given) in degrees. ``options`` (the rig file's
    ``[simulation.devices.NAME]`` table) may hold:

    - ``homing_switches`` (bool, default false): the axes have home switches and the
      controller has homing enabled (``$22=1``, so it boots locked in Alarm). False is the
      factory controller: ``$H`` answers ``error:5``.
    - ``factory_rates`` (bool, default false): keep GRBL's factory ``$110..$132`` instead of
      a controller commissioned to the rig file's speeds, accelerations and travel.
    - ``settings`` (table of ``"$N"`` or ``N`` to a number): any setting, applied last.
    - ``version`` / ``build``: what ``$I`` and the banner report.
    """
    opts = dict(options or {})
    unknown = set(opts) - {"homing_switches", "factory_rates", "settings", "version", "build"}
    if unknown:
        raise ValueError(f"unknown GRBL simulator option(s) {sorted(unknown)}")
    if not isinstance(opts.get("settings", {}), Mapping):
        raise ValueError("settings must be a table of $N = number")
    switches = bool(opts.get("homing_switches", False))
    per_axis: dict[str, GrblAxisSettings] = {}
    for ax in axes.values():
        upd = float(ax.units_per_degree)
        if opts.get("factory_rates", False):
            per_axis[ax.axis.upper()] = GrblAxisSettings(homing=switches)
        else:
            per_axis[ax.axis.upper()] = GrblAxisSettings(
                max_rate=ax.max_speed_dps * upd * 60.0,
                accel=ax.accel_dps2 * upd,
                max_travel=2.0 * max(abs(ax.min_deg), abs(ax.max_deg)) * upd,
                homing=switches,
            )
    settings: dict[int, float] = {22: 1.0} if switches else {}
    for key, value in dict(opts.get("settings", {})).items():
        try:
            settings[int(str(key).lstrip("$"))] = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"GRBL setting {key!r} = {value!r}: expected a number for $N") from None
    sim = GrblSimulator(
        name, clock, axes=per_axis, settings=settings, faults=faults,
        version=str(opts.get("version", "1.1h")), build=str(opts.get("build", "20190830")),
    )
    if world is not None:
        for role, ax in axes.items():
            # Timed: the camera asks where the stage was during an exposure already over.
            world.attach_axis(
                role, lambda t, s=sim, a=ax: s.axis_position(a.axis.upper(), t) / a.units_per_degree,
                timed=True,
            )
    return sim

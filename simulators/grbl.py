"""A GRBL 1.1 motion controller as a simulated serial device.

Sources (cited as [config], [iface], [src:FILE] below and in docs/simulators.md):
[config] the GRBL v1.1 wiki page "Grbl v1.1 Configuration" (the ``$$`` settings);
[iface] the GRBL v1.1 wiki page "Grbl v1.1 Interface" (replies, push messages, reports);
[src:FILE] the firmware source, gnea/grbl v1.1h, ``grbl/FILE``.

Its parts: this module is the controller on the wire (receive buffer, real-time bytes,
alarms, the reset sequence); ``grbl_settings`` what the board keeps in EEPROM (the ``$$``
table as data, coordinate tables, startup lines); ``grbl_motion`` the planner, the moves
and the controller state; ``grbl_commands`` the line interpreter (``$`` commands, G-code,
jogs; ``grbl_gcode`` parses the blocks); ``grbl_status`` the ``?`` report.

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
from collections.abc import Mapping
from typing import Any

from m2s2hil.protocols.grbl import (
    AXES,
    CRITICAL_ALARMS,
    MSG_RESET_TO_CONTINUE,
    MSG_UNLOCK,
    RX_BUFFER_USABLE,
    Alarm,
    Banner,
    DeviceLineSplitter,
    Event,
    GrblAlarm,
    Message,
    Ok,
    format_event,
    is_realtime,
)
from m2s2hil.simulators.device import SimDevice
from m2s2hil.simulators.fault_injection import FaultPlan
from m2s2hil.simulators.grbl_commands import GrblCommands
from m2s2hil.simulators.grbl_motion import AlarmStruck, GrblMotion, Homed
from m2s2hil.simulators.grbl_settings import GrblAxisSettings, GrblEeprom
from m2s2hil.simulators.grbl_status import StatusReports
from m2s2hil.simulators.motion_kit import InOrderReplies

_G10 = re.compile(rb"G0*10(?![0-9.])")


class GrblSimulator(InOrderReplies, SimDevice):
    """The controller on the wire: receive buffer, real-time bytes, alarms and resets; the
    parts it drives are the EEPROM (:class:`GrblEeprom`), the planner and axes
    (:class:`GrblMotion`), the line interpreter (:class:`GrblCommands`) and the status
    report (:class:`StatusReports`)."""

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
        self.eeprom = GrblEeprom(per_axis, settings or {})
        self.version, self.build = version, build
        self.rx_overflow = 0  # bytes lost to a full receive buffer
        self._motion = GrblMotion(self.eeprom, per_axis, self.faults, clock.monotonic())
        self._status = StatusReports()
        self._commands = GrblCommands(self, self.eeprom, self._motion, self._status, version, build)
        self._reset_volatile()

    def _reset_volatile(self) -> None:
        """What a reset loses on the controller's side (the motion clears its own)."""
        self._rx = bytearray()
        self._splitter = DeviceLineSplitter()
        self._critical = False
        self._owed_ok = False  # a line still executing when a critical alarm struck
        self._commands.reset()
        self._status.reset()

    # -- inspection (tests, the simulated world) -------------------------------------
    def axis_position(self, letter: str, at: float | None = None) -> float:
        """Where the axis physically is, in machine units from its home switch: now, or at
        clock time ``at`` (any moment since the last 16 motion changes; see :class:`PathLog`)."""
        i = AXES.index(letter.upper())
        with self.lock:
            now = self.clock.monotonic()
            self._advance(now)
            if at is None:
                return self._motion.physical(now)[i]
            return self._motion.physical_at(float(at))[i]

    def machine_position(self) -> tuple[float, ...]:
        """MPos as the controller would report it now."""
        with self.lock:
            now = self.clock.monotonic()
            self._advance(now)
            return self._motion.position(now)

    @property
    def state(self) -> str:
        with self.lock:
            self._advance(self.clock.monotonic())
            return self._motion.state_text()

    @property
    def settings(self) -> dict[int, float]:
        """The ``$$`` table as the board holds it."""
        return self.eeprom.settings

    @property
    def coord_data(self) -> dict[int, list[float]]:
        """The work coordinate tables (G54..G59, G28, G30), machine units."""
        return self.eeprom.coord_data

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
        self._motion.note(now)

    def poll(self, now: float) -> None:
        self._advance(now)

    def next_event(self) -> float | None:
        return self._motion.next_event()

    def on_disconnect(self) -> None:
        # USB-powered board unplugged: it loses power, position and everything volatile.
        now = self.clock.monotonic()
        self._motion.power_cycle(now)
        self._reset_volatile()
        self.forget_order()
        self._motion.note(now)

    def on_reconnect(self) -> None:
        self._greet()

    # -- time and lines ------------------------------------------------------------------
    def _advance(self, now: float) -> None:
        ended = self._motion.advance(now)
        if isinstance(ended, AlarmStruck):
            self._owed_ok = self._owed_ok or (ended.planner_full and self._line_complete())
            self.raise_alarm(ended.code)
        elif isinstance(ended, Homed):
            self.reply(Ok())
        self._process_lines(now)
        self._motion.note(now)

    def _line_complete(self) -> bool:
        return b"\n" in self._rx or b"\r" in self._rx

    def _line_blocked(self) -> bool:
        """A complete line waits while the planner is full: the firmware is inside its
        ``mc_line``, waiting for room (the simulator keeps the line in the buffer)."""
        return self._motion.planner_full() and self._line_complete()

    def _process_lines(self, now: float) -> None:
        motion = self._motion
        while (
            not self._critical
            and not motion.soft_limit_braking
            and motion.state != "Home"
            and not motion.planner_full()
        ):
            ends = [i for i in (self._rx.find(b"\n"), self._rx.find(b"\r")) if i >= 0]
            if not ends:
                return
            cut = min(ends) + 1
            chunk = bytes(self._rx[:cut])
            if motion.pending() and _G10.search(chunk.upper().replace(b" ", b"")):
                return  # an EEPROM write waits for the motion to finish [src:settings.c]
            del self._rx[:cut]
            for line in self._splitter.feed(chunk):
                self._commands.execute(line, now)

    # -- real-time bytes ---------------------------------------------------------------
    def _realtime(self, b: int, now: float) -> None:
        if b == 0x18:
            self.soft_reset(now)
        elif self._critical:
            return  # only a reset gets through
        elif b == 0x3F:
            self.reply(self._status.report(now, self._motion, self.eeprom, len(self._rx)))
        elif b == 0x21:
            self._motion.feed_hold(now)
        elif b == 0x7E:
            self._motion.cycle_start(now)
        elif b == 0x85:
            self._motion.jog_cancel(now)
        # other extended real-time bytes (overrides, door) are ignored

    # -- what the interpreter asks for (grbl_commands.Controller) --------------------------
    def soft_reset(self, now: float) -> None:
        motion = self._motion
        state = motion.state
        moving = state in ("Run", "Jog", "Home") or (state == "Hold" and not motion.hold_done)
        homing = state == "Home"
        owed = self._owed_ok or motion.soft_limit_braking or homing or self._line_blocked()
        motion.halt(now)
        self._reset_volatile()
        if moving:
            motion.state = "Alarm"
            code = GrblAlarm.HOMING_FAIL_RESET if homing else GrblAlarm.RESET_DURING_MOTION
            self._push(Alarm(code))
        elif motion.state != "Alarm":
            motion.state = "Idle"
        if owed:
            # The interrupted line returns to the main loop, which reports it before it
            # notices the abort [src:protocol.c protocol_main_loop].
            self.reply(Ok())
        self._greet()

    def raise_alarm(self, code: GrblAlarm) -> None:
        self._motion.state = "Alarm"
        self._push(Alarm(code))
        if code in CRITICAL_ALARMS:
            self._critical = True
            self._push(Message(MSG_RESET_TO_CONTINUE))
        elif code in (GrblAlarm.HOMING_FAIL_PULLOFF, GrblAlarm.HOMING_FAIL_APPROACH):
            # A failed homing cycle resets the controller itself (mc_reset): $H still returns
            # STATUS_OK, so its ok comes before the banner [src:limits.c, system.c].
            self._motion.clear()
            self._reset_volatile()
            self.reply(Ok())
            self._greet()

    def owe_ok(self) -> None:
        self._owed_ok = True

    def reply(self, *events: Event) -> None:
        self.send(b"".join(format_event(e) for e in events))

    def _push(self, event: Event) -> None:
        # Unsolicited messages: not a reply the generic reply faults should eat.
        self.send(format_event(event), reply=False)

    def _greet(self) -> None:
        self.reply(Banner(self.version))
        if self._motion.state == "Alarm":
            self._push(Message(MSG_UNLOCK))


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

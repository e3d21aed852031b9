"""The line interpreter of the simulated GRBL 1.1h: ``$`` system commands, G-code blocks
and ``$J=`` jogs, each answered ``ok`` or ``error:N`` as the firmware answers it
[src:system.c, gcode.c, settings.c; iface].

``$22=0``: ``$H`` answers ``error:5`` (setting disabled) [src:system.c]. A G0/G1 target
outside the travel with ``$20=1`` makes the firmware feed-hold to a controlled stop if it
is moving, then raise the critical ``ALARM:2``; the offending line gets its ``ok`` only
after the reset [src:limits.c limits_soft_check]. A jog target outside is ``error:15``.
``$RST=`` prints ``[MSG:Restoring defaults]`` and ``ok``, then the firmware resets itself
[src:system.c].
"""

from __future__ import annotations

import re
from typing import Protocol

from m2s2hil.protocols.grbl import (
    MSG_RESTORING_DEFAULTS,
    MSG_UNLOCKED,
    RX_BUFFER_SIZE,
    BuildInfo,
    BuildOptions,
    DeviceLine,
    Error,
    Event,
    Feedback,
    GrblAlarm,
    GrblError,
    Message,
    Ok,
    Setting,
    StartupBlock,
)
from m2s2hil.simulators.grbl_gcode import CoordWrite, GcodeError, Modal, Motion, parse_block
from m2s2hil.simulators.grbl_motion import PLANNER_BLOCKS, Block, GrblMotion
from m2s2hil.simulators.grbl_settings import COORD_TABLES, GrblEeprom
from m2s2hil.simulators.grbl_status import StatusReports

_HELP = "$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x"


class Controller(Protocol):
    """What the interpreter asks of the controller around it (the simulator)."""

    def reply(self, *events: Event) -> None: ...

    def raise_alarm(self, code: GrblAlarm) -> None: ...

    def soft_reset(self, now: float) -> None: ...

    def owe_ok(self) -> None:
        """The current line is answered only after the next reset."""


class GrblCommands:
    """Executes one complete line; keeps the G-code modal state (lost on a reset)."""

    def __init__(
        self,
        controller: Controller,
        eeprom: GrblEeprom,
        motion: GrblMotion,
        status: StatusReports,
        version: str,
        build: str,
    ) -> None:
        self._ctl, self._eeprom, self._motion, self._status = controller, eeprom, motion, status
        self._version, self._build = version, build
        self.reset()

    def reset(self) -> None:
        self._modal = Modal()

    def execute(self, line: DeviceLine, now: float) -> None:
        text = line.text
        if line.overflow:
            self._error(GrblError.LINE_OVERFLOW)
        elif not text:
            self._ctl.reply(Ok())
        elif text.startswith("$"):
            self._system(text, now)
        elif self._motion.state in ("Alarm", "Jog"):
            self._error(GrblError.LOCKED)
        else:
            self._gcode(text, now)

    def _error(self, code: GrblError) -> None:
        self._ctl.reply(Error(code))

    # -- G-code and jogs -------------------------------------------------------------------
    def _gcode(self, text: str, now: float) -> None:
        eeprom, motion = self._eeprom, self._motion
        try:
            modal, move = parse_block(text, self._modal, motion.planned_end(), offset=eeprom.work_offset())
        except GcodeError as exc:
            self._error(exc.code)
            return
        self._modal = modal
        if isinstance(move, CoordWrite):
            table = eeprom.coord_data[53 + (move.system or 1)]
            for i, v in move.offsets.items():
                table[i] = v
            self._status.wco_changed()
            self._ctl.reply(Ok())
            return
        if move is not None:
            if motion.outside_travel(move.target):
                self._ctl.owe_ok()  # answered only after the reset [src:limits.c]
                # Moving: a controlled stop first (a feed hold), then the alarm.
                if not motion.soft_limit(now):
                    self._ctl.raise_alarm(GrblAlarm.SOFT_LIMIT)
                return
            motion.plan(Block(move.target, move.feed, "run"), now)
        self._ctl.reply(Ok())

    def _jog(self, text: str, now: float) -> None:
        motion = self._motion
        if motion.state not in ("Idle", "Jog"):
            self._error(GrblError.NOT_IDLE)
            return
        try:
            _, move = parse_block(
                text[3:], self._modal, motion.planned_end(), jog=True, offset=self._eeprom.work_offset()
            )
        except GcodeError as exc:
            self._error(exc.code)
            return
        assert isinstance(move, Motion)
        if motion.outside_travel(move.target):
            self._error(GrblError.JOG_TRAVEL_EXCEEDED)
            return
        motion.plan(Block(move.target, move.feed, "jog"), now)
        self._ctl.reply(Ok())

    # -- $ commands ------------------------------------------------------------------------
    def _system(self, text: str, now: float) -> None:
        eeprom, state, reply = self._eeprom, self._motion.state, self._ctl.reply
        if text == "$":
            reply(Feedback("HLP", _HELP), Ok())
        elif text.startswith("$J="):
            self._jog(text, now)
        elif text == "$$":
            if state in ("Run", "Hold"):
                self._error(GrblError.NOT_IDLE)
            else:
                reply(*(Setting(n, v) for n, v in sorted(eeprom.settings.items())), Ok())
        elif text == "$G":
            m = self._modal
            feed = m.feed / 25.4 if m.inches else m.feed
            gc = f"G{m.motion} G54 G17 G{20 if m.inches else 21} G{90 if m.absolute else 91} G94 M5 M9 T0"
            reply(Feedback("GC", f"{gc} F{feed:g} S0"), Ok())
        elif text == "$X":
            if state == "Alarm":
                self._motion.state = "Idle"
                reply(Message(MSG_UNLOCKED), Ok())
            else:
                reply(Ok())
        elif state not in ("Idle", "Alarm"):
            self._error(GrblError.NOT_IDLE)
        elif text == "$H":
            self._home(now)
        elif text == "$#":
            zero = "0.000,0.000,0.000"
            lines = [Feedback(f"G{n}", ",".join(f"{v:.3f}" for v in eeprom.coord_data[n]))
                     for n in COORD_TABLES]
            reply(*lines, Feedback("G92", zero), Feedback("TLO", "0.000"), Feedback("PRB", f"{zero}:0"), Ok())
        elif text == "$I":
            opts = BuildOptions("V", PLANNER_BLOCKS, RX_BUFFER_SIZE)
            reply(BuildInfo(f"{self._version}.{self._build}", eeprom.build_text), opts, Ok())
        elif text.startswith("$I="):
            eeprom.build_text = text[3:]
            reply(Ok())
        elif text == "$N":
            reply(*(StartupBlock(i, b) for i, b in sorted(eeprom.startup_blocks.items())), Ok())
        elif re.fullmatch(r"\$N[01]=.*", text):
            eeprom.startup_blocks[int(text[2])] = text[4:]
            reply(Ok())
        elif text in ("$RST=$", "$RST=#", "$RST=*"):
            eeprom.restore(text[5])
            # "[MSG:Restoring defaults]", ok, then the firmware resets itself [src:system.c].
            reply(Message(MSG_RESTORING_DEFAULTS), Ok())
            self._ctl.soft_reset(now)
        else:
            error = eeprom.write_setting(text)
            reply(Ok() if error is None else Error(error))

    def _home(self, now: float) -> None:
        if not self._eeprom.settings[22]:
            self._error(GrblError.HOMING_DISABLED)
        elif self._motion.start_homing(now):
            self._ctl.reply(Ok())  # every homed axis was on its switch already

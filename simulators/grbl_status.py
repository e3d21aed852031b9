"""The ``?`` status report of the simulated GRBL 1.1h [iface, src:report.c].

``$10`` bit 0 set: MPos, else WPos (= MPos − WCO); bit 1: the ``Bf:`` field (planner
blocks and receive-buffer bytes free). ``WCO:`` rides on every 10th report (30th while
moving) [iface] and on the report after a G10 changed it; ``Ov:`` on every 10th (20th
while moving), put off to the next report when it falls on one with ``WCO:``.
"""

from __future__ import annotations

from m2s2hil.protocols.grbl import RX_BUFFER_USABLE, StatusReport
from m2s2hil.simulators.grbl_motion import PLANNER_BLOCKS, GrblMotion
from m2s2hil.simulators.grbl_settings import GrblEeprom


class StatusReports:
    """Builds the reports; keeps the firmware's WCO and override refresh counters."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._wco_counter = 0
        self._ov_counter = 0

    def wco_changed(self) -> None:
        """The next report carries the new WCO [src:report.c]."""
        self._wco_counter = 0

    def report(self, now: float, motion: GrblMotion, eeprom: GrblEeprom, rx_used: int) -> StatusReport:
        pos = motion.position(now)
        mask = int(eeprom.settings[10])
        busy = motion.segment is not None
        speed = motion.speed(now) * 60.0
        wco = ov = None
        if self._wco_counter > 0:
            self._wco_counter -= 1
        else:
            self._wco_counter = (30 if busy else 10) - 1
            self._ov_counter = self._ov_counter or 1  # overrides on the next report
            wco = eeprom.work_offset()
        if self._ov_counter > 0:
            self._ov_counter -= 1
        else:
            self._ov_counter = (20 if busy else 10) - 1
            ov = (100, 100, 100)
        state, _, sub = motion.state_text().partition(":")
        free = (PLANNER_BLOCKS - motion.planned_blocks(), RX_BUFFER_USABLE - rx_used)
        return StatusReport(
            state=state,
            substate=int(sub) if sub else None,
            mpos=pos if mask & 1 else None,
            wpos=None if mask & 1 else tuple(p - o for p, o in zip(pos, eeprom.work_offset(), strict=True)),
            buffer=free if mask & 2 else None,
            feed=round(speed, 3),
            spindle=0.0,
            wco=wco,
            overrides=ov,
        )

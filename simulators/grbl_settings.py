"""What a simulated GRBL 1.1h board keeps in EEPROM: the ``$$`` settings table, the work
coordinate tables, the ``$N`` startup lines and the ``$I`` text, and the checks the
firmware makes when a setting is written.

Sources as in :mod:`m2s2hil.simulators.grbl`: [config] the GRBL v1.1 wiki page "Grbl v1.1
Configuration"; [src:FILE] the firmware source, gnea/grbl v1.1h, ``grbl/FILE``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from m2s2hil.protocols.grbl import GrblError


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

#: The coordinate tables ``$#`` lists, in its order [iface]: G54..G59, G28, G30.
COORD_TABLES = (54, 55, 56, 57, 58, 59, 28, 30)

_SETTING_WRITE = re.compile(r"\$(\d+(?:\.\d*)?)=(.*)")


def _cleared_coords() -> dict[int, list[float]]:
    return {n: [0.0, 0.0, 0.0] for n in COORD_TABLES}


class GrblEeprom:
    """The board's non-volatile state: it survives soft resets and power cycles."""

    def __init__(self, per_axis: Sequence[GrblAxisSettings], overrides: Mapping[int, float]) -> None:
        self.settings: dict[int, float] = dict(FACTORY_SETTINGS)
        for i, ax in enumerate(per_axis):
            self.settings[100 + i] = ax.steps_per_unit
            self.settings[110 + i] = ax.max_rate
            self.settings[120 + i] = ax.accel
            self.settings[130 + i] = ax.max_travel
        unknown = set(overrides) - set(self.settings)
        if unknown:
            raise ValueError(f"GRBL 1.1 has no setting(s) {sorted(unknown)}")
        self.settings.update(overrides)
        self._defaults = dict(self.settings)  # what $RST=$ restores: this board's build
        self.build_text = ""
        self.startup_blocks = {0: "", 1: ""}
        # Work coordinate tables, machine units.
        self.coord_data: dict[int, list[float]] = _cleared_coords()

    def work_offset(self) -> tuple[float, ...]:
        """WCO: the active (G54) offset; G92 and tool offsets are not simulated."""
        return tuple(self.coord_data[54])

    def write_setting(self, text: str) -> GrblError | None:
        """``$N=value``: store it, or the error GRBL answers [src:settings.c, system.c]."""
        m = _SETTING_WRITE.fullmatch(text)
        if m is None:
            return GrblError.INVALID_STATEMENT
        try:
            number, value = int(float(m.group(1))), float(m.group(2))
        except ValueError:
            return GrblError.BAD_NUMBER_FORMAT
        if number not in self.settings:
            return GrblError.INVALID_STATEMENT
        if value < 0:
            return GrblError.NEGATIVE_VALUE
        if number == 20 and value and not self.settings[22]:
            return GrblError.SOFT_LIMITS_NEED_HOMING
        self.settings[number] = value
        return None

    def restore(self, what: str) -> None:
        """``$RST=$`` (settings), ``$RST=#`` (coordinate tables) or ``$RST=*`` (all)."""
        if what in "$*":
            self.settings = dict(self._defaults)
        if what in "#*":
            self.coord_data = _cleared_coords()
        if what == "*":  # everything GRBL keeps in EEPROM: startup lines and $I text too
            self.startup_blocks = {0: "", 1: ""}
            self.build_text = ""

"""The G-code subset the GRBL simulator executes, with GRBL 1.1's error codes.

Lines arrive cleaned by ``DeviceLineSplitter`` (upper case, no spaces or comments).
Supported: G0 G1 (motion), G90 G91, G20 G21, G53 (machine coordinates for one block),
G10 L2/L20 P0..P6 (write a work coordinate system), G17 G54 G94 (accepted, nothing to
do), F, X Y Z, N, S T (ignored), M5 M9 (no-ops), and ``$J=`` jog blocks. Anything else
GRBL knows (arcs, dwell, probing, G55..G59 selection, G92, ...) is answered ``error:20``
here: a simulator limitation, not GRBL's behaviour.

Work coordinates follow the GRBL 1.1 G-code parser (grbl/gcode.c, gnea/grbl v1.1h):
absolute targets are work positions, machine = work + WCO (G54 offset; no G92, no tool
offset here); G53 bypasses the offset. ``G10 L2 Pn`` stores the given values as the
offset of coordinate system n (P0 or no P = the active one, P1..P6 = G54..G59);
``G10 L20 Pn`` stores the offset that makes the current position read as the given
values (offset = machine position − value). Errors in gcode.c's order: no axis words
``error:26``, neither L nor P ``error:28``, P above 6 ``error:29``, an L other than 2 or
20 (a missing L reads as 0) ``error:20``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace

from m2s2hil.protocols.grbl import AXES, GrblError

MM_PER_INCH = 25.4
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")

# Modal groups of the G-codes the simulator accepts, for error:21.
_G_GROUP = {
    0: "motion",
    1: "motion",
    90: "distance",
    91: "distance",
    20: "units",
    21: "units",
    53: "non_modal",
    10: "non_modal",
    17: "plane",
    54: "wcs",
    94: "feed_mode",
}
_JOG_G = {90, 91, 20, 21, 53}


class GcodeError(Exception):
    def __init__(self, code: GrblError) -> None:
        self.code = code
        super().__init__(code.name)


@dataclass(frozen=True)
class Modal:
    absolute: bool = True
    inches: bool = False
    motion: int = 0
    feed: float = 0.0  # mm/min


@dataclass(frozen=True)
class Motion:
    target: tuple[float, ...]  # machine coordinates, mm
    feed: float | None  # mm/min; None = rapid


@dataclass(frozen=True)
class CoordWrite:
    """``G10``: new offsets (machine units) for some axes of coordinate system ``system``
    (1..6 = G54..G59; 0 = the active one)."""

    system: int
    offsets: dict[int, float]


def tokenize(text: str) -> list[tuple[str, float]]:
    """Words as (letter, value)."""
    words = []
    i = 0
    while i < len(text):
        letter = text[i]
        if not ("A" <= letter <= "Z"):
            raise GcodeError(GrblError.EXPECTED_COMMAND_LETTER)
        m = _NUMBER.match(text, i + 1)
        if m is None:
            raise GcodeError(GrblError.BAD_NUMBER_FORMAT)
        words.append((letter, float(m.group())))
        i = m.end()
    return words


def parse_block(
    text: str,
    modal: Modal,
    position: tuple[float, ...],
    *,
    jog: bool = False,
    offset: tuple[float, ...] = (0.0, 0.0, 0.0),
) -> tuple[Modal, Motion | CoordWrite | None]:
    """Execute one block's parsing: the new modal state and the motion (or offset write)
    it asks for. ``position`` is the planned machine position, ``offset`` the active work
    coordinate offset."""
    words = tokenize(text)
    groups: set[str] = set()
    g_codes: set[int] = set()
    axes: dict[int, float] = {}
    feed: float | None = None
    values: dict[str, float] = {}
    for letter, value in words:
        if letter in "FNPST" and value < 0:
            raise GcodeError(GrblError.NEGATIVE_VALUE)  # checked as each word is read (gcode.c)
        if letter == "G":
            code = int(value) if value.is_integer() else -1
            if code not in _G_GROUP or (jog and code not in _JOG_G):
                raise GcodeError(GrblError.INVALID_JOG_COMMAND if jog else GrblError.UNSUPPORTED_COMMAND)
            group = _G_GROUP[code]
            if group in groups:
                raise GcodeError(GrblError.MODAL_GROUP_VIOLATION)
            groups.add(group)
            g_codes.add(code)
        elif letter == "M":
            if jog:
                raise GcodeError(GrblError.INVALID_JOG_COMMAND)
            if value not in (5, 9):
                raise GcodeError(GrblError.UNSUPPORTED_COMMAND)
        elif letter in AXES:
            idx = AXES.index(letter)
            if idx in axes:
                raise GcodeError(GrblError.WORD_REPEATED)
            axes[idx] = value
        elif letter == "F":
            if feed is not None:
                raise GcodeError(GrblError.WORD_REPEATED)
            feed = value
        elif letter == "N":
            if not value.is_integer():
                raise GcodeError(GrblError.INVALID_LINE_NUMBER)
        elif letter in "ST" and not jog:
            continue
        elif letter in "LP" and not jog:
            if letter in values:
                raise GcodeError(GrblError.WORD_REPEATED)
            values[letter] = value
        else:
            raise GcodeError(GrblError.INVALID_JOG_COMMAND if jog else GrblError.UNUSED_WORDS)

    absolute = False if 91 in g_codes else True if 90 in g_codes else modal.absolute
    inches = True if 20 in g_codes else False if 21 in g_codes else modal.inches
    scale = MM_PER_INCH if inches else 1.0
    motion = 0 if 0 in g_codes else 1 if 1 in g_codes else modal.motion
    feed_mm = feed * scale if feed is not None else None
    if jog:
        # A jog leaves the parser's modal state as it was; it must carry its own feed.
        if feed_mm is None:
            raise GcodeError(GrblError.UNDEFINED_FEED_RATE)
        if not axes:
            raise GcodeError(GrblError.NO_AXIS_WORDS)
        return modal, Motion(_target(axes, position, absolute, 53 in g_codes, scale, offset), feed_mm)

    if 10 in g_codes:
        return modal, _coord_write(values, axes, position, scale, explicit_motion=bool(g_codes & {0, 1}))
    if values:
        raise GcodeError(GrblError.UNUSED_WORDS)
    new = replace(modal, absolute=absolute, inches=inches, motion=motion)
    if feed_mm is not None:
        new = replace(new, feed=feed_mm)
    if 53 in g_codes and motion not in (0, 1):
        raise GcodeError(GrblError.G53_INVALID_MOTION_MODE)
    if not axes:
        return new, None  # G0/G1 alone only sets the motion mode, as in GRBL
    if motion == 1 and new.feed <= 0:
        raise GcodeError(GrblError.UNDEFINED_FEED_RATE)
    target = _target(axes, position, absolute, 53 in g_codes, scale, offset)
    return new, Motion(target, None if motion == 0 else new.feed)


def _coord_write(
    values: dict[str, float],
    axes: dict[int, float],
    position: tuple[float, ...],
    scale: float,
    *,
    explicit_motion: bool,
) -> CoordWrite:
    # The checks in the order of gcode.c's NON_MODAL_SET_COORDINATE_DATA: a missing L reads as
    # L0 (unsupported), a missing P as P0 (the active system).
    if explicit_motion:
        raise GcodeError(GrblError.AXIS_COMMAND_CONFLICT)  # G10 and G0/G1 both want the axis words
    if not axes:
        raise GcodeError(GrblError.NO_AXIS_WORDS)
    if "L" not in values and "P" not in values:
        raise GcodeError(GrblError.VALUE_WORD_MISSING)
    system, mode = int(values.get("P", 0.0)), values.get("L", 0.0)
    if system > 6:
        raise GcodeError(GrblError.UNSUPPORTED_COORD_SYSTEM)
    if mode not in (2.0, 20.0):
        raise GcodeError(GrblError.UNSUPPORTED_COMMAND)
    if mode == 2:
        return CoordWrite(system, {i: v * scale for i, v in axes.items()})
    return CoordWrite(system, {i: position[i] - v * scale for i, v in axes.items()})


def _target(
    axes: dict[int, float],
    position: tuple[float, ...],
    absolute: bool,
    machine: bool,
    scale: float,
    offset: tuple[float, ...] = (0.0, 0.0, 0.0),
) -> tuple[float, ...]:
    out = list(position)
    for idx, value in axes.items():
        v = value * scale
        if machine:
            out[idx] = v
        elif absolute:
            out[idx] = v + offset[idx]
        else:
            out[idx] = position[idx] + v
    return tuple(out)

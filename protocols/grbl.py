"""GRBL 1.1 serial protocol, sans-I/O.

Host side: :class:`GrblReceiver` turns the controller's bytes into typed events
(feed it any split of the stream); ``encode_*`` build command lines and
:class:`Realtime` holds the single-byte real-time commands; :class:`CharacterCounter`
does GRBL's character-counting flow control for its 128-byte receive buffer.

Device side (for the simulator): :func:`is_realtime` picks real-time bytes out of the
stream as GRBL's serial interrupt does, :class:`DeviceLineSplitter` assembles the
remaining bytes into cleaned lines, and ``format_event`` writes any event back as
the bytes GRBL sends.

Garbage policy: the receiver never raises on device bytes. A line that is not valid
GRBL output (non-ASCII bytes, an unknown line, a malformed status report or a line
longer than ``max_line`` bytes) yields a :class:`ProtocolViolation` event holding the
offending bytes; the stream continues with the next line. ``CodecError`` is raised
only for bad *arguments* to the encoders and for a line that cannot fit the buffer.
"""

from __future__ import annotations

import enum
import math
import re
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

from m2s2hil.protocols.errors import CodecError

RX_BUFFER_SIZE = 128
RX_BUFFER_USABLE = RX_BUFFER_SIZE - 1  # the ring buffer always keeps one slot free
LINE_BUFFER_SIZE = 80  # GRBL stores at most LINE_BUFFER_SIZE - 1 characters of a line
AXES = "XYZ"


class GrblError(enum.IntEnum):
    """``error:N`` codes of GRBL 1.1."""

    EXPECTED_COMMAND_LETTER = 1
    BAD_NUMBER_FORMAT = 2
    INVALID_STATEMENT = 3
    NEGATIVE_VALUE = 4
    HOMING_DISABLED = 5  # "setting disabled": $H with $22=0
    STEP_PULSE_TOO_SHORT = 6
    SETTINGS_READ_FAIL = 7
    NOT_IDLE = 8
    LOCKED = 9  # G-code locked out during alarm or jog
    SOFT_LIMITS_NEED_HOMING = 10
    LINE_OVERFLOW = 11
    STEP_RATE_EXCEEDED = 12
    CHECK_DOOR = 13
    STARTUP_LINE_TOO_LONG = 14
    JOG_TRAVEL_EXCEEDED = 15
    INVALID_JOG_COMMAND = 16
    LASER_MODE_NEEDS_PWM = 17
    UNSUPPORTED_COMMAND = 20
    MODAL_GROUP_VIOLATION = 21
    UNDEFINED_FEED_RATE = 22
    VALUE_NOT_INTEGER = 23
    AXIS_COMMAND_CONFLICT = 24
    WORD_REPEATED = 25
    NO_AXIS_WORDS = 26
    INVALID_LINE_NUMBER = 27
    VALUE_WORD_MISSING = 28
    UNSUPPORTED_COORD_SYSTEM = 29
    G53_INVALID_MOTION_MODE = 30
    AXIS_WORDS_EXIST = 31
    NO_AXIS_WORDS_IN_PLANE = 32
    INVALID_TARGET = 33
    ARC_RADIUS_ERROR = 34
    NO_OFFSETS_IN_PLANE = 35
    UNUSED_WORDS = 36
    G43_DYNAMIC_AXIS_ERROR = 37
    TOOL_NUMBER_EXCEEDED = 38


class GrblAlarm(enum.IntEnum):
    """``ALARM:N`` codes of GRBL 1.1."""

    HARD_LIMIT = 1
    SOFT_LIMIT = 2
    RESET_DURING_MOTION = 3
    PROBE_FAIL_INITIAL = 4
    PROBE_FAIL_CONTACT = 5
    HOMING_FAIL_RESET = 6
    HOMING_FAIL_DOOR = 7
    HOMING_FAIL_PULLOFF = 8
    HOMING_FAIL_APPROACH = 9
    HOMING_FAIL_DUAL_APPROACH = 10


#: Alarms after which GRBL blocks everything until a soft reset ("Reset to continue").
CRITICAL_ALARMS = frozenset({GrblAlarm.HARD_LIMIT, GrblAlarm.SOFT_LIMIT})

MSG_RESET_TO_CONTINUE = "Reset to continue"
MSG_UNLOCK = "'$H'|'$X' to unlock"
MSG_UNLOCKED = "Caution: Unlocked"
MSG_RESTORING_DEFAULTS = "Restoring defaults"  # after $RST=..., before the firmware resets itself
#: Settings GRBL prints as integers (masks, booleans, microseconds); the rest get 3 decimals.
INTEGER_SETTINGS = frozenset({0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 30, 31, 32})
STATE_NAMES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")


def _code(enum_type: type[enum.IntEnum], n: int) -> enum.IntEnum | int:
    try:
        return enum_type(n)
    except ValueError:
        return n  # a code this table does not know (newer firmware): keep the number


# -- events ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ok:
    pass


@dataclass(frozen=True)
class Error:
    code: GrblError | int


@dataclass(frozen=True)
class Alarm:
    code: GrblAlarm | int

    @property
    def critical(self) -> bool:
        return self.code in CRITICAL_ALARMS


@dataclass(frozen=True)
class Banner:
    version: str  # "1.1h"
    help_text: str = "'$' for help"


@dataclass(frozen=True)
class Message:
    text: str


@dataclass(frozen=True)
class BuildInfo:
    """``[VER:1.1h.20190830:user text]``."""

    version: str
    text: str = ""


@dataclass(frozen=True)
class BuildOptions:
    """``[OPT:V,15,128]``: option letters, planner blocks, receive-buffer bytes."""

    codes: str
    planner_blocks: int | None = None
    rx_buffer: int | None = None


@dataclass(frozen=True)
class Setting:
    number: int
    value: float


@dataclass(frozen=True)
class StartupBlock:
    """``$N0=...``: a stored startup line."""

    index: int
    block: str


@dataclass(frozen=True)
class StartupExecuted:
    """``>G20:ok``: a startup line GRBL ran after reset, with its result."""

    block: str
    result: str


@dataclass(frozen=True)
class Feedback:
    """Any other ``[TAG:...]`` line (``GC``, ``HLP``, ``G54``, ``PRB``, ``echo`` ...)."""

    tag: str
    text: str


@dataclass(frozen=True)
class StatusReport:
    state: str  # one of STATE_NAMES
    substate: int | None = None  # Hold:0/1, Door:0..3
    mpos: tuple[float, ...] | None = None
    wpos: tuple[float, ...] | None = None
    wco: tuple[float, ...] | None = None
    feed: float | None = None
    spindle: float | None = None
    pins: str | None = None
    overrides: tuple[int, int, int] | None = None
    buffer: tuple[int, int] | None = None  # planner blocks free, RX bytes free
    line_number: int | None = None
    accessories: str | None = None
    extra: tuple[tuple[str, str], ...] = field(default=())

    @property
    def state_text(self) -> str:
        return self.state if self.substate is None else f"{self.state}:{self.substate}"

    @property
    def moving(self) -> bool:
        return self.state in ("Run", "Jog", "Home") or (self.state == "Hold" and self.substate == 1)

    def machine_position(self, wco: tuple[float, ...] | None = None) -> tuple[float, ...] | None:
        """MPos, or WPos + WCO when the controller reports work coordinates."""
        if self.mpos is not None:
            return self.mpos
        offset = self.wco if self.wco is not None else wco
        if self.wpos is None or offset is None:
            return None
        return tuple(w + o for w, o in zip(self.wpos, offset, strict=False))


@dataclass(frozen=True)
class ProtocolViolation:
    line: bytes
    reason: str


Event = (
    Ok
    | Error
    | Alarm
    | Banner
    | Message
    | BuildInfo
    | BuildOptions
    | Setting
    | StartupBlock
    | StartupExecuted
    | Feedback
    | StatusReport
    | ProtocolViolation
)


# -- host side: receiver -----------------------------------------------------------------
class GrblReceiver:
    """Bytes from the controller in, events out; tolerant of any split and any garbage."""

    def __init__(self, max_line: int = 256) -> None:
        self.max_line = max_line
        self._buf = bytearray()
        self._skipping = False  # inside an over-long line: drop bytes up to its newline

    @property
    def partial(self) -> bytes:
        """Bytes of a line not yet terminated."""
        return bytes(self._buf)

    def clear(self) -> None:
        """Forget a partial line (after a timeout the rest of it may never come)."""
        self._buf.clear()
        self._skipping = False

    def feed(self, data: bytes) -> list[Event]:
        self._buf += data
        events: list[Event] = []
        while True:
            nl = self._buf.find(b"\n")
            if self._skipping:
                if nl < 0:
                    self._buf.clear()
                    break
                del self._buf[: nl + 1]
                self._skipping = False
                continue
            if nl < 0 or nl > self.max_line:
                if len(self._buf) > self.max_line:
                    head = bytes(self._buf[: self.max_line])
                    events.append(ProtocolViolation(head, f"line over {self.max_line} bytes"))
                    del self._buf[: self.max_line]
                    self._skipping = True
                    continue
                break
            line = bytes(self._buf[:nl])
            del self._buf[: nl + 1]
            event = parse_line(line)
            if event is not None:
                events.append(event)
        return events


_BANNER = re.compile(r"Grbl(?:HAL)? (\S+) \[(.*)\]")
_SETTING = re.compile(r"\$(\d+)=(\S+)")
_STARTUP = re.compile(r"\$N(\d+)=(.*)")


def parse_line(line: bytes) -> Event | None:
    """One line without its newline; None for a blank line."""
    raw = line
    line = line.rstrip(b"\r")
    if not line:
        return None
    if any(b < 0x20 or b > 0x7E for b in line):
        return ProtocolViolation(raw, "non-printable or non-ASCII bytes")
    text = line.decode("ascii")
    try:
        event = _parse_text(text)
    except ValueError as exc:
        return ProtocolViolation(raw, str(exc))
    return event if event is not None else ProtocolViolation(raw, "unrecognised line")


def _parse_text(text: str) -> Event | None:
    if text == "ok":
        return Ok()
    if text.startswith("error:"):
        return Error(_code(GrblError, _int(text[6:])))
    if text.startswith("ALARM:"):
        return Alarm(_code(GrblAlarm, _int(text[6:])))
    if text.startswith("<") and text.endswith(">"):
        return parse_status(text[1:-1])
    if text.startswith("[") and text.endswith("]"):
        return _parse_bracket(text[1:-1])
    m = _BANNER.fullmatch(text)
    if m:
        return Banner(m.group(1), m.group(2))
    m = _STARTUP.fullmatch(text)
    if m:
        return StartupBlock(int(m.group(1)), m.group(2))
    m = _SETTING.fullmatch(text)
    if m:
        return Setting(int(m.group(1)), _float(m.group(2)))
    if text.startswith(">") and ":" in text:
        block, _, result = text[1:].partition(":")
        return StartupExecuted(block, result)
    return None


def _int(s: str) -> int:
    if not s.isdigit():
        raise ValueError(f"bad integer {s!r}")
    return int(s)


def _float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise ValueError(f"bad number {s!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"bad number {s!r}")
    return v


def _floats(s: str) -> tuple[float, ...]:
    return tuple(_float(p) for p in s.split(","))


def _parse_bracket(body: str) -> Event:
    tag, sep, rest = body.partition(":")
    if not sep or not tag:
        raise ValueError("feedback line without TAG:")
    if tag == "MSG":
        return Message(rest)
    if tag == "VER":
        version, _, extra = rest.partition(":")
        return BuildInfo(version, extra)
    if tag == "OPT":
        parts = rest.split(",")
        nums = [_int(p) for p in parts[1:3]]
        return BuildOptions(parts[0], *nums)
    return Feedback(tag, rest)


def parse_status(body: str) -> StatusReport:
    """The inside of ``<...>``; ValueError if malformed."""
    fields = body.split("|")
    name, _, sub = fields[0].partition(":")
    if name not in STATE_NAMES:
        raise ValueError(f"unknown state {fields[0]!r}")
    kw: dict[str, object] = {"state": name, "substate": _int(sub) if sub else None}
    extra: list[tuple[str, str]] = []
    for f in fields[1:]:
        key, sep, value = f.partition(":")
        if not sep:
            raise ValueError(f"status field without ':' {f!r}")
        if key in ("MPos", "WPos", "WCO"):
            kw[key.lower()] = _floats(value)
        elif key == "FS":
            feed, spindle = _floats(value)
            kw["feed"], kw["spindle"] = feed, spindle
        elif key == "F":
            kw["feed"] = _float(value)
        elif key == "Pn":
            kw["pins"] = value
        elif key == "Ov":
            a, b, c = (_int(p) for p in value.split(","))
            kw["overrides"] = (a, b, c)
        elif key == "Bf":
            blocks, rx = (_int(p) for p in value.split(","))
            kw["buffer"] = (blocks, rx)
        elif key == "Ln":
            kw["line_number"] = _int(value)
        elif key == "A":
            kw["accessories"] = value
        else:
            extra.append((key, value))
    if "mpos" not in kw and "wpos" not in kw:
        raise ValueError("status report without MPos or WPos")
    return StatusReport(**kw, extra=tuple(extra))  # type: ignore[arg-type]


# -- host side: encoders -----------------------------------------------------------------
class Realtime:
    """Single bytes GRBL acts on at once, without a newline and outside the buffer."""

    STATUS = b"?"
    FEED_HOLD = b"!"
    CYCLE_START = b"~"
    SOFT_RESET = b"\x18"
    SAFETY_DOOR = b"\x84"
    JOG_CANCEL = b"\x85"


HOME = "$H"
UNLOCK = "$X"
BUILD_INFO = "$I"
SETTINGS = "$$"
PARSER_STATE = "$G"


def encode_line(text: str) -> bytes:
    """A command line with its newline; CodecError for what GRBL would mangle."""
    if not text.isascii() or any(c in text for c in "\r\n?!~") or any(ord(c) < 0x20 for c in text):
        raise CodecError(f"not a GRBL line: {text!r}", text.encode("utf-8", "replace"))
    stored = sum(1 for c in text if c > " ")
    if stored > LINE_BUFFER_SIZE - 1:
        raise CodecError(f"line of {stored} characters exceeds GRBL's {LINE_BUFFER_SIZE - 1}", text.encode())
    return text.encode("ascii") + b"\n"


def fmt_number(v: float, decimals: int = 4) -> str:
    if not math.isfinite(v):
        raise CodecError(f"not a finite number: {v!r}")
    s = f"{v:.{decimals}f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _axis_words(axes: Mapping[str, float]) -> str:
    if not axes:
        raise CodecError("no axis words")
    words = []
    for letter, v in axes.items():
        if letter not in AXES:
            raise CodecError(f"unknown axis {letter!r}")
        words.append(f"{letter}{fmt_number(v)}")
    return " ".join(words)


def move_line(
    axes: Mapping[str, float],
    *,
    feed: float | None = None,
    incremental: bool = False,
    machine: bool = False,
) -> str:
    """``G90 G0 X..`` (rapid, no feed) or ``G90 G1 X.. F..``; ``machine`` adds G53."""
    if feed is not None and not feed > 0:
        raise CodecError(f"feed must be positive, got {feed}")
    if machine and incremental:
        raise CodecError("G53 moves are absolute")
    parts = ["G91" if incremental else "G90"]
    if machine:
        parts.append("G53")
    parts.append("G0" if feed is None else "G1")
    parts.append(_axis_words(axes))
    if feed is not None:
        parts.append(f"F{fmt_number(feed, 3)}")
    return " ".join(parts)


def jog_line(
    axes: Mapping[str, float], *, feed: float, incremental: bool = True, machine: bool = False
) -> str:
    """``$J=G91 X-5 F600``; ``machine`` jogs to a G53 machine position."""
    if not feed > 0:
        raise CodecError(f"jog feed must be positive, got {feed}")
    mode = "G53" if machine else ("G91" if incremental else "G90")
    return f"$J={mode} {_axis_words(axes)} F{fmt_number(feed, 3)}"


def setting_line(number: int, value: float) -> str:
    if number < 0:
        raise CodecError(f"bad setting number {number}")
    return f"${number}={fmt_number(value, 3)}"


def encode_move(axes: Mapping[str, float], **kw: object) -> bytes:
    return encode_line(move_line(axes, **kw))  # type: ignore[arg-type]


# -- host side: flow control -------------------------------------------------------------
class BufferFull(CodecError):
    """The line would overflow GRBL's receive buffer: wait for an ok/error first."""


class CharacterCounter:
    """GRBL's character-counting streaming: bytes sent whose ok/error has not come back.

    GRBL drops bytes that arrive with its receive buffer full, so a sender may only
    write a line if the unacknowledged bytes plus the line fit ``capacity``. Replies come
    strictly in order, so each ok/error retires the oldest line.
    """

    def __init__(self, capacity: int = RX_BUFFER_USABLE) -> None:
        self.capacity = capacity
        self._lines: deque[int] = deque()
        self.outstanding = 0

    @property
    def in_flight(self) -> int:
        return len(self._lines)

    def fits(self, line: bytes) -> bool:
        return self.outstanding + len(line) <= self.capacity

    def sent(self, line: bytes) -> None:
        if len(line) > self.capacity:
            raise BufferFull(f"a {len(line)}-byte line can never fit a {self.capacity}-byte buffer", line)
        if not self.fits(line):
            raise BufferFull(
                f"{len(line)} bytes would overflow: {self.outstanding} of {self.capacity} outstanding", line
            )
        self._lines.append(len(line))
        self.outstanding += len(line)

    def acknowledged(self) -> int:
        """An ok or error arrived: retire the oldest line and return its length."""
        if not self._lines:
            raise CodecError("ok/error with no line outstanding")
        n = self._lines.popleft()
        self.outstanding -= n
        return n

    def reset(self) -> None:
        """After a soft reset GRBL has flushed its buffer: nothing is outstanding."""
        self._lines.clear()
        self.outstanding = 0


# -- device side -------------------------------------------------------------------------
def is_realtime(byte: int) -> bool:
    """Bytes GRBL's serial interrupt takes out of the stream (never buffered)."""
    return byte in (0x3F, 0x21, 0x7E, 0x18) or byte > 0x7F


@dataclass(frozen=True)
class DeviceLine:
    """A line as GRBL's main loop sees it: no whitespace, comments removed, upper case."""

    text: str
    overflow: bool = False


class DeviceLineSplitter:
    """Assembles buffered (non-real-time) bytes into lines as GRBL 1.1 does.

    ``\\r`` and ``\\n`` each end a line, so ``\\r\\n`` gives a line and then an empty
    one (GRBL answers ``ok`` to both). Whitespace and control bytes are dropped,
    letters upper-cased, ``(...)`` and ``;`` comments removed; a line longer than
    ``LINE_BUFFER_SIZE - 1`` characters is flagged as overflowing.
    """

    def __init__(self) -> None:
        self._chars: list[str] = []
        self._overflow = False
        self._paren = False
        self._semicolon = False

    def feed(self, data: bytes) -> list[DeviceLine]:
        lines: list[DeviceLine] = []
        for b in data:
            c = chr(b)
            if c in "\r\n":
                lines.append(DeviceLine("".join(self._chars), self._overflow))
                self._chars, self._overflow, self._paren, self._semicolon = [], False, False, False
            elif self._paren:
                self._paren = c != ")"
            elif self._semicolon or b <= 0x20 or b > 0x7E:
                continue
            elif c == "(":
                self._paren = True
            elif c == ";":
                self._semicolon = True
            elif len(self._chars) >= LINE_BUFFER_SIZE - 1:
                self._overflow = True
            else:
                self._chars.append(c.upper())
        return lines


def format_event(event: Event) -> bytes:
    """The bytes GRBL sends for ``event`` (used by the simulator and round-trip tests)."""
    return _format_text(event).encode("ascii") + b"\r\n"


def _fmt_axes(values: tuple[float, ...]) -> str:
    return ",".join(f"{v:.3f}" for v in values)


def _fmt_rate(v: float) -> str:
    return f"{v:.0f}" if float(v).is_integer() else f"{v:.3f}".rstrip("0").rstrip(".")


def format_status(r: StatusReport) -> str:
    parts = [r.state_text]
    if r.mpos is not None:
        parts.append(f"MPos:{_fmt_axes(r.mpos)}")
    if r.wpos is not None:
        parts.append(f"WPos:{_fmt_axes(r.wpos)}")
    if r.buffer is not None:
        parts.append(f"Bf:{r.buffer[0]},{r.buffer[1]}")
    if r.line_number is not None:
        parts.append(f"Ln:{r.line_number}")
    if r.feed is not None and r.spindle is not None:
        parts.append(f"FS:{_fmt_rate(r.feed)},{_fmt_rate(r.spindle)}")
    elif r.feed is not None:
        parts.append(f"F:{_fmt_rate(r.feed)}")
    if r.pins:
        parts.append(f"Pn:{r.pins}")
    if r.wco is not None:
        parts.append(f"WCO:{_fmt_axes(r.wco)}")
    if r.overrides is not None:
        parts.append("Ov:" + ",".join(str(o) for o in r.overrides))
    if r.accessories:
        parts.append(f"A:{r.accessories}")
    parts.extend(f"{k}:{v}" for k, v in r.extra)
    return "<" + "|".join(parts) + ">"


def _format_text(e: Event) -> str:
    match e:
        case Ok():
            return "ok"
        case Error(code):
            return f"error:{int(code)}"
        case Alarm(code):
            return f"ALARM:{int(code)}"
        case Banner(version, help_text):
            return f"\r\nGrbl {version} [{help_text}]"
        case Message(text):
            return f"[MSG:{text}]"
        case BuildInfo(version, text):
            return f"[VER:{version}:{text}]"
        case BuildOptions(codes, blocks, rx):
            return f"[OPT:{codes}" + "".join(f",{n}" for n in (blocks, rx) if n is not None) + "]"
        case Setting(number, value):
            shown = f"{value:.0f}" if number in INTEGER_SETTINGS else f"{value:.3f}"
            return f"${number}={shown}"
        case StartupBlock(index, block):
            return f"$N{index}={block}"
        case StartupExecuted(block, result):
            return f">{block}:{result}"
        case Feedback(tag, text):
            return f"[{tag}:{text}]"
        case StatusReport():
            return format_status(e)
    raise CodecError(f"cannot format {e!r}")

"""Zaber ASCII protocol, sans-I/O.

Host → device: ``/addr axis [id] command [data][:CC]\\n``. Device → host: replies
``@01 1 [id] OK|RJ IDLE|BUSY <flag> <data>[:CC]``, info lines ``#01 1 [id] text``
and alerts ``!01 1 IDLE <flag>``, each ending ``\\r\\n``. The checksum is
256 − (sum of the bytes between the leading character and the ``:``) mod 256, as two
hex digits: ``/1 1 00 get pos:2C``.

Host side: :func:`encode_command` and :class:`ZaberReceiver` (feed it any split; it
yields :class:`Reply`, :class:`Info`, :class:`Alert`). Device side (the simulator):
:class:`CommandParser` and :func:`format_reply`.

Garbage policy (both directions): never raise on received bytes. A line with a wrong
checksum yields :class:`ChecksumMismatch`; any other malformed line yields
:class:`ProtocolViolation` (ChecksumMismatch is a subclass). ``CodecError`` is raised
only for bad arguments to the encoders. Continuation packets of firmware 7 (messages
split with a trailing ``\\``) are not assembled: they come out as separate lines.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable
from dataclasses import dataclass

from m2s2hil.protocols.errors import CodecError

MAX_MESSAGE_ID = 99
NO_FLAG = "--"

# Unit conversions of the data fields (firmware 6/7 ASCII).
VELOCITY_DATA_PER_USTEP_S = 1.6384  # speed data = microsteps/s × 1.6384
ACCEL_DATA_PER_USTEP_S2 = 1.6384 / 10000  # accel data = microsteps/s² × 1.6384 / 10000


class WarningFlag(enum.Enum):
    """Two-letter flags, in precedence order within each class (F faults > W warnings > N notes)."""

    FD = "driver disabled"
    FQ = "encoder error"
    FS = "stalled and stopped"
    FT = "excessive twist"
    FB = "stream bounds error"
    FP = "interpolated path deviation"
    FE = "limit error"
    FO = "overdrive limit exceeded"
    WL = "unexpected limit trigger"
    WV = "voltage out of range"
    WT = "system temperature high"
    WM = "displaced when stationary"
    WR = "no reference position"
    NC = "manual control"
    NI = "command interrupted"
    ND = "stream discontinuity"
    NU = "setting update pending"
    NJ = "joystick calibrating"


_ORDER = {f.name: i for i, f in enumerate(WarningFlag)}


def flag_rank(code: str) -> tuple[int, int]:
    """Sort key: faults first, then warnings, then notes; known codes in table order."""
    kind = code[:1]
    return ("FWN".index(kind) if kind and kind in "FWN" else 3, _ORDER.get(code, len(_ORDER)))


def highest_flag(codes: Iterable[str]) -> str:
    codes = [c for c in codes if c and c != NO_FLAG]
    return min(codes, key=flag_rank) if codes else NO_FLAG


def is_fault(code: str) -> bool:
    return code.startswith("F")


class RejectReason(enum.Enum):
    """Data of an ``RJ`` reply."""

    AGAIN = "AGAIN"
    BADAXIS = "BADAXIS"
    BADCOMMAND = "BADCOMMAND"
    BADDATA = "BADDATA"
    BADMESSAGEID = "BADMESSAGEID"
    DEVICEONLY = "DEVICEONLY"
    FULL = "FULL"
    LOCKSTEP = "LOCKSTEP"
    NOACCESS = "NOACCESS"
    PARKED = "PARKED"
    STATUSBUSY = "STATUSBUSY"


def checksum(body: bytes) -> int:
    return (256 - sum(body) % 256) % 256


def _verify(line: bytes) -> tuple[bytes, bool | None]:
    """(body without ``:CC``, checksum ok / None if the line carries none); body excludes the lead byte."""
    if len(line) >= 4 and line[-3:-2] == b":" and all(c in b"0123456789abcdefABCDEF" for c in line[-2:]):
        body = line[1:-3]
        return body, (sum(body) + int(line[-2:], 16)) % 256 == 0
    return line[1:], None


# -- messages ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Command:
    address: int | None = None  # None: "/" alone, all devices
    axis: int | None = None  # 0 = the device itself / all its axes
    message_id: int | None = None
    text: str = ""  # "get pos", "move abs 1000", "" = status poll


@dataclass(frozen=True)
class Reply:
    address: int
    axis: int
    message_id: int | None
    flag: str  # "OK" | "RJ"
    status: str  # "IDLE" | "BUSY"
    warning: str  # "--" or the highest-priority two-letter code
    data: str

    @property
    def rejected(self) -> bool:
        return self.flag == "RJ"

    @property
    def busy(self) -> bool:
        return self.status == "BUSY"

    @property
    def fault(self) -> bool:
        return is_fault(self.warning)


@dataclass(frozen=True)
class Info:
    address: int
    axis: int
    message_id: int | None
    text: str


@dataclass(frozen=True)
class Alert:
    address: int
    axis: int
    status: str
    warning: str
    data: str = ""


@dataclass(frozen=True)
class ProtocolViolation:
    line: bytes
    reason: str


@dataclass(frozen=True)
class ChecksumMismatch(ProtocolViolation):
    pass


Event = Reply | Info | Alert | ProtocolViolation


# -- host side ---------------------------------------------------------------------------
def _check_text(text: str) -> None:
    if not text.isascii() or any(c in text for c in "/:\r\n@#!\\") or any(ord(c) < 0x20 for c in text):
        raise CodecError(f"not a Zaber command: {text!r}", text.encode("utf-8", "replace"))


def encode_command(cmd: Command, *, with_checksum: bool = True) -> bytes:
    parts: list[str] = []
    if cmd.address is not None:
        if not 0 <= cmd.address <= 99:
            raise CodecError(f"device address {cmd.address} outside 0..99")
        parts.append(str(cmd.address))
    if cmd.axis is not None:
        if cmd.address is None or not 0 <= cmd.axis <= 9:
            raise CodecError(f"axis {cmd.axis} needs an address and must be 0..9")
        parts.append(str(cmd.axis))
    if cmd.message_id is not None:
        if cmd.axis is None or not 0 <= cmd.message_id <= MAX_MESSAGE_ID:
            raise CodecError(f"message id {cmd.message_id} needs an axis and must be 0..{MAX_MESSAGE_ID}")
        parts.append(f"{cmd.message_id:02d}")
    _check_text(cmd.text)
    text = " ".join(cmd.text.split())
    if text:
        if text[0].isdigit() or text[0] in "+-":
            raise CodecError(f"a command starts with a letter: {text!r}")
        parts.append(text)
    body = " ".join(parts).encode("ascii")
    if with_checksum:
        body += b":%02X" % checksum(body)
    return b"/" + body + b"\n"


class _Lines:
    """Splits a byte stream into lines; over-long lines become violations (split-invariant)."""

    def __init__(self, max_line: int) -> None:
        self.max_line = max_line
        self._buf = bytearray()
        self._skipping = False

    def clear(self) -> None:
        self._buf.clear()
        self._skipping = False

    def feed(self, data: bytes) -> list[bytes | ProtocolViolation]:
        self._buf += data
        out: list[bytes | ProtocolViolation] = []
        while True:
            ends = [i for i in (self._buf.find(b"\n"), self._buf.find(b"\r")) if i >= 0]
            end = min(ends) if ends else -1
            if self._skipping:
                if end < 0:
                    self._buf.clear()
                    break
                del self._buf[: end + 1]
                self._skipping = False
                continue
            if end < 0 or end > self.max_line:
                if len(self._buf) > self.max_line:
                    head = bytes(self._buf[: self.max_line])
                    out.append(ProtocolViolation(head, f"line over {self.max_line} bytes"))
                    del self._buf[: self.max_line]
                    self._skipping = True
                    continue
                break
            line = bytes(self._buf[:end])
            del self._buf[: end + 1]
            if line:
                out.append(line)
        return out


class ZaberReceiver:
    """Device bytes in, events out."""

    def __init__(self, max_line: int = 256) -> None:
        self._lines = _Lines(max_line)

    def clear(self) -> None:
        self._lines.clear()

    def feed(self, data: bytes) -> list[Event]:
        events: list[Event] = []
        for item in self._lines.feed(data):
            events.append(item if isinstance(item, ProtocolViolation) else parse_message(item))
        return events


def parse_message(line: bytes) -> Event:
    """One line (no terminator) from a device."""
    if any(b < 0x20 or b > 0x7E for b in line):
        return ProtocolViolation(line, "non-printable or non-ASCII bytes")
    lead = line[:1]
    if lead not in (b"@", b"#", b"!"):
        return ProtocolViolation(line, "does not start with @, # or !")
    body, ok = _verify(line)
    if ok is False:
        return ChecksumMismatch(line, f"checksum {line[-2:].decode()} does not match")
    tokens = body.decode("ascii").split(" ")
    try:
        if lead == b"@":
            return _parse_reply(tokens)
        if lead == b"#":
            return _parse_info(tokens)
        return _parse_alert(tokens)
    except (ValueError, IndexError) as exc:
        return ProtocolViolation(line, f"malformed: {exc}")


def _num(tok: str, what: str) -> int:
    if not tok.isdigit():
        raise ValueError(f"bad {what} {tok!r}")
    return int(tok)


def _head(tokens: list[str]) -> tuple[int, int, list[str]]:
    if len(tokens[0]) != 2:
        raise ValueError(f"address {tokens[0]!r} is not two digits")
    return _num(tokens[0], "address"), _num(tokens[1], "axis"), tokens[2:]


def _parse_reply(tokens: list[str]) -> Reply:
    address, axis, rest = _head(tokens)
    mid = None
    if rest and rest[0].isdigit():
        mid = int(rest.pop(0))
    flag, status, warning = rest[0], rest[1], rest[2]
    if flag not in ("OK", "RJ") or status not in ("IDLE", "BUSY"):
        raise ValueError(f"bad reply flag/status {flag!r} {status!r}")
    if len(warning) != 2 or not (warning == NO_FLAG or (warning.isalpha() and warning.isupper())):
        raise ValueError(f"bad warning flag {warning!r}")
    data = " ".join(rest[3:])
    if not data or ":" in data:
        raise ValueError(f"bad reply data {data!r}")
    return Reply(address, axis, mid, flag, status, warning, data)


def _parse_info(tokens: list[str]) -> Info:
    address, axis, rest = _head(tokens)
    mid = None
    if rest and rest[0].isdigit() and len(rest[0]) == 2:
        mid = int(rest.pop(0))
    return Info(address, axis, mid, " ".join(rest))


def _parse_alert(tokens: list[str]) -> Alert:
    address, axis, rest = _head(tokens)
    status, warning = rest[0], rest[1]
    if status not in ("IDLE", "BUSY"):
        raise ValueError(f"bad alert status {status!r}")
    return Alert(address, axis, status, warning, " ".join(rest[2:]))


# -- device side -------------------------------------------------------------------------
@dataclass(frozen=True)
class ReceivedCommand:
    command: Command
    checksummed: bool  # answer with a checksum too


class CommandParser:
    """Host bytes in (device side): commands, or violations for bad ones.

    Bytes before the ``/`` of a line are ignored, as the devices do; ``\\r`` and
    ``\\n`` each end a line, so ``\\r\\n`` is fine.
    """

    def __init__(self, max_line: int = 200) -> None:
        self._lines = _Lines(max_line)

    def feed(self, data: bytes) -> list[ReceivedCommand | ProtocolViolation]:
        out: list[ReceivedCommand | ProtocolViolation] = []
        for item in self._lines.feed(data):
            if isinstance(item, ProtocolViolation):
                out.append(item)
                continue
            start = item.find(b"/")
            if start < 0:
                continue  # noise between commands
            parsed = parse_command(item[start:])
            out.append(parsed)
        return out


def parse_command(line: bytes) -> ReceivedCommand | ProtocolViolation:
    if any(b < 0x20 or b > 0x7E for b in line):
        return ProtocolViolation(line, "non-printable or non-ASCII bytes")
    body, ok = _verify(line)
    if ok is False:
        return ChecksumMismatch(line, "command checksum does not match")
    tokens = body.decode("ascii").split()
    nums: list[int] = []
    while tokens and tokens[0].isdigit() and len(nums) < 3:
        nums.append(int(tokens.pop(0)))
    padded: list[int | None] = [*nums, None, None, None]
    address, axis, mid = padded[:3]
    if mid is not None and mid > MAX_MESSAGE_ID:
        return ProtocolViolation(line, f"message id {mid} out of range")
    return ReceivedCommand(Command(address, axis, mid, " ".join(tokens)), ok is True)


def format_reply(reply: Reply, *, with_checksum: bool = False) -> bytes:
    parts = [f"{reply.address:02d}", str(reply.axis)]
    if reply.message_id is not None:
        parts.append(f"{reply.message_id:02d}")
    parts += [reply.flag, reply.status, reply.warning, reply.data]
    return _frame(b"@", " ".join(parts), with_checksum)


def format_info(info: Info, *, with_checksum: bool = False) -> bytes:
    parts = [f"{info.address:02d}", str(info.axis)]
    if info.message_id is not None:
        parts.append(f"{info.message_id:02d}")
    parts.append(info.text)
    return _frame(b"#", " ".join(parts), with_checksum)


def format_alert(alert: Alert, *, with_checksum: bool = False) -> bytes:
    parts = [f"{alert.address:02d}", str(alert.axis), alert.status, alert.warning]
    if alert.data:
        parts.append(alert.data)
    return _frame(b"!", " ".join(parts), with_checksum)


def _frame(lead: bytes, text: str, with_checksum: bool) -> bytes:
    body = text.encode("ascii")
    if with_checksum:
        body += b":%02X" % checksum(body)
    return lead + body + b"\r\n"

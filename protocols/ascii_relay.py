"""The ASCII command set of Numato-style USB relay boards: a sans-I/O codec.

The host types a command line ended by CR (``relay on 0\\r``). The board echoes each
character as it arrives, answers the CR with LF CR, prints the answer lines (each
ended by LF CR) and then a ``>`` prompt::

    host:  relay read 0\\r
    board: relay read 0\\n\\ron\\n\\r>

Commands: ``relay on N``, ``relay off N``, ``relay read N`` (answer ``on``/``off``),
``relay readall`` (answer: hex mask, bit N = relay N), ``relay writeall XX``,
``ver`` (answer: firmware version). Relays 0-9 are written as digits and relays 10
and up as letters from ``A`` (Numato's convention, not hexadecimal: it goes past F).
The mask has one hex digit per four relays (two for an 8-relay board).

Host side: :func:`encode` and :class:`ReplyParser` (echo, answer lines, prompt, from
any split of the incoming bytes). Board side: :func:`parse_command` and
:func:`encode_reply`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from m2s2hil.protocols.errors import CodecError

CR = b"\r"
LINE_END = b"\n\r"  # what the board prints after the echo and after each answer line
PROMPT = b">"
MAX_CHANNELS = 32
MAX_LINE = 128  # longer than any answer; a longer run without a line end is garbage


# -- commands -------------------------------------------------------------------------------
def channel_token(channel: int) -> str:
    if not 0 <= channel < MAX_CHANNELS:
        raise ValueError(f"relay {channel} outside 0..{MAX_CHANNELS - 1}")
    return str(channel) if channel < 10 else chr(ord("A") + channel - 10)


def parse_channel_token(token: str) -> int | None:
    if len(token) != 1:
        return None
    if token.isdigit():
        return int(token)
    if "A" <= token <= chr(ord("A") + MAX_CHANNELS - 11):
        return ord(token) - ord("A") + 10
    return None


def mask_digits(channels: int) -> int:
    return max(1, (channels + 3) // 4)


def format_mask(mask: int, channels: int) -> str:
    if not 0 <= mask < 1 << channels:
        raise ValueError(f"mask {mask:#x} does not fit {channels} relays")
    return f"{mask:0{mask_digits(channels)}x}"


def parse_mask(text: str, channels: int) -> int:
    """A hex mask as the board prints it; CodecError if it is not one for ``channels`` relays."""
    if not text or len(text) > mask_digits(channels) or any(c not in "0123456789abcdefABCDEF" for c in text):
        raise CodecError(f"not a {mask_digits(channels)}-digit hex relay mask", text.encode())
    mask = int(text, 16)
    if mask >= 1 << channels:
        raise CodecError(f"mask sets relays beyond {channels}", text.encode())
    return mask


@dataclass(frozen=True)
class RelayOn:
    channel: int

    @property
    def text(self) -> str:
        return f"relay on {channel_token(self.channel)}"


@dataclass(frozen=True)
class RelayOff:
    channel: int

    @property
    def text(self) -> str:
        return f"relay off {channel_token(self.channel)}"


@dataclass(frozen=True)
class RelayRead:
    channel: int

    @property
    def text(self) -> str:
        return f"relay read {channel_token(self.channel)}"


@dataclass(frozen=True)
class ReadAll:
    @property
    def text(self) -> str:
        return "relay readall"


@dataclass(frozen=True)
class WriteAll:
    mask: int
    channels: int = 8

    @property
    def text(self) -> str:
        return f"relay writeall {format_mask(self.mask, self.channels)}"


@dataclass(frozen=True)
class Version:
    @property
    def text(self) -> str:
        return "ver"


@dataclass(frozen=True)
class EmptyLine:
    """A bare CR: the board prints a fresh prompt (used to resynchronise)."""

    @property
    def text(self) -> str:
        return ""


Command = RelayOn | RelayOff | RelayRead | ReadAll | WriteAll | Version | EmptyLine


def encode(command: Command) -> bytes:
    return command.text.encode("ascii") + CR


def parse_command(line: str, channels: int = 8) -> Command | None:
    """The command in a line the board received, or None for one it would ignore.

    Extra words after a complete command are ignored, as the real firmware does.
    """
    words = line.split()
    if not words:
        return EmptyLine()
    if words[0] == "ver":
        return Version()
    if words[0] != "relay" or len(words) < 2:
        return None
    verb = words[1]
    if verb == "readall":
        return ReadAll()
    if len(words) < 3:
        return None
    if verb == "writeall":
        try:
            return WriteAll(parse_mask(words[2], channels), channels)
        except CodecError:
            return None
    channel = parse_channel_token(words[2])
    if channel is None or channel >= channels:
        return None
    make: dict[str, Callable[[int], RelayOn | RelayOff | RelayRead]] = {
        "on": RelayOn, "off": RelayOff, "read": RelayRead}
    return make[verb](channel) if verb in make else None


def encode_reply(answers: list[str] | tuple[str, ...] = ()) -> bytes:
    """What the board prints after echoing a command line: line end, answers, prompt."""
    out = bytearray(LINE_END)
    for line in answers:
        out += line.encode("ascii") + LINE_END
    return bytes(out + PROMPT)


# -- host-side parser ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Echo:
    text: str


@dataclass(frozen=True)
class Answer:
    text: str


@dataclass(frozen=True)
class Prompt:
    pass


class _NeedData:
    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA = _NeedData()

ReplyEvent = Echo | Answer | Prompt


def _printable(b: int) -> bool:
    return 0x20 <= b <= 0x7E


class ReplyParser:
    """Incremental parser of the board's output: Echo, Answer..., Prompt per command.

    The first line after a prompt (or after :meth:`reset`) is the echo, the other
    lines are answers; ``>`` at the start of a line is the prompt. Line ends are any
    run of CR/LF (the board prints LF CR), so empty lines vanish. A byte that is not
    printable ASCII raises :class:`CodecError`; the bytes up to it are dropped and the
    parser carries on.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._expect_echo = True

    def receive_data(self, data: bytes) -> None:
        self._buf += data

    def reset(self) -> None:
        self._buf.clear()
        self._expect_echo = True

    @property
    def buffered(self) -> bytes:
        return bytes(self._buf)

    def next_event(self) -> ReplyEvent | _NeedData:
        buf = self._buf
        skip = 0
        while skip < len(buf) and buf[skip] in b"\r\n":
            skip += 1
        del buf[:skip]
        if not buf:
            return NEED_DATA
        end = len(buf)
        for i, b in enumerate(buf):
            if b in b"\r\n":
                end = i
                break
            if not _printable(b):
                junk = bytes(buf[: i + 1])
                del buf[: i + 1]
                raise CodecError(f"byte {b:#04x} is not printable ASCII", junk)
        if buf[0] == PROMPT[0]:
            del buf[:1]
            self._expect_echo = True
            return Prompt()
        if end == len(buf):
            if len(buf) > MAX_LINE:
                junk = bytes(buf)
                buf.clear()
                raise CodecError(f"no line end within {MAX_LINE} bytes", junk)
            return NEED_DATA
        text = buf[:end].decode("ascii")
        del buf[:end]
        if self._expect_echo:
            self._expect_echo = False
            return Echo(text)
        return Answer(text)

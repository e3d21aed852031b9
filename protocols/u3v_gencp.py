"""GenCP over USB3 Vision: the control channel's command and acknowledge packets.

Every packet is a 12-byte little-endian header plus a payload:

- command:     u32 prefix, u16 flags,  u16 command id, u16 payload length, u16 request id
- acknowledge: u32 prefix, u16 status, u16 command id, u16 payload length, u16 request id

The prefix is "U3VC" (0x43563355) on the control channel and "U3VE" (0x45563355) on the
event channel. Sans-I/O: functions turn values into bytes and bytes into frozen
dataclasses; anything malformed raises :class:`CodecError`.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag

from m2s2hil.protocols.errors import CodecError

CONTROL_PREFIX = 0x43563355  # b"U3VC"
EVENT_PREFIX = 0x45563355  # b"U3VE"
HEADER_SIZE = 12
MAX_PAYLOAD = 0xFFFF  # the length field is a u16

_HEADER = struct.Struct("<IHHHH")
_READMEM = struct.Struct("<QHH")
_ADDRESS = struct.Struct("<Q")
_RES_U16 = struct.Struct("<HH")
_EVENT = struct.Struct("<HHQ")


class CommandId(IntEnum):
    READMEM_CMD = 0x0800
    READMEM_ACK = 0x0801
    WRITEMEM_CMD = 0x0802
    WRITEMEM_ACK = 0x0803
    PENDING_ACK = 0x0805
    EVENT_CMD = 0x0C00
    EVENT_ACK = 0x0C01


class Flags(IntFlag):
    NONE = 0
    REQUEST_ACK = 0x4000
    RESEND = 0x8000


class Status(IntEnum):
    """GenCP / U3V status codes carried in acknowledges and stream trailers."""

    SUCCESS = 0x0000
    NOT_IMPLEMENTED = 0x8001
    INVALID_PARAMETER = 0x8002
    INVALID_ADDRESS = 0x8003
    WRITE_PROTECT = 0x8004
    BAD_ALIGNMENT = 0x8005
    ACCESS_DENIED = 0x8006
    BUSY = 0x8007
    MSG_TIMEOUT = 0x800B
    INVALID_HEADER = 0x800E
    WRONG_CONFIG = 0x800F
    GENERIC_ERROR = 0x8FFF
    RESEND_NOT_SUPPORTED = 0xA001
    STREAM_ENDPOINT_HALTED = 0xA002
    PAYLOAD_SIZE_NOT_ALIGNED = 0xA003
    STREAM_REGISTERS_INCONSISTENT = 0xA004
    DATA_DISCARDED = 0xA100


def status_name(code: int) -> str:
    """``"INVALID_ADDRESS"`` for 0x8003; unknown codes as ``"0x1234"``."""
    try:
        return Status(code).name
    except ValueError:
        return f"0x{code:04X}"


# -- request ids ------------------------------------------------------------------------


def next_request_id(request_id: int) -> int:
    """The id after ``request_id``: increments, wraps 0xFFFF -> 1 (0 is never used)."""
    if not 0 <= request_id <= 0xFFFF:
        raise ValueError(f"request id {request_id} outside 0..0xFFFF")
    return 1 if request_id >= 0xFFFF else request_id + 1


class RequestIds:
    """Hands out request ids 1, 2, ... 0xFFFF, 1, ..."""

    def __init__(self, last: int = 0) -> None:
        self.last = last

    def next(self) -> int:
        self.last = next_request_id(self.last)
        return self.last


# -- packets ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Command:
    command_id: int
    request_id: int
    payload: bytes = b""
    flags: int = Flags.REQUEST_ACK
    prefix: int = CONTROL_PREFIX

    def encode(self) -> bytes:
        return encode_command(self.command_id, self.payload, self.request_id, self.flags, self.prefix)

    @property
    def is_resend(self) -> bool:
        return bool(self.flags & Flags.RESEND)


@dataclass(frozen=True)
class Ack:
    status: int
    command_id: int
    request_id: int
    payload: bytes = b""
    prefix: int = CONTROL_PREFIX

    def encode(self) -> bytes:
        return encode_ack(self.status, self.command_id, self.payload, self.request_id, self.prefix)

    @property
    def ok(self) -> bool:
        return self.status == Status.SUCCESS

    @property
    def status_name(self) -> str:
        return status_name(self.status)


def _check_u16(name: str, value: int) -> None:
    if not 0 <= value <= 0xFFFF:
        raise ValueError(f"{name} {value} outside 0..0xFFFF")


def encode_command(
    command_id: int,
    payload: bytes,
    request_id: int,
    flags: int = Flags.REQUEST_ACK,
    prefix: int = CONTROL_PREFIX,
) -> bytes:
    for name, v in (("command id", command_id), ("request id", request_id), ("flags", int(flags))):
        _check_u16(name, v)
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    return _HEADER.pack(prefix, int(flags), command_id, len(payload), request_id) + bytes(payload)


def encode_ack(
    status: int, command_id: int, payload: bytes, request_id: int, prefix: int = CONTROL_PREFIX
) -> bytes:
    for name, v in (("status", status), ("command id", command_id), ("request id", request_id)):
        _check_u16(name, v)
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    return _HEADER.pack(prefix, status, command_id, len(payload), request_id) + bytes(payload)


def _split(data: bytes, what: str) -> tuple[int, int, int, int, bytes]:
    data = bytes(data)
    if len(data) < HEADER_SIZE:
        raise CodecError(f"GenCP {what}: {len(data)} bytes, shorter than the 12-byte header", data)
    prefix, word, command_id, length, request_id = _HEADER.unpack_from(data)
    if prefix not in (CONTROL_PREFIX, EVENT_PREFIX):
        raise CodecError(f"GenCP {what}: bad prefix 0x{prefix:08X}", data)
    if len(data) != HEADER_SIZE + length:
        raise CodecError(
            f"GenCP {what}: header says {length} payload bytes, got {len(data) - HEADER_SIZE}", data
        )
    return prefix, word, command_id, request_id, data[HEADER_SIZE:]


def decode_command(data: bytes) -> Command:
    prefix, flags, command_id, request_id, payload = _split(data, "command")
    if command_id & 1:
        raise CodecError(f"GenCP command: id 0x{command_id:04X} is an acknowledge id", data)
    return Command(command_id, request_id, payload, flags, prefix)


def decode_ack(data: bytes) -> Ack:
    prefix, status, command_id, request_id, payload = _split(data, "acknowledge")
    if not command_id & 1:
        raise CodecError(f"GenCP acknowledge: id 0x{command_id:04X} is a command id", data)
    return Ack(status, command_id, request_id, payload, prefix)


def ack_matches(ack: Ack, command: Command) -> bool:
    """The final answer to ``command``: same request id and command id + 1."""
    return ack.request_id == command.request_id and ack.command_id == command.command_id + 1


def is_pending_for(ack: Ack, command: Command) -> bool:
    """A PENDING_ACK for ``command`` (the host keeps waiting)."""
    return ack.request_id == command.request_id and ack.command_id == CommandId.PENDING_ACK


# -- READMEM ----------------------------------------------------------------------------


def read_mem(address: int, length: int, request_id: int, *, resend: bool = False) -> Command:
    if not 0 <= address < 1 << 64:
        raise ValueError(f"address {address:#x} outside u64")
    _check_u16("read length", length)
    flags = Flags.REQUEST_ACK | (Flags.RESEND if resend else 0)
    return Command(CommandId.READMEM_CMD, request_id, _READMEM.pack(address, 0, length), flags)


def parse_read_mem(command: Command) -> tuple[int, int]:
    """(address, length) of a READMEM_CMD."""
    if command.command_id != CommandId.READMEM_CMD:
        raise CodecError(f"not a READMEM_CMD: 0x{command.command_id:04X}")
    if len(command.payload) != _READMEM.size:
        raise CodecError(f"READMEM_CMD payload is {len(command.payload)} bytes, expected 12", command.payload)
    address, _reserved, length = _READMEM.unpack(command.payload)
    return address, length


def read_mem_ack(data: bytes, request_id: int, status: int = Status.SUCCESS) -> Ack:
    return Ack(status, CommandId.READMEM_ACK, request_id, bytes(data))


# -- WRITEMEM ---------------------------------------------------------------------------


def write_mem(address: int, data: bytes, request_id: int, *, resend: bool = False) -> Command:
    if not 0 <= address < 1 << 64:
        raise ValueError(f"address {address:#x} outside u64")
    if len(data) > MAX_PAYLOAD - _ADDRESS.size:
        raise ValueError(f"write of {len(data)} bytes exceeds one command")
    flags = Flags.REQUEST_ACK | (Flags.RESEND if resend else 0)
    return Command(CommandId.WRITEMEM_CMD, request_id, _ADDRESS.pack(address) + bytes(data), flags)


def parse_write_mem(command: Command) -> tuple[int, bytes]:
    """(address, data) of a WRITEMEM_CMD."""
    if command.command_id != CommandId.WRITEMEM_CMD:
        raise CodecError(f"not a WRITEMEM_CMD: 0x{command.command_id:04X}")
    if len(command.payload) < _ADDRESS.size:
        raise CodecError("WRITEMEM_CMD payload shorter than its 8-byte address", command.payload)
    (address,) = _ADDRESS.unpack_from(command.payload)
    return address, command.payload[_ADDRESS.size :]


def write_mem_ack(written: int, request_id: int, status: int = Status.SUCCESS) -> Ack:
    _check_u16("bytes written", written)
    return Ack(status, CommandId.WRITEMEM_ACK, request_id, _RES_U16.pack(0, written))


def parse_write_mem_ack(ack: Ack) -> int | None:
    """Bytes written, or None when the device sent no count (allowed with an error status)."""
    if ack.command_id != CommandId.WRITEMEM_ACK:
        raise CodecError(f"not a WRITEMEM_ACK: 0x{ack.command_id:04X}")
    if not ack.payload:
        return None
    if len(ack.payload) != _RES_U16.size:
        raise CodecError(f"WRITEMEM_ACK payload is {len(ack.payload)} bytes, expected 4", ack.payload)
    return _RES_U16.unpack(ack.payload)[1]


# -- PENDING_ACK ------------------------------------------------------------------------


def pending_ack(timeout_ms: int, request_id: int) -> Ack:
    _check_u16("pending timeout", timeout_ms)
    return Ack(Status.SUCCESS, CommandId.PENDING_ACK, request_id, _RES_U16.pack(0, timeout_ms))


def parse_pending_ack(ack: Ack) -> int:
    """The new timeout in milliseconds."""
    if ack.command_id != CommandId.PENDING_ACK:
        raise CodecError(f"not a PENDING_ACK: 0x{ack.command_id:04X}")
    if len(ack.payload) != _RES_U16.size:
        raise CodecError(f"PENDING_ACK payload is {len(ack.payload)} bytes, expected 4", ack.payload)
    return _RES_U16.unpack(ack.payload)[1]


# -- EVENT ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Event:
    event_id: int
    timestamp: int
    data: bytes = b""


def event_command(event: Event, request_id: int, *, want_ack: bool = False) -> Command:
    _check_u16("event id", event.event_id)
    payload = _EVENT.pack(0, event.event_id, event.timestamp) + bytes(event.data)
    flags = Flags.REQUEST_ACK if want_ack else Flags.NONE
    return Command(CommandId.EVENT_CMD, request_id, payload, flags, EVENT_PREFIX)


def parse_event(command: Command) -> Event:
    if command.command_id != CommandId.EVENT_CMD or command.prefix != EVENT_PREFIX:
        raise CodecError(f"not a U3VE EVENT_CMD: 0x{command.command_id:04X}")
    if len(command.payload) < _EVENT.size:
        raise CodecError(f"EVENT_CMD payload is {len(command.payload)} bytes, needs 12", command.payload)
    _reserved, event_id, timestamp = _EVENT.unpack_from(command.payload)
    return Event(event_id, timestamp, command.payload[_EVENT.size :])

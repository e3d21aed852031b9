"""Modbus RTU for coil relay boards (Waveshare-style, 8 coils): a sans-I/O codec.

Bytes in, events out, for both ends of the wire: ``role="client"`` encodes requests
and decodes responses (the driver); ``role="server"`` decodes requests and encodes
responses (the simulator). Only the relay functions are modelled: FC01 read coils,
FC05 write single coil, FC0F write multiple coils, and exception responses.

pymodbus does the protocol work: its PDU classes encode and decode the function
bodies, ``DecodePDU.lookupPduClass`` / ``calculateRtuFrameSize`` tell how long a
frame is, and ``FramerRTU`` builds frames and checks the CRC. What this module adds
is the buffer management of a sans-I/O parser. ``FramerRTU.decode`` is written for
one frame per exchange: it swallows everything after the frame it found and throws
the whole buffer away on a CRC mismatch. Here a frame consumes exactly its own
bytes, and a CRC mismatch raises :class:`CodecError` after dropping one byte, so
the next call hunts for a frame start one byte further on (RTU has no start marker;
the real line has 3.5 character times of silence, which a byte stream does not keep).

Usage (client)::

    codec = ModbusRelayCodec("client")
    wire = codec.send(WriteCoils(unit=1, address=0, values=(True, False)))
    codec.receive_data(reply_bytes)
    event = codec.next_event()   # CoilsWritten(...) or NEED_DATA; CodecError on bad bytes
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Literal

from m2s2hil.protocols.errors import CodecError
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadCoilsResponse,
    WriteMultipleCoilsRequest,
    WriteMultipleCoilsResponse,
    WriteSingleCoilRequest,
    WriteSingleCoilResponse,
)

READ_COILS = 0x01
WRITE_SINGLE_COIL = 0x05
WRITE_MULTIPLE_COILS = 0x0F
COIL_ON = 0xFF00
COIL_OFF = 0x0000
MAX_COILS = 2000  # per request, Modbus application protocol spec
BROADCAST = 0

#: Modbus exception codes, by number (pymodbus' ExcCodes).
EXCEPTION_NAMES = {int(c): c.name.lower() for c in ExcCodes}


class _NeedData:
    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA = _NeedData()
"""Returned by :meth:`ModbusRelayCodec.next_event` when a frame is incomplete."""


# -- requests (client -> server) -----------------------------------------------------
@dataclass(frozen=True)
class ReadCoils:
    unit: int
    address: int
    count: int


@dataclass(frozen=True)
class WriteCoil:
    unit: int
    address: int
    on: bool


@dataclass(frozen=True)
class WriteCoils:
    unit: int
    address: int
    values: tuple[bool, ...]


@dataclass(frozen=True)
class OtherRequest:
    """A well-framed request for a function this codec does not model (FC03, ...)."""

    unit: int
    function_code: int


@dataclass(frozen=True)
class IllegalRequest:
    """A well-framed request whose data breaks the spec (FC05 value not FF00/0000,
    FC0F byte count wrong, count out of range): the server answers ILLEGAL_VALUE."""

    unit: int
    function_code: int
    reason: str


# -- responses (server -> client) ---------------------------------------------------
@dataclass(frozen=True)
class CoilStatus:
    """FC01 answer. ``values`` is padded with False to a multiple of 8."""

    unit: int
    values: tuple[bool, ...]


@dataclass(frozen=True)
class CoilWritten:
    unit: int
    address: int
    on: bool


@dataclass(frozen=True)
class CoilsWritten:
    unit: int
    address: int
    count: int


@dataclass(frozen=True)
class ExceptionReply:
    unit: int
    function_code: int  # the request's function code (without the 0x80 bit)
    exception_code: int

    @property
    def name(self) -> str:
        return EXCEPTION_NAMES.get(self.exception_code, f"exception {self.exception_code:#04x}")


@dataclass(frozen=True)
class OtherResponse:
    """A well-framed response to a function this codec does not model."""

    unit: int
    function_code: int


Request = ReadCoils | WriteCoil | WriteCoils
Response = CoilStatus | CoilWritten | CoilsWritten | ExceptionReply
Event = Request | OtherRequest | IllegalRequest | Response | OtherResponse


class ModbusRelayCodec:
    """One end of a Modbus RTU line, as a state machine over a byte buffer."""

    def __init__(self, role: Literal["client", "server"]) -> None:
        if role not in ("client", "server"):
            raise ValueError(f"role must be 'client' or 'server', not {role!r}")
        self.role = role
        self._decoder = DecodePDU(is_server=(role == "server"))
        self._framer = FramerRTU(self._decoder)
        self._buf = bytearray()
        self.discarded = 0  # bytes skipped while hunting for a frame start

    # -- outgoing ----------------------------------------------------------------------
    def send(self, event: Event) -> bytes:
        """The RTU frame (address, PDU, CRC) for ``event``."""
        pdu = self._to_pdu(event)
        try:
            return self._framer.buildFrame(pdu)
        except (ValueError, struct.error) as exc:
            raise ValueError(f"cannot encode {event!r}: {exc}") from exc

    def _to_pdu(self, event: Event) -> ModbusPDU:
        client = self.role == "client"
        if not 0 <= event.unit <= 255:
            raise ValueError(f"unit id {event.unit} outside 0..255")
        if client and isinstance(event, ReadCoils):
            return ReadCoilsRequest(address=event.address, count=event.count, dev_id=event.unit)
        if client and isinstance(event, WriteCoil):
            return WriteSingleCoilRequest(address=event.address, bits=[event.on], dev_id=event.unit)
        if client and isinstance(event, WriteCoils):
            if not event.values:
                raise ValueError("WriteCoils needs at least one value")
            return WriteMultipleCoilsRequest(
                address=event.address, bits=list(event.values), dev_id=event.unit
            )
        if not client and isinstance(event, CoilStatus):
            return ReadCoilsResponse(bits=list(event.values), dev_id=event.unit)
        if not client and isinstance(event, CoilWritten):
            return WriteSingleCoilResponse(address=event.address, bits=[event.on], dev_id=event.unit)
        if not client and isinstance(event, CoilsWritten):
            return WriteMultipleCoilsResponse(address=event.address, count=event.count, dev_id=event.unit)
        if not client and isinstance(event, ExceptionReply):
            return ExceptionResponse(event.function_code & 0x7F, event.exception_code, device_id=event.unit)
        raise ValueError(f"a {self.role} does not send {type(event).__name__}")

    # -- incoming ----------------------------------------------------------------------
    def receive_data(self, data: bytes) -> None:
        self._buf += data

    def reset(self) -> None:
        """Forget buffered bytes (before a new request, after a timeout)."""
        self._buf.clear()

    @property
    def buffered(self) -> bytes:
        return bytes(self._buf)

    def next_event(self) -> Event | _NeedData:
        """The next complete frame as an event, or NEED_DATA.

        Raises CodecError for a frame with a bad CRC or a body pymodbus cannot decode;
        the codec stays usable (the offending bytes are dropped).
        """
        buf = self._buf
        while True:
            if len(buf) < FramerRTU.MIN_SIZE:
                return NEED_DATA
            try:
                pdu_class = self._decoder.lookupPduClass(bytes(buf))
                size = pdu_class.calculateRtuFrameSize(bytes(buf)) if pdu_class else 0
            except (ModbusException, IndexError, KeyError, struct.error):
                pdu_class, size = None, 0
            if pdu_class is None or size > FramerRTU.MAX_SIZE:
                # Not a plausible frame start (unknown function code, impossible length): hunt on.
                del buf[0]
                self.discarded += 1
                continue
            if size == 0 or len(buf) < size:
                # Sizes are capped at FramerRTU.MAX_SIZE above, so the buffer stays bounded.
                return NEED_DATA
            frame = bytes(buf[:size])
            crc = int.from_bytes(frame[-2:], "big")
            if not FramerRTU.check_CRC(frame[:-2], crc):
                del buf[0]
                self.discarded += 1
                raise CodecError(
                    f"CRC mismatch: frame says {crc:04X}, bytes give {FramerRTU.compute_CRC(frame[:-2]):04X}",
                    frame,
                )
            del buf[:size]
            return self._to_event(frame)

    def _to_event(self, frame: bytes) -> Event:
        unit, body = frame[0], frame[1:-2]
        function_code = body[0]
        pdu = self._decoder.decode(body)
        if self.role == "server":
            if function_code & 0x80:
                raise CodecError("an exception response where a request was expected", frame)
            if pdu is None:
                # The CRC is sound, so the master did send this: the spec's answer is 03.
                return IllegalRequest(unit, function_code, "request data pymodbus cannot decode")
            return self._request_event(unit, pdu, body)
        if pdu is None:
            raise CodecError(f"undecodable response for function {function_code:#04x}", frame)
        return self._response_event(unit, pdu)

    @staticmethod
    def _request_event(unit: int, pdu: ModbusPDU, body: bytes) -> Event:
        if isinstance(pdu, ReadCoilsRequest) and pdu.function_code == READ_COILS:
            return ReadCoils(unit, pdu.address, pdu.count)
        if isinstance(pdu, WriteSingleCoilRequest):
            # pymodbus reads any non-zero value as "on"; the spec allows only FF00 and 0000.
            (raw,) = struct.unpack(">H", body[3:5])
            if raw not in (COIL_ON, COIL_OFF):
                return IllegalRequest(unit, WRITE_SINGLE_COIL, f"coil value {raw:#06x} is not FF00/0000")
            return WriteCoil(unit, pdu.address, raw == COIL_ON)
        if isinstance(pdu, WriteMultipleCoilsRequest):
            expected = (pdu.count + 7) // 8
            if pdu.byte_count != expected or pdu.data_byte_count != expected:
                return IllegalRequest(
                    unit,
                    WRITE_MULTIPLE_COILS,
                    f"byte count {pdu.byte_count} (data {pdu.data_byte_count}) for {pdu.count} coils",
                )
            return WriteCoils(unit, pdu.address, tuple(bool(b) for b in pdu.bits[: pdu.count]))
        return OtherRequest(unit, pdu.function_code)

    @staticmethod
    def _response_event(unit: int, pdu: ModbusPDU) -> Event:
        if isinstance(pdu, ExceptionResponse):
            return ExceptionReply(unit, pdu.function_code & 0x7F, pdu.exception_code)
        if isinstance(pdu, ReadCoilsResponse) and pdu.function_code == READ_COILS:
            return CoilStatus(unit, tuple(bool(b) for b in pdu.bits))
        if isinstance(pdu, WriteSingleCoilResponse):
            return CoilWritten(unit, pdu.address, bool(pdu.bits[0]))
        if isinstance(pdu, WriteMultipleCoilsResponse):
            return CoilsWritten(unit, pdu.address, pdu.count)
        return OtherResponse(unit, pdu.function_code)


def expected_reply_size(request: Request) -> int:
    """Bytes in the normal RTU answer to ``request`` (an exception answer has 5)."""
    if isinstance(request, ReadCoils):
        return 5 + (request.count + 7) // 8
    return 8

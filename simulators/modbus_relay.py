"""A simulated Modbus RTU relay board (Waveshare-style: 8 coils at 0x0000-0x0007).

It answers FC01 read coils, FC05 write single coil and FC0F write multiple coils
through the same codec the driver uses (server role). Like a real slave it stays
silent for frames with a bad CRC and for other unit ids, executes broadcast (unit 0)
writes without answering, and answers exceptions: ILLEGAL_FUNCTION for other
function codes, ILLEGAL_ADDRESS for coils beyond its channels, ILLEGAL_VALUE for
malformed data.

``on_change(channel, on)`` is called for every coil that really changes, so the rig
can mirror the relays into the simulated world (``World.set_lamp``).

Device fault ``relay_stuck`` (param ``channel``, default 0): each occurrence is one
write request during which that coil keeps its state while the board acknowledges
the write as usual. Generic faults (drop_reply, garble, late_reply, vanish) come
from :class:`SimDevice`. A vanished port is an unplugged USB adapter: the board
keeps its coils (it has its own supply).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from m2s2hil.protocols.errors import CodecError
from m2s2hil.protocols.modbus_relay import (
    BROADCAST,
    NEED_DATA,
    CoilStatus,
    CoilsWritten,
    CoilWritten,
    ExceptionReply,
    IllegalRequest,
    ModbusRelayCodec,
    OtherRequest,
    ReadCoils,
    Response,
    WriteCoil,
    WriteCoils,
)
from m2s2hil.simulators.device import SimDevice
from m2s2hil.simulators.fault_injection import FaultPlan
from pymodbus.constants import ExcCodes

OnChange = Callable[[int, bool], None]


class ModbusRelaySim(SimDevice):
    baudrate = 9600

    def __init__(
        self,
        name: str,
        clock: Any,
        faults: FaultPlan | None = None,
        *,
        unit: int = 1,
        channels: int = 8,
        on_change: OnChange | None = None,
        response_delay_s: float = 0.005,
    ) -> None:
        super().__init__(name, clock, faults)
        if not 1 <= unit <= 247:
            raise ValueError(f"Modbus unit id {unit} outside 1..247")
        if not 1 <= channels <= 64:
            raise ValueError(f"channels {channels} outside 1..64")
        self.unit = unit
        self.channels = channels
        self.on_change = on_change
        self.response_delay_s = response_delay_s
        self._coils = [False] * channels
        self._codec = ModbusRelayCodec("server")
        self.ignored_frames = 0  # bad CRC, foreign unit ids: what a real slave drops

    # -- state, for tests and the rig ---------------------------------------------------
    @property
    def coils(self) -> tuple[bool, ...]:
        with self.lock:
            return tuple(self._coils)

    @property
    def on_channels(self) -> frozenset[int]:
        with self.lock:
            return frozenset(i for i, on in enumerate(self._coils) if on)

    # -- wire -----------------------------------------------------------------------------
    def on_bytes(self, data: bytes) -> None:
        self._codec.receive_data(data)
        while True:
            try:
                event = self._codec.next_event()
            except CodecError:
                self.ignored_frames += 1  # a slave never answers a corrupt frame
                continue
            if event is NEED_DATA:
                return
            reply = self._handle(event)
            if reply is not None:
                self.send(self._codec.send(reply), self.response_delay_s)

    def _handle(self, event: Any) -> Response | None:
        unit = event.unit
        if unit not in (self.unit, BROADCAST):
            self.ignored_frames += 1
            return None
        reply = self._execute(event)
        return None if unit == BROADCAST else reply

    def _execute(self, event: Any) -> Response:
        if isinstance(event, IllegalRequest):
            return ExceptionReply(self.unit, event.function_code, ExcCodes.ILLEGAL_VALUE)
        if isinstance(event, OtherRequest):
            return ExceptionReply(self.unit, event.function_code, ExcCodes.ILLEGAL_FUNCTION)
        if isinstance(event, ReadCoils):
            if event.address + event.count > self.channels:
                return ExceptionReply(self.unit, 0x01, ExcCodes.ILLEGAL_ADDRESS)
            values = self.coils[event.address : event.address + event.count]
            return CoilStatus(self.unit, values)
        if isinstance(event, WriteCoil):
            if event.address >= self.channels:
                return ExceptionReply(self.unit, 0x05, ExcCodes.ILLEGAL_ADDRESS)
            self._write(event.address, (event.on,))
            return CoilWritten(self.unit, event.address, event.on)
        if isinstance(event, WriteCoils):
            if event.address + len(event.values) > self.channels:
                return ExceptionReply(self.unit, 0x0F, ExcCodes.ILLEGAL_ADDRESS)
            self._write(event.address, event.values)
            return CoilsWritten(self.unit, event.address, len(event.values))
        # A server-role codec yields only requests; anything else is a bug here.
        raise TypeError(f"unexpected event {event!r}")

    def _write(self, address: int, values: tuple[bool, ...]) -> None:
        stuck = self.faults.take("relay_stuck")
        stuck_channel = int(stuck.get("channel", 0)) if stuck is not None else None
        changed: list[tuple[int, bool]] = []
        with self.lock:
            for offset, on in enumerate(values):
                channel = address + offset
                if channel == stuck_channel or self._coils[channel] == on:
                    continue
                self._coils[channel] = on
                changed.append((channel, on))
        if self.on_change is not None:
            for channel, on in changed:
                self.on_change(channel, on)

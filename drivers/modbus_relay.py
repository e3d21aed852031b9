"""The relay board on Modbus RTU (Waveshare-style module, coils 0x0000-0x0007).

Transport choice: our :class:`SerialLink` plus the sans-I/O codec in
``m2s2hil.protocols.modbus_relay`` (which uses pymodbus' PDU classes, frame sizes and
CRC), rather than pymodbus' own ``ModbusSerialClient``. The stock client measures
its timeouts with ``time.time()`` and sleeps with ``time.sleep()``, so it cannot run
on the injected clock (a virtual-clock simulation would cost real seconds per
timeout); it reports failures as ``ModbusIOException`` / ``isError()`` results that
we would have to translate back into timeout, garbage or refusal anyway; and it
retries and closes the port on its own schedule. With the link and the codec every
wait is on ``clock``, every failure is one of our typed errors, and a test can
script the exact bytes.

Every public call is one or two transactions, each started after the RTU inter-frame
silence (3.5 character times) measured on ``clock``. A transaction is retried up to
``retries`` more times after a timeout, garbage or a port that vanished (the port
is reopened first); a Modbus exception answer is final (:class:`CommandRejected`
with the exception code). ``set`` writes all coils with FC0F and reads them back
with FC01; a difference is :class:`RelayNotSwitched`.
"""

from __future__ import annotations

from typing import Any, cast

from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.drivers.errors import CommandRejected, DeviceGone, ProtocolError, RelayNotSwitched
from m2s2hil.drivers.locking import one_at_a_time
from m2s2hil.drivers.relay_base import RelayBoardBase
from m2s2hil.drivers.serial_link import SerialLink
from m2s2hil.protocols.modbus_relay import (
    NEED_DATA,
    CoilStatus,
    CoilsWritten,
    CoilWritten,
    Event,
    ExceptionReply,
    ModbusRelayCodec,
    ReadCoils,
    Request,
    WriteCoil,
    WriteCoils,
)


class ModbusRelayBoard(RelayBoardBase):
    """A :class:`~m2s2hil.drivers.interfaces.LightBank` on a Modbus RTU relay module."""

    def __init__(
        self,
        url: str,
        *,
        device: str = "relays",
        unit: int = 1,
        baudrate: int = 9600,
        timeout_s: float = 0.5,
        clock: Clock = SYSTEM_CLOCK,
        channels: int = 8,
        retries: int = 2,
        reconnect_attempts: int = 4,
        reconnect_interval_s: float = 0.5,
        parity: str = "N",
        stopbits: float = 1,
    ) -> None:
        if not 1 <= unit <= 247:
            raise ValueError(f"{device}: Modbus unit id {unit} outside 1..247")
        super().__init__(
            device, channels, 64, retries=retries, timeout_s=timeout_s, clock=clock,
            reconnect_attempts=reconnect_attempts, reconnect_interval_s=reconnect_interval_s,
        )
        self.unit = unit
        # Waveshare ships 8N1; the Modbus serial-line spec's default is 8E1: both configurable.
        self._link = SerialLink(
            url,
            device=device,
            baudrate=baudrate,
            parity=parity,
            stopbits=stopbits,
            timeout_s=timeout_s,
            clock=clock,
        )
        self._codec = ModbusRelayCodec("client")
        # RTU frames are delimited by 3.5 character times of silence (11 bits a character;
        # a fixed 1.75 ms above 19200 baud, as the Modbus serial line spec says).
        self.frame_gap_s = 3.5 * 11 / baudrate if baudrate <= 19200 else 0.00175
        self._quiet_since = float("-inf")

    # -- connection -----------------------------------------------------------------------
    @one_at_a_time
    def connect(self) -> None:
        """Open the port and check that the board answers (reads the coils)."""
        self.state()

    # -- LightBank ------------------------------------------------------------------------
    @one_at_a_time
    def switch(self, channel: int, on: bool) -> None:
        """Switch one channel (FC05), leaving the others; verified by read-back."""
        (ch,) = self._check_channels([channel])
        command = f"switch {ch} {'on' if on else 'off'}"
        reply = self._transact(WriteCoil(self.unit, ch, on), command)
        if not (isinstance(reply, CoilWritten) and reply.address == ch and reply.on == on):
            raise ProtocolError(
                f"write echo {reply!r} does not match the request", device=self.name, command=command
            )
        actual = self.state()
        if (ch in actual) != on:
            raise RelayNotSwitched(
                f"channel {ch} reads {'on' if ch in actual else 'off'} after switching it "
                f"{'on' if on else 'off'}",
                device=self.name,
                command=command,
            )

    @one_at_a_time
    def state(self) -> frozenset[int]:
        """The channels whose coil reads on (FC01)."""
        reply = self._transact(ReadCoils(self.unit, 0, self.channels), "read coils")
        assert isinstance(reply, CoilStatus)  # _check_reply made sure
        return frozenset(ch for ch in range(self.channels) if reply.values[ch])

    # -- internals --------------------------------------------------------------------------
    def _write_all(self, wanted: frozenset[int]) -> str:
        """One FC0F write of every coil."""
        values = tuple(ch in wanted for ch in range(self.channels))
        command = f"set {sorted(wanted)}"
        reply = self._transact(WriteCoils(self.unit, 0, values), command)
        if not (isinstance(reply, CoilsWritten) and reply.address == 0 and reply.count == self.channels):
            raise ProtocolError(
                f"write echo {reply!r} does not match the request", device=self.name, command=command
            )
        return command

    def _transact(self, request: Request, command: str) -> Event:
        return self._retrying(lambda attempt: self._attempt(request, command, attempt))

    def _attempt(self, request: Request, command: str, attempt: int) -> Event:
        where: dict[str, Any] = {"device": self.name, "command": command, "attempt": attempt}
        try:
            self._open_line()
            self._codec.reset()
            self.clock.sleep(self._quiet_since + self.frame_gap_s - self.clock.monotonic())
            self._link.write(self._codec.send(request), command=command)
            try:
                reply = self._read_reply(command, attempt)
            finally:
                self._quiet_since = self.clock.monotonic()
        except DeviceGone as exc:
            raise DeviceGone(exc.detail, **where) from exc
        return self._check_reply(request, reply, where)

    def _read_reply(self, command: str, attempt: int) -> Event:
        deadline = self.clock.monotonic() + self.timeout_s

        def missing() -> str:
            got = self._codec.buffered
            return f"no complete answer within {self.timeout_s:.3g} s (got {got.hex(' ') or 'nothing'})"

        while True:
            self._codec.receive_data(self._read_some(deadline, command, attempt, missing))
            event = self._decoded(self._codec.next_event, command, attempt)
            if event is not NEED_DATA:
                return cast(Event, event)  # the codec's NEED_DATA sentinel is not an Event

    def _check_reply(self, request: Request, reply: Event, where: dict[str, Any]) -> Event:
        if reply.unit != request.unit:
            raise ProtocolError(f"answer from unit {reply.unit}, asked unit {request.unit}", **where)
        function_code = {ReadCoils: 0x01, WriteCoil: 0x05, WriteCoils: 0x0F}[type(request)]
        if isinstance(reply, ExceptionReply):
            if reply.function_code != function_code:
                raise ProtocolError(
                    f"exception for function {reply.function_code:#04x}, asked {function_code:#04x}", **where
                )
            raise CommandRejected(
                f"Modbus exception {reply.exception_code:#04x} ({reply.name})",
                code=reply.exception_code,
                **where,
            )
        expected = {ReadCoils: CoilStatus, WriteCoil: CoilWritten, WriteCoils: CoilsWritten}[type(request)]
        if not isinstance(reply, expected):
            raise ProtocolError(f"answer {reply!r} does not fit the request {request!r}", **where)
        if isinstance(reply, CoilStatus) and len(reply.values) != 8 * ((self.channels + 7) // 8):
            raise ProtocolError(f"{len(reply.values) // 8} data bytes for {self.channels} coils", **where)
        return reply

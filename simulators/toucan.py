"""The simulated SILIOS TOUCAN: a USB3 Vision camera seen from the wire.

It answers GenCP commands on the control endpoint (PENDING_ACK for AcquisitionStart, error
statuses for bad addresses and refused writes, resend of the last acknowledge) and streams
leader + payload transfers + trailer on the stream endpoint, timed on the injected clock.
Serve it to pyusb with :class:`~m2s2hil.simulators.u3v_backend.SimUsbBackend`. Its parts:

- ``toucan_register_map``: the registers as a table (address, width, access, default, the
  document each comes from); ``toucan_registers``: their state, reads and writes;
- ``toucan_stream``: frame timing, the device's buffer, leader/payload/trailer;
- ``toucan_render``: the pluggable frame source (what is rendered into a frame)::

    class FrameSource(Protocol):
        def capture(self, exposure_s: float, gain: float) -> np.ndarray: ...

  returning a uint16 (height, width) mosaic with values below ``2**bit_depth``. The values
  travel unshifted in every pixel format (Mono12/Mono16 carry the same 10-bit numbers as
  Mono10).

Faults (``self.faults``), each drawn once per frame when the frame is due:
``unplug`` (``duration_s``, default 1.0: the device leaves the bus, I/O fails with
ENODEV, then it re-enumerates with power-on defaults), ``stall`` (the stream stops
until acquisition is stopped and started again), ``frame_timeout`` (this frame is
never sent), ``incomplete`` (``fraction`` of the payload sent, default 0.5, and a
trailer saying so), ``trailer_error`` (``status``, default DATA_DISCARDED).
``drop_reply`` and ``late_reply`` (``delay_s``) hit GenCP acknowledges.
"""

from __future__ import annotations

import hashlib
import importlib.resources
import struct
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from m2s2hil.protocols import u3v
from m2s2hil.protocols.errors import CodecError
from m2s2hil.protocols.u3v import ABRM, Status
from m2s2hil.simulators.fault_injection import FaultPlan
from m2s2hil.simulators.toucan_register_map import (
    MAX_ACK_TRANSFER,
    MAX_COMMAND_TRANSFER,
    RESPONSE_TIME_MS,
    Settings,
    default_of,
)
from m2s2hil.simulators.toucan_registers import XML_NAME, Effect, RegisterSpace
from m2s2hil.simulators.toucan_render import FrameSource, GradientSource
from m2s2hil.simulators.toucan_stream import ToucanStream
from m2s2hil.simulators.u3v_backend import (
    EP_CONTROL_IN,
    EP_CONTROL_OUT,
    EP_EVENT_IN,
    EP_STREAM_IN,
    Halted,
    NoDevice,
    Overflow,
    UsbIdentity,
)


class ToucanCamera:
    """A simulated TOUCAN behind a :class:`SimUsbBackend` (see the module docstring)."""

    def __init__(
        self,
        *,
        clock: Any,
        frame_source: FrameSource | None = None,
        serial: str = str(default_of(ABRM.SERIAL_NUMBER)),
        width: int = 2048,
        height: int = 2048,
        bit_depth: int = 10,
        faults: FaultPlan | None = None,
        name: str = "toucan",
        vendor_id: int = 0x1209,
        product_id: int = 0x0001,
        zip_xml: bool = False,
        max_fps: float = 65.0,
        temperature_c: float | Callable[[], float] = 35.0,
        start_delay_s: float = 0.3,
        frame_buffer: int = 4,
    ) -> None:
        if bit_depth not in (8, 10, 12, 16):
            raise ValueError(f"bit depth {bit_depth} not one of 8, 10, 12, 16")
        self.name = name
        self.clock = clock
        self.width, self.height, self.bit_depth = int(width), int(height), int(bit_depth)
        self.frame_source: FrameSource = frame_source or GradientSource(width, height, bit_depth)
        self.faults = faults if faults is not None else FaultPlan()
        self.serial = serial
        self.max_fps = float(max_fps)
        self.start_delay_s = float(start_delay_s)
        self.identity = UsbIdentity(
            vendor_id=vendor_id,
            product_id=product_id,
            manufacturer=str(default_of(ABRM.MANUFACTURER_NAME)),
            model=str(default_of(ABRM.MODEL_NAME)),
            serial=serial,
            family=str(default_of(ABRM.FAMILY_NAME)),
            device_version=str(default_of(ABRM.DEVICE_VERSION)),
            manufacturer_info=str(default_of(ABRM.MANUFACTURER_INFO)),
            guid=f"{vendor_id:04X}{int(hashlib.sha1(serial.encode()).hexdigest()[:8], 16):08X}",
        )
        self.lock = threading.RLock()
        self.registers = RegisterSpace(
            clock=clock,
            strings={ABRM.SERIAL_NUMBER: serial},
            width=self.width,
            height=self.height,
            bit_depth=self.bit_depth,
            max_fps=self.max_fps,
            temperature_c=temperature_c,
            xml=importlib.resources.files("m2s2hil.simulators").joinpath("data", XML_NAME).read_bytes(),
            zip_xml=zip_xml,
        )
        self.stream = ToucanStream(self.registers, self.faults, max_fps=self.max_fps,
                                   frame_buffer=int(frame_buffer))
        self.commands: list[u3v.Command] = []  # every GenCP command received (tests look)
        self.unplugs = 0
        self._epoch = 0
        self._absent_until: float | None = None
        self._power_on()

    # -- what tests and the rig look at ----------------------------------------------------
    @property
    def settings(self) -> Settings:
        return self.registers.settings

    @property
    def temperature_c(self) -> float | Callable[[], float]:
        return self.registers.temperature_c

    @temperature_c.setter
    def temperature_c(self, value: float | Callable[[], float]) -> None:
        self.registers.temperature_c = value

    @property
    def acquiring(self) -> bool:
        return self.stream.acquiring

    @property
    def stalled(self) -> bool:
        return self.stream.stalled

    @property
    def sent_block_ids(self) -> deque[int]:
        return self.stream.sent_block_ids  # leaders sent, in order

    @property
    def dropped_block_ids(self) -> deque[int]:
        return self.stream.dropped_block_ids  # lost in the device (buffer, faults)

    def served_file(self) -> bytes:
        """The device description file as the manifest serves it (XML or ZIP)."""
        return self.registers.served_file()

    def payload_size(self) -> int:
        return self.registers.payload_size()

    # -- life cycle ---------------------------------------------------------------------
    def _power_on(self) -> None:
        """Power-on state: defaults, stream disabled, block ids from 1."""
        self.registers.power_on()
        self._acks: deque[tuple[float, bytes]] = deque()
        self._last_ack: tuple[int, bytes] | None = None
        self.stream.power_on()

    @property
    def present(self) -> bool:
        with self.lock:
            if self._absent_until is not None and self.clock.monotonic() >= self._absent_until:
                self._absent_until = None
                self._epoch += 1  # re-enumerates: a new device for the host
                self._power_on()
            return self._absent_until is None

    @property
    def epoch(self) -> int:
        with self.lock:
            return self._epoch

    def unplug(self, duration_s: float = 1.0) -> None:
        """Leave the bus for ``duration_s`` of the clock, then re-enumerate freshly powered."""
        with self.lock:
            self.unplugs += 1
            self._absent_until = self.clock.monotonic() + float(duration_s)
            self._epoch += 1
            self._acks.clear()
            self.stream.reset()

    def usb_reset(self) -> None:
        with self.lock:
            self._acks.clear()
            self.stream.drop_transfers()

    def clear_halt(self, ep: int) -> None:
        pass  # endpoints never halt in this model

    # -- endpoints (called by the backend) ---------------------------------------------
    def _require_present(self) -> None:
        if not self.present:
            raise NoDevice(self.name)

    def write_endpoint(self, ep: int, data: bytes) -> None:
        with self.lock:
            self._require_present()
            if ep != EP_CONTROL_OUT:
                raise Halted(f"{self.name}: no OUT endpoint 0x{ep:02X}")
            if len(data) > MAX_COMMAND_TRANSFER:
                return  # longer than the device accepts: dropped, the host times out
            self._on_command(bytes(data))

    def take_endpoint(self, ep: int, max_len: int) -> bytes | memoryview | None:
        with self.lock:
            self._require_present()
            now = self.clock.monotonic()
            if ep == EP_CONTROL_IN:
                if self._acks and self._acks[0][0] <= now:
                    raw = self._acks.popleft()[1]
                    if len(raw) > max_len:  # like babble on the bus: the data is lost
                        raise Overflow(f"ack of {len(raw)} bytes, buffer {max_len}")
                    return raw
                return None
            if ep == EP_STREAM_IN:
                return self._take_stream(now, max_len)
            if ep == EP_EVENT_IN:
                return None  # no events are generated
            raise Halted(f"{self.name}: no IN endpoint 0x{ep:02X}")

    def next_due(self, ep: int) -> float | None:
        with self.lock:
            if self._absent_until is not None:
                return self._absent_until
            if ep == EP_CONTROL_IN:
                return self._acks[0][0] if self._acks else None
            if ep == EP_STREAM_IN:
                return self.stream.next_due(self.clock.monotonic())
            return None

    def _take_stream(self, now: float, max_len: int) -> bytes | memoryview | None:
        stream = self.stream
        if not stream.sending:
            unplug_s = stream.schedule(now)
            if unplug_s is not None:
                self.unplug(unplug_s)
            if not self.present:
                raise NoDevice(self.name)
            if not stream.begin_frame(self.frame_source):
                return None
        return stream.next_transfer(max_len)

    # -- GenCP --------------------------------------------------------------------------
    def _queue_ack(self, ack: u3v.Ack, delay: float = 0.0, *, final: bool = True) -> None:
        raw = ack.encode()
        if final:
            self._last_ack = (ack.request_id, raw)
            if self.faults.take("drop_reply") is not None:
                return
            late = self.faults.take("late_reply")
            if late is not None:
                delay += float(late.get("delay_s", 1.0))
        self._acks.append((self.clock.monotonic() + delay, raw))

    def _on_command(self, data: bytes) -> None:
        try:
            cmd = u3v.decode_command(data)
        except CodecError:
            if len(data) >= u3v.HEADER_SIZE:
                prefix, _f, cid, _n, rid = struct.unpack_from("<IHHHH", data)
                if prefix == u3v.CONTROL_PREFIX and not cid & 1:
                    self._queue_ack(u3v.Ack(Status.INVALID_HEADER, cid + 1, rid))
            return
        self.commands.append(cmd)
        if cmd.is_resend and self._last_ack is not None and self._last_ack[0] == cmd.request_id:
            # Already executed: repeat the answer, or say it is still pending.
            now = self.clock.monotonic()
            queued = [due for due, raw in self._acks if raw == self._last_ack[1]]
            if queued:
                wait_ms = min(0xFFFF, int((queued[0] - now) * 1000) + RESPONSE_TIME_MS)
                self._acks.appendleft((now, u3v.pending_ack(wait_ms, cmd.request_id).encode()))
            else:
                self._acks.append((now, self._last_ack[1]))
            return
        if cmd.command_id == u3v.CommandId.READMEM_CMD:
            address, length = u3v.parse_read_mem(cmd)
            if length > MAX_ACK_TRANSFER - u3v.HEADER_SIZE:
                self._queue_ack(u3v.read_mem_ack(b"", cmd.request_id, Status.INVALID_PARAMETER))
                return
            status, payload = self.registers.read(address, length)
            self._queue_ack(
                u3v.read_mem_ack(payload if status == Status.SUCCESS else b"", cmd.request_id, status)
            )
        elif cmd.command_id == u3v.CommandId.WRITEMEM_CMD:
            address, payload = u3v.parse_write_mem(cmd)
            status, delay = self._write(address, payload)
            if delay > 0:
                pending_ms = min(0xFFFF, int(delay * 1000) + RESPONSE_TIME_MS)
                self._queue_ack(u3v.pending_ack(pending_ms, cmd.request_id), final=False)
            written = len(payload) if status == Status.SUCCESS else 0
            self._queue_ack(u3v.write_mem_ack(written, cmd.request_id, status), delay)
        else:
            self._queue_ack(u3v.Ack(Status.NOT_IMPLEMENTED, cmd.command_id + 1, cmd.request_id))

    def _write(self, address: int, data: bytes) -> tuple[int, float]:
        """(status, delay before the final acknowledge); applies what the write asks of the stream."""
        stream = self.stream
        status, effect = self.registers.write(address, data, acquiring=stream.acquiring)
        if effect is Effect.START:
            stream.start(self.clock.monotonic() + self.start_delay_s)
            return status, self.start_delay_s
        if effect is Effect.STOP:
            stream.reset()
        elif effect is Effect.TRIGGER:
            stream.trigger(self.clock.monotonic())
        return status, 0.0

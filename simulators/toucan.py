"""The simulated SILIOS TOUCAN: a USB3 Vision camera seen from the wire.

It holds a GenCP register space (ABRM, SBRM, SIRM, manifest, its GenICam XML and
feature registers), answers GenCP commands on the control endpoint (PENDING_ACK for
AcquisitionStart, error statuses for bad addresses and refused writes, resend of the
last acknowledge) and streams leader + payload transfers + trailer on the stream
endpoint, timed on the injected clock. Serve it to pyusb with
:class:`~m2s2hil.simulators.u3v_backend.SimUsbBackend`.

Frame content comes from a pluggable source::

    class FrameSource(Protocol):
        def capture(self, exposure_s: float, gain: float) -> np.ndarray: ...

returning a uint16 (height, width) mosaic with values below ``2**bit_depth``; ``gain``
is the linear factor of the ``Gain`` feature. A source whose ``capture`` also takes a
``start_s`` keyword is told when the frame's exposure began (clock time: the trigger,
or the free-running frame clock), so it can render the exposure interval, motion
included; the camera renders a frame when the host starts reading it, after the
exposure. The values travel unshifted in every pixel format (Mono12/Mono16 carry the
same 10-bit numbers as Mono10).

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
import inspect
import io
import math
import struct
import threading
import zipfile
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Protocol

import numpy as np
from m2s2hil.protocols import u3v
from m2s2hil.protocols.errors import CodecError
from m2s2hil.protocols.u3v import ABRM, SBRM, SIRM, PixelFormat, Status
from m2s2hil.protocols.u3v_bootstrap import DeviceCapability, StringEncoding, encode_device_capability
from m2s2hil.simulators.fault_injection import FaultPlan
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

SBRM_ADDRESS = 0x1000
SIRM_ADDRESS = 0x2000
MANIFEST_ADDRESS = 0x3000
FILE_ADDRESS = 0x100000
FEATURES_ADDRESS = 0x10000
FEATURES_SIZE = 0x50

MAX_COMMAND_TRANSFER = 1024
MAX_ACK_TRANSFER = 1024
STREAM_ALIGNMENT = 1024
RESPONSE_TIME_MS = 200
XML_NAME = "toucan_genicam.xml"

#: What this device has, as the ABRM Device Capability register says it (GenCP 1.x bit
#: layout): a writable user-defined name, the timestamp registers (0x01F0..0x01FC), ASCII
#: strings, a family name, an SBRM, the protocol endianness register (0x0208) and a written
#: length in every WRITEMEM_ACK. No heartbeat/access privilege, message (event) channel,
#: multi-event, stacked commands or device software interface version register.
DEVICE_CAPABILITY = encode_device_capability(
    DeviceCapability.USER_DEFINED_NAME
    | DeviceCapability.TIMESTAMP
    | DeviceCapability.FAMILY_NAME
    | DeviceCapability.SBRM
    | DeviceCapability.ENDIANNESS_REGISTER
    | DeviceCapability.WRITTEN_LENGTH_FIELD,
    StringEncoding.ASCII,
)


class FeatureReg(IntEnum):
    """Feature registers (must match simulators/data/toucan_genicam.xml)."""

    WIDTH = 0x10000
    HEIGHT = 0x10004
    PIXEL_FORMAT = 0x10008
    PAYLOAD_SIZE = 0x1000C
    ACQUISITION_MODE = 0x10010
    ACQUISITION_START = 0x10014
    ACQUISITION_STOP = 0x10018
    TRIGGER_MODE = 0x1001C
    TRIGGER_SOURCE = 0x10020
    TRIGGER_SOFTWARE = 0x10024
    TRIGGER_SELECTOR = 0x10028
    EXPOSURE_TIME = 0x10030  # f64, µs
    GAIN = 0x10038  # f64, linear
    FRAME_RATE = 0x10040  # f64, Hz
    TEMPERATURE = 0x10048  # f64, °C


class FrameSource(Protocol):
    def capture(self, exposure_s: float, gain: float) -> np.ndarray: ...


class GradientSource:
    """Deterministic default content: a diagonal ramp scaled by exposure × gain.

    Full scale is reached at exposure × gain = ``full_at_s``; the result is cached per
    setting so free-running at 65 fps costs no rendering.
    """

    def __init__(self, width: int, height: int, bit_depth: int = 10, full_at_s: float = 0.05) -> None:
        self.width, self.height, self.bit_depth, self.full_at_s = width, height, bit_depth, full_at_s
        self._cache: dict[tuple[float, float], np.ndarray] = {}

    def capture(self, exposure_s: float, gain: float) -> np.ndarray:
        key = (exposure_s, gain)
        img = self._cache.get(key)
        if img is None:
            top = (1 << self.bit_depth) - 1
            level = min(1.0, exposure_s * gain / self.full_at_s)
            ramp = np.add.outer(np.arange(self.height), np.arange(self.width)).astype(np.float32)
            ramp *= top * level / max(1, self.width + self.height - 2)
            img = ramp.astype(np.uint16)
            img.setflags(write=False)
            self._cache = {key: img}
        return img


@dataclass
class _Job:
    """A frame the sensor has finished and the device will send."""

    block_id: int
    start: float  # exposure start (clock time)
    ready: float  # end of readout
    exposure_s: float
    gain: float
    pixel_format: PixelFormat
    incomplete: float | None = None  # fraction of the payload sent
    trailer_status: int = Status.SUCCESS


@dataclass
class _Settings:
    """Power-on defaults of the feature registers."""

    pixel_format: PixelFormat = PixelFormat.Mono10
    acquisition_mode: int = 0  # Continuous
    trigger_mode: int = 0
    trigger_source: int = 0
    trigger_selector: int = 0
    exposure_us: float = 10_000.0
    gain: float = 1.0
    frame_rate: float = 65.0
    user_name: str = ""


class ToucanCamera:
    """A simulated TOUCAN behind a :class:`SimUsbBackend` (see the module docstring)."""

    def __init__(
        self,
        *,
        clock: Any,
        frame_source: FrameSource | None = None,
        serial: str = "TOUCAN-0001",
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
        self.temperature_c = temperature_c
        self.start_delay_s = float(start_delay_s)
        self.frame_buffer = int(frame_buffer)
        self.identity = UsbIdentity(
            vendor_id=vendor_id,
            product_id=product_id,
            manufacturer="SILIOS",
            model="TOUCAN",
            serial=serial,
            family="TOUCAN",
            device_version="1.0.0 (simulated)",
            manufacturer_info="m2s2hil simulator",
            guid=f"{vendor_id:04X}{int(hashlib.sha1(serial.encode()).hexdigest()[:8], 16):08X}",
        )
        self.lock = threading.RLock()
        self._xml = importlib.resources.files("m2s2hil.simulators").joinpath("data", XML_NAME).read_bytes()
        self.zip_xml = zip_xml
        self._zipped: bytes | None = None
        # what tests look at
        self.sent_block_ids: deque[int] = deque(maxlen=512)  # leaders sent, in order
        self.dropped_block_ids: deque[int] = deque(maxlen=4096)  # lost in the device (buffer, faults)
        self.commands: list[u3v.Command] = []  # every GenCP command received
        self.unplugs = 0
        self._epoch = 0
        self._absent_until: float | None = None
        self._power_on()

    # -- life cycle ---------------------------------------------------------------------
    def _power_on(self) -> None:
        """Power-on state: defaults, stream disabled, block ids from 1."""
        self.settings = _Settings()
        if self.bit_depth > 10:
            self.settings.pixel_format = PixelFormat.Mono12 if self.bit_depth == 12 else PixelFormat.Mono16
        self._boot = self.clock.monotonic()
        self._latched_ts = 0
        self._acks: deque[tuple[float, bytes]] = deque()
        self._last_ack: tuple[int, bytes] | None = None
        self._sirm_host = {
            SIRM.MAX_LEADER_SIZE: 0,
            SIRM.PAYLOAD_TRANSFER_SIZE: 0,
            SIRM.PAYLOAD_TRANSFER_COUNT: 0,
            SIRM.FINAL_TRANSFER1_SIZE: 0,
            SIRM.FINAL_TRANSFER2_SIZE: 0,
            SIRM.MAX_TRAILER_SIZE: 0,
        }
        self._si_enabled = False
        self._next_block = 1
        self._reset_acquisition()

    def _reset_acquisition(self) -> None:
        self.acquiring = False
        self.stalled = False
        self._acq_t0 = 0.0
        self._frames_scheduled = 0  # free-run frames accounted for since start
        # triggered frames: (exposure start, exposure_s, gain) as set when triggered
        self._triggers: deque[tuple[float, float, float]] = deque()
        self._last_start = -math.inf
        self._last_period = 0.0  # the frame period when the last trigger was taken
        self._jobs: deque[_Job] = deque()
        self._transfers: deque[bytes | memoryview] = deque()
        self._single_done = False

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
            self._reset_acquisition()

    def usb_reset(self) -> None:
        with self.lock:
            self._acks.clear()
            self._transfers.clear()

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
                if self._transfers or self._jobs:
                    return self.clock.monotonic()
                return self._next_ready()
            return None

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
            status, payload = self._read(address, length)
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

    # -- register space ----------------------------------------------------------------
    def served_file(self) -> bytes:
        """The device description file as the manifest serves it (XML or ZIP)."""
        if not self.zip_xml:
            return self._xml
        if self._zipped is None:
            buf = io.BytesIO()
            with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
                info = zipfile.ZipInfo(XML_NAME, date_time=(2026, 1, 1, 0, 0, 0))
                zf.writestr(info, self._xml, zipfile.ZIP_DEFLATED)
            self._zipped = buf.getvalue()
        return self._zipped

    def payload_size(self) -> int:
        return u3v.payload_size(self.settings.pixel_format, self.width, self.height)

    def _timestamp(self) -> int:
        return round((self.clock.monotonic() - self._boot) * 1e9)

    def _temperature(self) -> float:
        t = self.temperature_c
        return float(t() if callable(t) else t)

    def _regions(self) -> list[tuple[int, Callable[[], bytes]]]:
        """(base address, contents) by descending base."""
        return [
            (FILE_ADDRESS, self.served_file),
            (FEATURES_ADDRESS, self._features),
            (MANIFEST_ADDRESS, self._manifest),
            (SIRM_ADDRESS, self._sirm),
            (SBRM_ADDRESS, self._sbrm),
            (0, self._abrm),
        ]

    def _read(self, address: int, length: int) -> tuple[int, bytes]:
        for base, build in self._regions():
            if address >= base:
                blob = build()
                if address + length <= base + len(blob):
                    return Status.SUCCESS, blob[address - base : address - base + length]
                break
        return Status.INVALID_ADDRESS, b""

    def _abrm(self) -> bytes:
        s = self.settings
        b = bytearray(u3v.ABRM_SIZE)
        struct.pack_into("<I", b, ABRM.GENCP_VERSION, 0x00010002)
        for off, text in (
            (ABRM.MANUFACTURER_NAME, self.identity.manufacturer),
            (ABRM.MODEL_NAME, self.identity.model),
            (ABRM.FAMILY_NAME, self.identity.family),
            (ABRM.DEVICE_VERSION, self.identity.device_version),
            (ABRM.MANUFACTURER_INFO, self.identity.manufacturer_info),
            (ABRM.SERIAL_NUMBER, self.serial),
            (ABRM.USER_DEFINED_NAME, s.user_name),
        ):
            b[off : off + u3v.STRING_LENGTH] = u3v.encode_string(text)
        struct.pack_into("<Q", b, ABRM.DEVICE_CAPABILITY, DEVICE_CAPABILITY)
        struct.pack_into("<I", b, ABRM.MAX_DEVICE_RESPONSE_TIME, RESPONSE_TIME_MS)
        struct.pack_into("<Q", b, ABRM.MANIFEST_TABLE_ADDRESS, MANIFEST_ADDRESS)
        struct.pack_into("<Q", b, ABRM.SBRM_ADDRESS, SBRM_ADDRESS)
        struct.pack_into("<Q", b, ABRM.TIMESTAMP, self._latched_ts)
        struct.pack_into("<Q", b, ABRM.TIMESTAMP_INCREMENT, 1)  # 1 ns per tick
        struct.pack_into("<I", b, ABRM.PROTOCOL_ENDIANNESS, 0xFFFFFFFF)  # little-endian
        return bytes(b)

    def _sbrm(self) -> bytes:
        b = bytearray(u3v.SBRM_SIZE)
        struct.pack_into("<I", b, SBRM.U3V_VERSION, 0x00010000)
        struct.pack_into("<Q", b, SBRM.U3VCP_CAPABILITY, 0x1)  # SIRM available
        struct.pack_into("<I", b, SBRM.MAX_COMMAND_TRANSFER_LENGTH, MAX_COMMAND_TRANSFER)
        struct.pack_into("<I", b, SBRM.MAX_ACK_TRANSFER_LENGTH, MAX_ACK_TRANSFER)
        struct.pack_into("<I", b, SBRM.NUM_STREAM_CHANNELS, 1)
        struct.pack_into("<Q", b, SBRM.SIRM_ADDRESS, SIRM_ADDRESS)
        struct.pack_into("<I", b, SBRM.SIRM_LENGTH, u3v.SIRM_SIZE)
        return bytes(b)

    def _sirm(self) -> bytes:
        b = bytearray(u3v.SIRM_SIZE)
        struct.pack_into("<I", b, SIRM.INFO, u3v.sirm_info(STREAM_ALIGNMENT))
        struct.pack_into("<I", b, SIRM.CONTROL, u3v.SI_CONTROL_ENABLE if self._si_enabled else 0)
        struct.pack_into("<Q", b, SIRM.REQUIRED_PAYLOAD_SIZE, self.payload_size())
        struct.pack_into("<I", b, SIRM.REQUIRED_LEADER_SIZE, u3v.IMAGE_LEADER_SIZE)
        struct.pack_into("<I", b, SIRM.REQUIRED_TRAILER_SIZE, u3v.IMAGE_TRAILER_SIZE)
        for off, value in self._sirm_host.items():
            struct.pack_into("<I", b, off, value)
        return bytes(b)

    def _manifest(self) -> bytes:
        blob = self.served_file()
        entry = u3v.ManifestEntry(
            address=FILE_ADDRESS,
            size=len(blob),
            file_format=u3v.FileFormat.ZIP if self.zip_xml else u3v.FileFormat.XML,
            version=(1, 0, 0),
            schema=(1, 1),
            sha1=hashlib.sha1(blob).digest(),
        )
        return u3v.encode_manifest([entry])

    def _features(self) -> bytes:
        s = self.settings
        b = bytearray(FEATURES_SIZE)
        for reg, value in (
            (FeatureReg.WIDTH, self.width),
            (FeatureReg.HEIGHT, self.height),
            (FeatureReg.PIXEL_FORMAT, int(s.pixel_format)),
            (FeatureReg.PAYLOAD_SIZE, self.payload_size()),
            (FeatureReg.ACQUISITION_MODE, s.acquisition_mode),
            (FeatureReg.TRIGGER_MODE, s.trigger_mode),
            (FeatureReg.TRIGGER_SOURCE, s.trigger_source),
            (FeatureReg.TRIGGER_SELECTOR, s.trigger_selector),
        ):
            struct.pack_into("<I", b, reg - FEATURES_ADDRESS, value)
        for reg, fvalue in (
            (FeatureReg.EXPOSURE_TIME, s.exposure_us),
            (FeatureReg.GAIN, s.gain),
            (FeatureReg.FRAME_RATE, s.frame_rate),
            (FeatureReg.TEMPERATURE, self._temperature()),
        ):
            struct.pack_into("<d", b, reg - FEATURES_ADDRESS, fvalue)
        return bytes(b)  # command registers read 0: done

    def _write(self, address: int, data: bytes) -> tuple[int, float]:
        """(status, delay before the final acknowledge)."""
        s = self.settings
        n = len(data)
        if address == ABRM.USER_DEFINED_NAME and n <= u3v.STRING_LENGTH:
            s.user_name = data.split(b"\0", 1)[0].decode("ascii", "replace")
            return Status.SUCCESS, 0.0
        if address == ABRM.TIMESTAMP_LATCH and n == 4:
            self._latched_ts = self._timestamp()
            return Status.SUCCESS, 0.0
        if SIRM_ADDRESS <= address < SIRM_ADDRESS + u3v.SIRM_SIZE:
            return self._write_sirm(address - SIRM_ADDRESS, data), 0.0
        if FEATURES_ADDRESS <= address < FEATURES_ADDRESS + FEATURES_SIZE:
            return self._write_feature(address, data)
        if self._read(address, max(n, 1))[0] == Status.SUCCESS:
            return Status.WRITE_PROTECT, 0.0
        return Status.INVALID_ADDRESS, 0.0

    def _write_sirm(self, offset: int, data: bytes) -> int:
        if len(data) != 4:
            return Status.INVALID_PARAMETER
        (value,) = struct.unpack("<I", data)
        if offset == SIRM.CONTROL:
            if value & u3v.SI_CONTROL_ENABLE:
                status = self._check_stream_config()
                if status != Status.SUCCESS:
                    return status
                self._si_enabled = True
            else:
                self._si_enabled = False
                self._reset_acquisition()
            return Status.SUCCESS
        if offset in self._sirm_host:
            if self._si_enabled:
                return Status.ACCESS_DENIED
            self._sirm_host[SIRM(offset)] = value
            return Status.SUCCESS
        return Status.WRITE_PROTECT

    def _check_stream_config(self) -> int:
        h = self._sirm_host
        size, count = h[SIRM.PAYLOAD_TRANSFER_SIZE], h[SIRM.PAYLOAD_TRANSFER_COUNT]
        f1, f2 = h[SIRM.FINAL_TRANSFER1_SIZE], h[SIRM.FINAL_TRANSFER2_SIZE]
        if any(v % STREAM_ALIGNMENT for v in (size, f1, f2)):
            return Status.PAYLOAD_SIZE_NOT_ALIGNED
        if (
            h[SIRM.MAX_LEADER_SIZE] < u3v.IMAGE_LEADER_SIZE
            or h[SIRM.MAX_TRAILER_SIZE] < u3v.IMAGE_TRAILER_SIZE
            or size * count + f1 + f2 < self.payload_size()
            or (count and not size)
        ):
            return Status.STREAM_REGISTERS_INCONSISTENT
        return Status.SUCCESS

    def _write_feature(self, address: int, data: bytes) -> tuple[int, float]:
        s = self.settings
        try:
            reg = FeatureReg(address)
        except ValueError:
            return Status.INVALID_ADDRESS, 0.0
        if reg in (FeatureReg.EXPOSURE_TIME, FeatureReg.GAIN, FeatureReg.FRAME_RATE):
            if len(data) != 8:
                return Status.INVALID_PARAMETER, 0.0
            (f,) = struct.unpack("<d", data)
            lo, hi = {
                FeatureReg.EXPOSURE_TIME: (100.0, 5_000_000.0),
                FeatureReg.GAIN: (1.0, 16.0),
                FeatureReg.FRAME_RATE: (0.1, self.max_fps),
            }[reg]
            if not lo <= f <= hi:
                return Status.INVALID_PARAMETER, 0.0
            if reg is FeatureReg.EXPOSURE_TIME:
                s.exposure_us = f
            elif reg is FeatureReg.GAIN:
                s.gain = f
            else:
                s.frame_rate = f
            return Status.SUCCESS, 0.0
        if len(data) != 4:
            return Status.INVALID_PARAMETER, 0.0
        (v,) = struct.unpack("<I", data)
        if reg is FeatureReg.PIXEL_FORMAT:
            try:
                fmt = PixelFormat(v)
            except ValueError:
                return Status.INVALID_PARAMETER, 0.0
            if fmt is PixelFormat.Mono8 or fmt.depth < self.bit_depth:
                return Status.INVALID_PARAMETER, 0.0
            if self._si_enabled or self.acquiring:
                return Status.ACCESS_DENIED, 0.0  # payload size is locked while streaming is set up
            s.pixel_format = fmt
            return Status.SUCCESS, 0.0
        if reg is FeatureReg.ACQUISITION_MODE:
            if v not in (0, 1):
                return Status.INVALID_PARAMETER, 0.0
            if self.acquiring:
                return Status.ACCESS_DENIED, 0.0
            s.acquisition_mode = v
            return Status.SUCCESS, 0.0
        if reg is FeatureReg.TRIGGER_MODE:
            if v not in (0, 1):
                return Status.INVALID_PARAMETER, 0.0
            s.trigger_mode = v
            return Status.SUCCESS, 0.0
        if reg in (FeatureReg.TRIGGER_SOURCE, FeatureReg.TRIGGER_SELECTOR):
            if v != 0:
                return Status.INVALID_PARAMETER, 0.0
            return Status.SUCCESS, 0.0
        if reg is FeatureReg.ACQUISITION_START:
            if not self._si_enabled:
                return Status.WRONG_CONFIG, 0.0  # stream interface not enabled
            if not self.acquiring:
                self._reset_acquisition()
                self.acquiring = True
                self._acq_t0 = self.clock.monotonic() + self.start_delay_s
            return Status.SUCCESS, self.start_delay_s
        if reg is FeatureReg.ACQUISITION_STOP:
            self._reset_acquisition()
            return Status.SUCCESS, 0.0
        if reg is FeatureReg.TRIGGER_SOFTWARE:
            if not self.acquiring or s.trigger_mode != 1:
                return Status.ACCESS_DENIED, 0.0
            now = max(self.clock.monotonic(), self._acq_t0)
            # The previous frame occupies the sensor for ITS period (its own exposure), not
            # the one just configured: a long exposure after a short one starts at once.
            start = max(now, self._last_start + self._last_period)
            self._last_start = start
            self._last_period = self._period()
            self._triggers.append((start, self._exposure_s(), s.gain))
            return Status.SUCCESS, 0.0
        return Status.WRITE_PROTECT, 0.0  # width, height, payload size, temperature

    # -- streaming ----------------------------------------------------------------------
    def _exposure_s(self) -> float:
        return self.settings.exposure_us * 1e-6

    def _period(self) -> float:
        return max(1.0 / self.settings.frame_rate, self._exposure_s())

    def _readout_s(self) -> float:
        return 1.0 / self.max_fps

    def _next_ready(self) -> float | None:
        """When the next frame finishes (None if none is coming)."""
        if not self.acquiring or self.stalled or not self._si_enabled or self._single_done:
            return None
        if self.settings.trigger_mode == 1:
            if not self._triggers:
                return None
            start, exposure, _gain = self._triggers[0]
            return start + exposure + self._readout_s()
        tail = self._exposure_s() + self._readout_s()
        return self._acq_t0 + self._frames_scheduled * self._period() + tail

    def _schedule(self, now: float) -> None:
        """Turn frames finished by ``now`` into jobs (faults are drawn here)."""
        self._skip_overflow(now)
        while True:
            ready = self._next_ready()
            if ready is None or ready > now:
                return
            if self.settings.trigger_mode == 1:
                start, exposure, gain = self._triggers.popleft()
            else:
                start = self._acq_t0 + self._frames_scheduled * self._period()
                exposure, gain = self._exposure_s(), self.settings.gain
                self._frames_scheduled += 1
            if self.settings.acquisition_mode == 1:
                self._single_done = True
            block_id = self._next_block
            self._next_block += 1
            if self._frame_faults(block_id, start, ready, exposure, gain):
                return
            if self._single_done:
                self.acquiring = False

    def _skip_overflow(self, now: float) -> None:
        """Free-running with a full buffer: drop the frames due by ``now`` in one step."""
        if (
            self.settings.trigger_mode == 1
            or self.settings.acquisition_mode == 1
            or len(self._jobs) < self.frame_buffer
            or any(self.faults.pending(k) for k in ("unplug", "stall", "frame_timeout"))
        ):
            return
        ready = self._next_ready()
        if ready is None or ready > now:
            return
        n = int((now - ready) / self._period()) + 1
        self.dropped_block_ids.extend(range(self._next_block, self._next_block + n))
        self._next_block += n
        self._frames_scheduled += n

    def _frame_faults(self, block_id: int, start: float, ready: float, exposure: float, gain: float) -> bool:
        """Apply this frame's faults and queue it; True if the device left the bus."""
        unplug = self.faults.take("unplug")
        if unplug is not None:
            self.dropped_block_ids.append(block_id)
            self.unplug(float(unplug.get("duration_s", 1.0)))
            return True
        if self.faults.take("stall") is not None:
            self.stalled = True
            self.dropped_block_ids.append(block_id)
            return False
        if self.faults.take("frame_timeout") is not None or len(self._jobs) >= self.frame_buffer:
            self.dropped_block_ids.append(block_id)
            return False
        job = _Job(block_id, start, ready, exposure, gain, self.settings.pixel_format)
        inc = self.faults.take("incomplete")
        if inc is not None:
            job.incomplete = float(inc.get("fraction", 0.5))
        err = self.faults.take("trailer_error")
        if err is not None:
            job.trailer_status = int(err.get("status", Status.DATA_DISCARDED))
        self._jobs.append(job)
        return False

    def _take_stream(self, now: float, max_len: int) -> bytes | memoryview | None:
        if not self._transfers:
            self._schedule(now)
            if not self.present:
                raise NoDevice(self.name)
            if not self._jobs:
                return None
            self._transfers.extend(self._render(self._jobs.popleft()))
        chunk = self._transfers.popleft()
        if len(chunk) > max_len:  # like babble on the bus: the transfer is lost
            raise Overflow(f"stream transfer of {len(chunk)} bytes, buffer {max_len}")
        return chunk

    def _render(self, job: _Job) -> list[bytes | memoryview]:
        if _takes_start(self.frame_source):
            img = self.frame_source.capture(job.exposure_s, job.gain, start_s=job.start)
        else:
            img = self.frame_source.capture(job.exposure_s, job.gain)
        if img.shape != (self.height, self.width):
            raise ValueError(f"frame source gave {img.shape}, camera is {self.height}x{self.width}")
        payload = memoryview(u3v.encode_image(img, job.pixel_format)).cast("B")
        total = len(payload)
        send = total if job.incomplete is None else int(total * job.incomplete)
        h = self._sirm_host
        sizes = [h[SIRM.PAYLOAD_TRANSFER_SIZE]] * h[SIRM.PAYLOAD_TRANSFER_COUNT]
        sizes += [h[SIRM.FINAL_TRANSFER1_SIZE], h[SIRM.FINAL_TRANSFER2_SIZE]]
        leader = u3v.ImageLeader(
            block_id=job.block_id,
            timestamp=round((job.start - self._boot) * 1e9),
            pixel_format=int(job.pixel_format),
            size_x=self.width,
            size_y=self.height,
        )
        out: list[bytes | memoryview] = [leader.encode()]
        pos = 0
        for size in sizes:
            if pos >= send or size == 0:
                continue
            out.append(payload[pos : min(pos + size, send)])
            pos = min(pos + size, send)
        # A short payload keeps status 0: the host must notice the valid size itself.
        out.append(u3v.Trailer(job.block_id, job.trailer_status, pos, self.height).encode())
        self.sent_block_ids.append(job.block_id)
        return out


def _takes_start(source: Any) -> bool:
    """Whether ``source.capture`` accepts the ``start_s`` keyword."""
    try:
        params = inspect.signature(source.capture).parameters
    except (TypeError, ValueError):
        return False
    return "start_s" in params or any(p.kind is p.VAR_KEYWORD for p in params.values())

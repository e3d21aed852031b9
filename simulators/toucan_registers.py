"""The simulated TOUCAN's register space: what a GenCP read answers and what a write does.

The registers are those of the table in :mod:`~m2s2hil.simulators.toucan_register_map`; this
module holds their state (the writable settings, the host-written SIRM registers, the stream
enable, the latched timestamp), lays out the memory map (ABRM, SBRM, SIRM, manifest, features,
the GenICam file) and checks writes. A write that acts on the stream (AcquisitionStart, Stop,
TriggerSoftware, disabling the stream interface) returns an :class:`Effect` for the device to
apply, so the register space knows nothing of stream timing.
"""

from __future__ import annotations

import hashlib
import io
import struct
import zipfile
from collections.abc import Callable
from enum import Enum
from typing import Any

from m2s2hil.protocols import u3v
from m2s2hil.protocols.u3v import ABRM, SIRM, PixelFormat, Status
from m2s2hil.simulators.toucan_register_map import (
    BY_ADDRESS,
    FEATURES_ADDRESS,
    FEATURES_SIZE,
    FILE_ADDRESS,
    MANIFEST_ADDRESS,
    SBRM_ADDRESS,
    SIRM_ADDRESS,
    STREAM_ALIGNMENT,
    FeatureReg,
    Settings,
    Value,
    encode_block,
)

XML_NAME = "toucan_genicam.xml"

#: The SIRM registers the host writes before it enables the stream.
HOST_SIRM = (
    SIRM.MAX_LEADER_SIZE,
    SIRM.PAYLOAD_TRANSFER_SIZE,
    SIRM.PAYLOAD_TRANSFER_COUNT,
    SIRM.FINAL_TRANSFER1_SIZE,
    SIRM.FINAL_TRANSFER2_SIZE,
    SIRM.MAX_TRAILER_SIZE,
)


class Effect(Enum):
    """What a successful write asks of the stream."""

    START = "start"  # AcquisitionStart
    STOP = "stop"  # AcquisitionStop, or the stream interface disabled
    TRIGGER = "trigger"  # TriggerSoftware


class RegisterSpace:
    """The registers of one camera (see the module docstring); :meth:`power_on` resets them."""

    def __init__(
        self,
        *,
        clock: Any,
        strings: dict[int, str],
        width: int,
        height: int,
        bit_depth: int,
        max_fps: float,
        temperature_c: float | Callable[[], float],
        xml: bytes,
        zip_xml: bool,
    ) -> None:
        self.clock = clock
        self.strings = strings  # ABRM string address -> this device's text (serial, names)
        self.width, self.height, self.bit_depth = width, height, bit_depth
        self.max_fps = max_fps
        self.temperature_c = temperature_c
        self._xml = xml
        self.zip_xml = zip_xml
        self._zipped: bytes | None = None
        self.power_on()

    def power_on(self) -> None:
        """Defaults, stream interface disabled, timestamps counted from now."""
        self.settings = Settings()
        if self.bit_depth > 10:
            self.settings.pixel_format = PixelFormat.Mono12 if self.bit_depth == 12 else PixelFormat.Mono16
        self.boot = self.clock.monotonic()
        self._latched_ts = 0
        self.sirm_host: dict[SIRM, int] = dict.fromkeys(HOST_SIRM, 0)
        self.si_enabled = False

    # -- values ---------------------------------------------------------------------------
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

    def timestamp(self) -> int:
        return round((self.clock.monotonic() - self.boot) * 1e9)

    def _temperature(self) -> float:
        t = self.temperature_c
        return float(t() if callable(t) else t)

    def _values(self) -> dict[int, Value]:
        """The registers whose value is this device's or live (the others hold their default)."""
        s = self.settings
        values: dict[int, Value] = dict(self.strings)
        values[ABRM.USER_DEFINED_NAME] = s.user_name
        values[ABRM.TIMESTAMP] = self._latched_ts
        values[SIRM_ADDRESS + SIRM.CONTROL] = u3v.SI_CONTROL_ENABLE if self.si_enabled else 0
        values[SIRM_ADDRESS + SIRM.REQUIRED_PAYLOAD_SIZE] = self.payload_size()
        for off, v in self.sirm_host.items():
            values[SIRM_ADDRESS + off] = v
        values.update({
            FeatureReg.WIDTH: self.width,
            FeatureReg.HEIGHT: self.height,
            FeatureReg.PIXEL_FORMAT: int(s.pixel_format),
            FeatureReg.PAYLOAD_SIZE: self.payload_size(),
            FeatureReg.ACQUISITION_MODE: s.acquisition_mode,
            FeatureReg.TRIGGER_MODE: s.trigger_mode,
            FeatureReg.TRIGGER_SOURCE: s.trigger_source,
            FeatureReg.TRIGGER_SELECTOR: s.trigger_selector,
            FeatureReg.EXPOSURE_TIME: s.exposure_us,
            FeatureReg.GAIN: s.gain,
            FeatureReg.FRAME_RATE: s.frame_rate,
            FeatureReg.TEMPERATURE: self._temperature(),
        })
        return values

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

    def _regions(self) -> list[tuple[int, Callable[[], bytes]]]:
        """(base address, contents) by descending base."""

        def block(base: int, size: int) -> Callable[[], bytes]:
            return lambda: encode_block(base, size, self._values())

        return [
            (FILE_ADDRESS, self.served_file),
            (FEATURES_ADDRESS, block(FEATURES_ADDRESS, FEATURES_SIZE)),
            (MANIFEST_ADDRESS, self._manifest),
            (SIRM_ADDRESS, block(SIRM_ADDRESS, u3v.SIRM_SIZE)),
            (SBRM_ADDRESS, block(SBRM_ADDRESS, u3v.SBRM_SIZE)),
            (0, block(0, u3v.ABRM_SIZE)),
        ]

    # -- GenCP reads and writes -------------------------------------------------------------
    def read(self, address: int, length: int) -> tuple[int, bytes]:
        for base, build in self._regions():
            if address >= base:
                blob = build()
                if address + length <= base + len(blob):
                    return Status.SUCCESS, blob[address - base : address - base + length]
                break
        return Status.INVALID_ADDRESS, b""

    def write(self, address: int, data: bytes, *, acquiring: bool) -> tuple[int, Effect | None]:
        """(status, what the stream must do); ``acquiring``: whether the stream is running."""
        n = len(data)
        if address == ABRM.USER_DEFINED_NAME and n <= u3v.STRING_LENGTH:
            self.settings.user_name = data.split(b"\0", 1)[0].decode("ascii", "replace")
            return Status.SUCCESS, None
        if address == ABRM.TIMESTAMP_LATCH and n == 4:
            self._latched_ts = self.timestamp()
            return Status.SUCCESS, None
        if SIRM_ADDRESS <= address < SIRM_ADDRESS + u3v.SIRM_SIZE:
            return self._write_sirm(address - SIRM_ADDRESS, data)
        if FEATURES_ADDRESS <= address < FEATURES_ADDRESS + FEATURES_SIZE:
            return self._write_feature(address, data, acquiring)
        if self.read(address, max(n, 1))[0] == Status.SUCCESS:
            return Status.WRITE_PROTECT, None
        return Status.INVALID_ADDRESS, None

    def _write_sirm(self, offset: int, data: bytes) -> tuple[int, Effect | None]:
        if len(data) != 4:
            return Status.INVALID_PARAMETER, None
        (value,) = struct.unpack("<I", data)
        if offset == SIRM.CONTROL:
            if value & u3v.SI_CONTROL_ENABLE:
                status = self._check_stream_config()
                if status != Status.SUCCESS:
                    return status, None
                self.si_enabled = True
                return Status.SUCCESS, None
            self.si_enabled = False
            return Status.SUCCESS, Effect.STOP
        if offset in self.sirm_host:
            if self.si_enabled:
                return Status.ACCESS_DENIED, None
            self.sirm_host[SIRM(offset)] = value
            return Status.SUCCESS, None
        return Status.WRITE_PROTECT, None

    def _check_stream_config(self) -> int:
        h = self.sirm_host
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

    def _write_float(self, reg: FeatureReg, data: bytes) -> int:
        if len(data) != 8:
            return Status.INVALID_PARAMETER
        (f,) = struct.unpack("<d", data)
        entry = BY_ADDRESS[reg]
        top = self.max_fps if reg is FeatureReg.FRAME_RATE else entry.maximum
        assert entry.minimum is not None and top is not None
        if not entry.minimum <= f <= top:
            return Status.INVALID_PARAMETER
        s = self.settings
        if reg is FeatureReg.EXPOSURE_TIME:
            s.exposure_us = f
        elif reg is FeatureReg.GAIN:
            s.gain = f
        else:
            s.frame_rate = f
        return Status.SUCCESS

    def _write_feature(self, address: int, data: bytes, acquiring: bool) -> tuple[int, Effect | None]:
        try:
            reg = FeatureReg(address)
        except ValueError:
            return Status.INVALID_ADDRESS, None
        if reg in (FeatureReg.EXPOSURE_TIME, FeatureReg.GAIN, FeatureReg.FRAME_RATE):
            return self._write_float(reg, data), None
        if len(data) != 4:
            return Status.INVALID_PARAMETER, None
        if reg in (FeatureReg.ACQUISITION_START, FeatureReg.ACQUISITION_STOP, FeatureReg.TRIGGER_SOFTWARE):
            return self._command(reg, acquiring)
        return self._write_u32(reg, struct.unpack("<I", data)[0], acquiring), None

    def _write_u32(self, reg: FeatureReg, v: int, acquiring: bool) -> int:
        s = self.settings
        if reg is FeatureReg.PIXEL_FORMAT:
            try:
                fmt = PixelFormat(v)
            except ValueError:
                return Status.INVALID_PARAMETER
            if fmt is PixelFormat.Mono8 or fmt.depth < self.bit_depth:
                return Status.INVALID_PARAMETER
            if self.si_enabled or acquiring:
                return Status.ACCESS_DENIED  # payload size is locked while streaming is set up
            s.pixel_format = fmt
            return Status.SUCCESS
        if reg is FeatureReg.ACQUISITION_MODE:
            if v not in (0, 1):
                return Status.INVALID_PARAMETER
            if acquiring:
                return Status.ACCESS_DENIED
            s.acquisition_mode = v
            return Status.SUCCESS
        if reg is FeatureReg.TRIGGER_MODE:
            if v not in (0, 1):
                return Status.INVALID_PARAMETER
            s.trigger_mode = v
            return Status.SUCCESS
        if reg in (FeatureReg.TRIGGER_SOURCE, FeatureReg.TRIGGER_SELECTOR):
            return Status.INVALID_PARAMETER if v != 0 else Status.SUCCESS
        return Status.WRITE_PROTECT  # width, height, payload size, temperature

    def _command(self, reg: FeatureReg, acquiring: bool) -> tuple[int, Effect | None]:
        """A write of a command register: AcquisitionStart, AcquisitionStop, TriggerSoftware."""
        if reg is FeatureReg.ACQUISITION_START:
            if not self.si_enabled:
                return Status.WRONG_CONFIG, None  # stream interface not enabled
            return Status.SUCCESS, Effect.START
        if reg is FeatureReg.ACQUISITION_STOP:
            return Status.SUCCESS, Effect.STOP
        if not acquiring or self.settings.trigger_mode != 1:
            return Status.ACCESS_DENIED, None
        return Status.SUCCESS, Effect.TRIGGER

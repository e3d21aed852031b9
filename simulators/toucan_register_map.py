"""The simulated TOUCAN's register map, as a table: every register the device implements, its
address, width, access, power-on default and the document each fact comes from.

The keys of ``source`` are those of docs/simulators.md ("Sources"): ``u3v`` the USB3 Vision /
GenCP layouts in hardware-notes.md, ``gencp`` GenCP 1.x's ABRM, ``toucan`` the camera's own
figures in hardware-notes.md (2048×2048, up to 65 frames/s, exposure 100 µs … 5 s, 10-bit);
``assumed`` marks what no document at hand gives (the TOUCAN's feature registers are this
simulator's, laid out as its GenICam XML, ``data/toucan_genicam.xml``, says).

A register's default is what a :class:`~m2s2hil.simulators.toucan.ToucanCamera` built with its
own defaults answers at power-on; a device answers its own values where it has them (serial,
sensor size, the live payload size and temperature). Bytes no register covers read 0;
command registers read 0 too ("done").
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum, StrEnum

from m2s2hil.protocols import u3v
from m2s2hil.protocols.u3v import ABRM, SBRM, SIRM, PixelFormat
from m2s2hil.protocols.u3v_bootstrap import DeviceCapability, StringEncoding, encode_device_capability

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


class Access(StrEnum):
    RO = "RO"
    RW = "RW"
    WO = "WO"  # a command: executed by a write, reads 0


class Kind(StrEnum):
    UINT = "uint"  # little-endian, 4 or 8 bytes
    FLOAT = "float"  # IEEE 754 double
    STRING = "string"  # ASCII, NUL-padded


Value = int | float | str


@dataclass(frozen=True)
class Register:
    """One register: where, how wide, how encoded, who may write it, its power-on default."""

    address: int  # absolute
    name: str
    width: int  # bytes
    kind: Kind
    access: Access
    default: Value
    source: str
    minimum: float | None = None  # a float register's writable range
    maximum: float | None = None

    @property
    def readable(self) -> bool:
        return self.access is not Access.WO

    def encode(self, value: Value) -> bytes:
        if self.kind is Kind.STRING:
            return u3v.encode_string(str(value), self.width)
        if self.kind is Kind.FLOAT:
            return struct.pack("<d", float(value))
        return int(value).to_bytes(self.width, "little")

    def decode(self, raw: bytes) -> Value:
        if self.kind is Kind.STRING:
            return u3v.decode_string(raw)
        if self.kind is Kind.FLOAT:
            return float(struct.unpack("<d", raw)[0])
        return int.from_bytes(raw, "little")


_S, _U, _F = Kind.STRING, Kind.UINT, Kind.FLOAT
_RO, _RW, _WO = Access.RO, Access.RW, Access.WO
_STR = u3v.STRING_LENGTH

REGISTERS: tuple[Register, ...] = (
    # ABRM, absolute addresses
    Register(ABRM.GENCP_VERSION, "GenCPVersion", 4, _U, _RO, 0x00010002, "u3v: ABRM 0x0000 GenCP version"),
    Register(ABRM.MANUFACTURER_NAME, "ManufacturerName", _STR, _S, _RO, "SILIOS",
             "u3v: ABRM 0x0004; toucan: the vendor"),
    Register(ABRM.MODEL_NAME, "ModelName", _STR, _S, _RO, "TOUCAN", "u3v: ABRM 0x0044; toucan: the model"),
    Register(ABRM.FAMILY_NAME, "FamilyName", _STR, _S, _RO, "TOUCAN",
             "u3v: ABRM 0x0084; assumed: the family"),
    Register(ABRM.DEVICE_VERSION, "DeviceVersion", _STR, _S, _RO, "1.0.0 (simulated)",
             "u3v: ABRM 0x00C4; assumed: the text"),
    Register(ABRM.MANUFACTURER_INFO, "ManufacturerInfo", _STR, _S, _RO, "m2s2hil simulator",
             "u3v: ABRM 0x0104; assumed: the text"),
    Register(ABRM.SERIAL_NUMBER, "SerialNumber", _STR, _S, _RO, "TOUCAN-0001",
             "u3v: ABRM 0x0144; assumed: the default serial (each device has its own)"),
    Register(ABRM.USER_DEFINED_NAME, "UserDefinedName", _STR, _S, _RW, "",
             "u3v: ABRM 0x0184; gencp: writable (capability bit 0)"),
    Register(ABRM.DEVICE_CAPABILITY, "DeviceCapability", 8, _U, _RO, DEVICE_CAPABILITY,
             "u3v: ABRM 0x01C4; gencp: its bits"),
    Register(ABRM.MAX_DEVICE_RESPONSE_TIME, "MaxDeviceResponseTime", 4, _U, _RO, RESPONSE_TIME_MS,
             "u3v: ABRM 0x01CC (ms); assumed: 200 ms"),
    Register(ABRM.MANIFEST_TABLE_ADDRESS, "ManifestTableAddress", 8, _U, _RO, MANIFEST_ADDRESS,
             "u3v: ABRM 0x01D0; assumed: the address"),
    Register(ABRM.SBRM_ADDRESS, "SBRMAddress", 8, _U, _RO, SBRM_ADDRESS,
             "u3v: ABRM 0x01D8; assumed: the address"),
    Register(ABRM.TIMESTAMP, "Timestamp", 8, _U, _RO, 0,
             "u3v: ABRM 0x01F0; gencp: the value latched by TimestampLatch (ns since power-on here)"),
    Register(ABRM.TIMESTAMP_LATCH, "TimestampLatch", 4, _U, _WO, 0, "gencp: ABRM 0x01F8 (capability bit 3)"),
    Register(ABRM.TIMESTAMP_INCREMENT, "TimestampIncrement", 8, _U, _RO, 1,
             "gencp: ABRM 0x01FC, ns per tick; assumed: 1 ns"),
    Register(ABRM.PROTOCOL_ENDIANNESS, "ProtocolEndianness", 4, _U, _RO, 0xFFFFFFFF,
             "gencp: ABRM 0x0208 (capability bit 10), 0xFFFFFFFF = little-endian; u3v: little-endian"),
    # SBRM
    Register(SBRM_ADDRESS + SBRM.U3V_VERSION, "U3VVersion", 4, _U, _RO, 0x00010000,
             "u3v: SBRM 0x00 (offset as protocols/u3v_bootstrap.py); assumed: version 1.0"),
    Register(SBRM_ADDRESS + SBRM.U3VCP_CAPABILITY, "U3VCPCapability", 8, _U, _RO, 0x1,
             "u3v: SBRM 0x04, bit 0 = SIRM present"),
    Register(SBRM_ADDRESS + SBRM.MAX_COMMAND_TRANSFER_LENGTH, "MaxCommandTransferLength", 4, _U, _RO,
             MAX_COMMAND_TRANSFER, "u3v: SBRM 0x14; assumed: 1024 bytes"),
    Register(SBRM_ADDRESS + SBRM.MAX_ACK_TRANSFER_LENGTH, "MaxAckTransferLength", 4, _U, _RO,
             MAX_ACK_TRANSFER, "u3v: SBRM 0x18; assumed: 1024 bytes"),
    Register(SBRM_ADDRESS + SBRM.NUM_STREAM_CHANNELS, "NumStreamChannels", 4, _U, _RO, 1, "u3v: SBRM 0x1C"),
    Register(SBRM_ADDRESS + SBRM.SIRM_ADDRESS, "SIRMAddress", 8, _U, _RO, SIRM_ADDRESS,
             "u3v: SBRM 0x20; assumed: the address"),
    Register(SBRM_ADDRESS + SBRM.SIRM_LENGTH, "SIRMLength", 4, _U, _RO, u3v.SIRM_SIZE, "u3v: SBRM 0x28"),
    # SIRM
    Register(SIRM_ADDRESS + SIRM.INFO, "SIInfo", 4, _U, _RO, u3v.sirm_info(STREAM_ALIGNMENT),
             "u3v: SIRM 0x00, bits 24..31 = log2 alignment; assumed: 1024-byte alignment"),
    Register(SIRM_ADDRESS + SIRM.CONTROL, "SIControl", 4, _U, _RW, 0,
             "u3v: SIRM 0x04, bit 0 = stream enable"),
    Register(SIRM_ADDRESS + SIRM.REQUIRED_PAYLOAD_SIZE, "SIRequiredPayloadSize", 8, _U, _RO, 2048 * 2048 * 2,
             "u3v: SIRM 0x08; toucan: 2048×2048, Mono10 in 16-bit words"),
    Register(SIRM_ADDRESS + SIRM.REQUIRED_LEADER_SIZE, "SIRequiredLeaderSize", 4, _U, _RO,
             u3v.IMAGE_LEADER_SIZE, "u3v: SIRM 0x10; an image leader is 52 bytes"),
    Register(SIRM_ADDRESS + SIRM.REQUIRED_TRAILER_SIZE, "SIRequiredTrailerSize", 4, _U, _RO,
             u3v.IMAGE_TRAILER_SIZE, "u3v: SIRM 0x14; a trailer with size_y"),
    Register(SIRM_ADDRESS + SIRM.MAX_LEADER_SIZE, "SIMaxLeaderSize", 4, _U, _RW, 0,
             "u3v: SIRM 0x18, host-written"),
    Register(SIRM_ADDRESS + SIRM.PAYLOAD_TRANSFER_SIZE, "SIPayloadTransferSize", 4, _U, _RW, 0,
             "u3v: SIRM 0x1C, host-written"),
    Register(SIRM_ADDRESS + SIRM.PAYLOAD_TRANSFER_COUNT, "SIPayloadTransferCount", 4, _U, _RW, 0,
             "u3v: SIRM 0x20, host-written"),
    Register(SIRM_ADDRESS + SIRM.FINAL_TRANSFER1_SIZE, "SIPayloadFinalTransfer1Size", 4, _U, _RW, 0,
             "u3v: SIRM 0x24, host-written"),
    Register(SIRM_ADDRESS + SIRM.FINAL_TRANSFER2_SIZE, "SIPayloadFinalTransfer2Size", 4, _U, _RW, 0,
             "u3v: SIRM 0x28, host-written"),
    Register(SIRM_ADDRESS + SIRM.MAX_TRAILER_SIZE, "SIMaxTrailerSize", 4, _U, _RW, 0,
             "u3v: SIRM 0x2C, host-written"),
    # features (GenICam SFNC names, as the XML has them)
    Register(FeatureReg.WIDTH, "Width", 4, _U, _RO, 2048, "toucan: 2048×2048 sensor; assumed: the address"),
    Register(FeatureReg.HEIGHT, "Height", 4, _U, _RO, 2048, "toucan: 2048×2048 sensor; assumed: the address"),
    Register(FeatureReg.PIXEL_FORMAT, "PixelFormat", 4, _U, _RW, int(PixelFormat.Mono10),
             "toucan: 10-bit digitisation; u3v: PFNC Mono10 0x01100003; assumed: the address"),
    Register(FeatureReg.PAYLOAD_SIZE, "PayloadSize", 4, _U, _RO, 2048 * 2048 * 2,
             "assumed: the address; the payload of the pixel format"),
    Register(FeatureReg.ACQUISITION_MODE, "AcquisitionMode", 4, _U, _RW, 0,
             "assumed: 0 Continuous, 1 SingleFrame, as the XML enumerates"),
    Register(FeatureReg.ACQUISITION_START, "AcquisitionStart", 4, _U, _WO, 0, "assumed: the address"),
    Register(FeatureReg.ACQUISITION_STOP, "AcquisitionStop", 4, _U, _WO, 0, "assumed: the address"),
    Register(FeatureReg.TRIGGER_MODE, "TriggerMode", 4, _U, _RW, 0,
             "assumed: 0 Off, 1 On, as the XML enumerates"),
    Register(FeatureReg.TRIGGER_SOURCE, "TriggerSource", 4, _U, _RW, 0, "assumed: 0 Software, the only one"),
    Register(FeatureReg.TRIGGER_SOFTWARE, "TriggerSoftware", 4, _U, _WO, 0, "assumed: the address"),
    Register(FeatureReg.TRIGGER_SELECTOR, "TriggerSelector", 4, _U, _RW, 0,
             "assumed: 0 FrameStart, the only one"),
    Register(FeatureReg.EXPOSURE_TIME, "ExposureTime", 8, _F, _RW, 10_000.0,
             "toucan: exposure 100 µs … 5 s; assumed: the address, in µs, and the 10 ms default",
             minimum=100.0, maximum=5_000_000.0),
    Register(FeatureReg.GAIN, "Gain", 8, _F, _RW, 1.0, "assumed: linear gain 1 … 16, the address",
             minimum=1.0, maximum=16.0),
    Register(FeatureReg.FRAME_RATE, "AcquisitionFrameRate", 8, _F, _RW, 65.0,
             "toucan: up to 65 frames/s; assumed: the address (the top is the device's max_fps)",
             minimum=0.1, maximum=65.0),
    Register(FeatureReg.TEMPERATURE, "DeviceTemperature", 8, _F, _RO, 35.0,
             "assumed: the address and the 35 °C default (the world may drive it)"),
)

BY_ADDRESS: dict[int, Register] = {r.address: r for r in REGISTERS}


def default_of(address: int) -> Value:
    return BY_ADDRESS[address].default


def encode_block(base: int, size: int, values: Mapping[int, Value]) -> bytes:
    """The ``size`` bytes from ``base``: each register there holds ``values[address]`` (its
    default where absent); bytes no register covers, and command registers, read 0."""
    b = bytearray(size)
    for reg in REGISTERS:
        if base <= reg.address < base + size and reg.readable:
            off = reg.address - base
            b[off : off + reg.width] = reg.encode(values.get(reg.address, reg.default))
    return bytes(b)


_POWER_ON_FORMAT = PixelFormat(int(default_of(FeatureReg.PIXEL_FORMAT)))


@dataclass
class Settings:
    """The writable feature registers (and the user name), at their power-on defaults."""

    pixel_format: PixelFormat = _POWER_ON_FORMAT
    acquisition_mode: int = int(default_of(FeatureReg.ACQUISITION_MODE))  # Continuous
    trigger_mode: int = int(default_of(FeatureReg.TRIGGER_MODE))
    trigger_source: int = int(default_of(FeatureReg.TRIGGER_SOURCE))
    trigger_selector: int = int(default_of(FeatureReg.TRIGGER_SELECTOR))
    exposure_us: float = float(default_of(FeatureReg.EXPOSURE_TIME))
    gain: float = float(default_of(FeatureReg.GAIN))
    frame_rate: float = float(default_of(FeatureReg.FRAME_RATE))
    user_name: str = str(default_of(ABRM.USER_DEFINED_NAME))

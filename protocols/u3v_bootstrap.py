"""USB3 Vision bootstrap registers, the manifest table and the device-info descriptor.

Addresses are byte offsets; every register is little-endian. ABRM offsets are
absolute, SBRM and SIRM offsets are relative to the addresses the ABRM and SBRM give.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag

from m2s2hil.protocols.errors import CodecError

STRING_LENGTH = 64  # ABRM string registers: NUL-padded


class ABRM(IntEnum):
    """Technology-agnostic bootstrap register map (absolute addresses)."""

    GENCP_VERSION = 0x0000  # u32
    MANUFACTURER_NAME = 0x0004  # string[64]
    MODEL_NAME = 0x0044
    FAMILY_NAME = 0x0084
    DEVICE_VERSION = 0x00C4
    MANUFACTURER_INFO = 0x0104
    SERIAL_NUMBER = 0x0144
    USER_DEFINED_NAME = 0x0184
    DEVICE_CAPABILITY = 0x01C4  # u64
    MAX_DEVICE_RESPONSE_TIME = 0x01CC  # u32, ms
    MANIFEST_TABLE_ADDRESS = 0x01D0  # u64
    SBRM_ADDRESS = 0x01D8  # u64
    DEVICE_CONFIGURATION = 0x01E0  # u64
    HEARTBEAT_TIMEOUT = 0x01E8  # u32
    MESSAGE_CHANNEL_ID = 0x01EC  # u32
    TIMESTAMP = 0x01F0  # u64
    TIMESTAMP_LATCH = 0x01F8  # u32
    TIMESTAMP_INCREMENT = 0x01FC  # u64, ns per tick
    ACCESS_PRIVILEGE = 0x0204  # u32
    PROTOCOL_ENDIANNESS = 0x0208  # u32
    IMPLEMENTATION_ENDIANNESS = 0x020C  # u32


ABRM_SIZE = 0x0210


class SBRM(IntEnum):
    """Technology-specific (U3V) bootstrap registers, offsets from the SBRM address."""

    U3V_VERSION = 0x00  # u32
    U3VCP_CAPABILITY = 0x04  # u64
    U3VCP_CONFIGURATION = 0x0C  # u64
    MAX_COMMAND_TRANSFER_LENGTH = 0x14  # u32
    MAX_ACK_TRANSFER_LENGTH = 0x18  # u32
    NUM_STREAM_CHANNELS = 0x1C  # u32
    SIRM_ADDRESS = 0x20  # u64
    SIRM_LENGTH = 0x28  # u32
    EIRM_ADDRESS = 0x2C  # u64
    EIRM_LENGTH = 0x34  # u32
    IIDC2_ADDRESS = 0x38  # u64
    CURRENT_SPEED = 0x40  # u32


SBRM_SIZE = 0x44


class DeviceCapability(IntFlag):
    """Bits of the ABRM Device Capability register (u64 at 0x01C4), bit 0 = least
    significant, as GenCP 1.x lays it out (cross-checked against the cameleon U3V
    implementation). Bits 4..7 hold the string encoding (:class:`StringEncoding`)."""

    USER_DEFINED_NAME = 1 << 0
    ACCESS_PRIVILEGE_HEARTBEAT = 1 << 1
    MESSAGE_CHANNEL = 1 << 2
    TIMESTAMP = 1 << 3
    FAMILY_NAME = 1 << 8
    SBRM = 1 << 9
    ENDIANNESS_REGISTER = 1 << 10
    WRITTEN_LENGTH_FIELD = 1 << 11
    MULTI_EVENT = 1 << 12
    STACKED_COMMANDS = 1 << 13
    DEVICE_SOFTWARE_INTERFACE_VERSION = 1 << 14


class StringEncoding(IntEnum):
    """Device Capability bits 4..7: how the ABRM string registers are encoded."""

    ASCII = 0
    UTF8 = 1
    UTF16 = 2


_ENCODING_SHIFT = 4
_KNOWN_CAPABILITY_BITS = 0x7F0F  # bits 0..14; 15..63 are reserved


def encode_device_capability(flags: DeviceCapability, encoding: StringEncoding = StringEncoding.ASCII) -> int:
    return int(flags) | (int(encoding) << _ENCODING_SHIFT)


def decode_device_capability(value: int) -> tuple[DeviceCapability, StringEncoding]:
    """The flags and string encoding of a Device Capability register value."""
    if not 0 <= value < 1 << 64:
        raise CodecError(f"device capability {value!r} is not a u64")
    code = (value >> _ENCODING_SHIFT) & 0xF
    try:
        encoding = StringEncoding(code)
    except ValueError:
        raise CodecError(f"device capability 0x{value:016X}: unknown string encoding {code}") from None
    return DeviceCapability(value & _KNOWN_CAPABILITY_BITS), encoding


class SIRM(IntEnum):
    """Streaming interface registers, offsets from the SIRM address."""

    INFO = 0x00  # u32: bits 24..31 = log2(payload alignment)
    CONTROL = 0x04  # u32: bit 0 = stream enable
    REQUIRED_PAYLOAD_SIZE = 0x08  # u64
    REQUIRED_LEADER_SIZE = 0x10  # u32
    REQUIRED_TRAILER_SIZE = 0x14  # u32
    MAX_LEADER_SIZE = 0x18  # u32, host-written from here on
    PAYLOAD_TRANSFER_SIZE = 0x1C
    PAYLOAD_TRANSFER_COUNT = 0x20
    FINAL_TRANSFER1_SIZE = 0x24
    FINAL_TRANSFER2_SIZE = 0x28
    MAX_TRAILER_SIZE = 0x2C


SIRM_SIZE = 0x30
SI_CONTROL_ENABLE = 0x1


def sirm_alignment(info: int) -> int:
    """Payload transfer alignment in bytes from the SI info register."""
    shift = (info >> 24) & 0xFF
    if shift > 20:  # alignment above 1 MiB is not a real device
        raise CodecError(f"SI info 0x{info:08X}: alignment 2**{shift} is implausible")
    return 1 << shift


def sirm_info(alignment: int) -> int:
    if alignment <= 0 or alignment & (alignment - 1):
        raise ValueError(f"alignment {alignment} is not a power of two")
    return (alignment.bit_length() - 1) << 24


def encode_string(text: str, length: int = STRING_LENGTH) -> bytes:
    raw = text.encode("ascii")
    if len(raw) >= length:
        raise ValueError(f"{text!r} does not fit a {length}-byte string register")
    return raw.ljust(length, b"\0")


def decode_string(data: bytes) -> str:
    raw = bytes(data).split(b"\0", 1)[0]
    try:
        return raw.decode("ascii")
    except UnicodeDecodeError:
        raise CodecError("string register is not ASCII", data) from None


# -- manifest ---------------------------------------------------------------------------

MANIFEST_ENTRY_SIZE = 64
_ENTRY = struct.Struct("<HBBIQQ20s")  # 44 bytes, then reserved up to 64


class FileFormat(IntEnum):
    XML = 0  # uncompressed
    ZIP = 1


@dataclass(frozen=True)
class ManifestEntry:
    """One device description file: where it is, how big, how stored."""

    address: int
    size: int
    file_format: int = FileFormat.XML
    version: tuple[int, int, int] = (1, 0, 0)  # major, minor, subminor of the file
    schema: tuple[int, int] = (1, 1)  # GenApi schema major, minor
    sha1: bytes | None = None

    @property
    def format_info(self) -> int:
        major, minor = self.schema
        return (major & 0xFF) << 24 | (minor & 0xFF) << 16 | (self.file_format & 0x1F) << 10

    @property
    def is_zip(self) -> bool:
        return self.file_format == FileFormat.ZIP

    def encode(self) -> bytes:
        sha = self.sha1 if self.sha1 is not None else bytes(20)
        if len(sha) != 20:
            raise ValueError("SHA-1 must be 20 bytes")
        major, minor, sub = self.version
        body = _ENTRY.pack(sub, minor, major, self.format_info, self.address, self.size, sha)
        return body.ljust(MANIFEST_ENTRY_SIZE, b"\0")


def decode_manifest_entry(data: bytes) -> ManifestEntry:
    data = bytes(data)
    if len(data) < MANIFEST_ENTRY_SIZE:
        raise CodecError(f"manifest entry is {len(data)} bytes, expected 64", data)
    sub, minor, major, info, address, size, sha = _ENTRY.unpack_from(data)
    file_format = (info >> 10) & 0x1F
    if file_format not in (FileFormat.XML, FileFormat.ZIP):
        raise CodecError(f"manifest entry: unknown file format {file_format}", data)
    return ManifestEntry(
        address=address,
        size=size,
        file_format=file_format,
        version=(major, minor, sub),
        schema=((info >> 24) & 0xFF, (info >> 16) & 0xFF),
        sha1=None if sha == bytes(20) else sha,
    )


def encode_manifest(entries: list[ManifestEntry]) -> bytes:
    return struct.pack("<Q", len(entries)) + b"".join(e.encode() for e in entries)


def manifest_count(data: bytes) -> int:
    if len(data) < 8:
        raise CodecError("manifest table shorter than its 8-byte count", data)
    (count,) = struct.unpack_from("<Q", data)
    if count > 64:  # a device has a handful of files; more means garbage
        raise CodecError(f"manifest table claims {count} entries", data)
    return count


def decode_manifest(data: bytes) -> list[ManifestEntry]:
    count = manifest_count(data)
    need = 8 + count * MANIFEST_ENTRY_SIZE
    if len(data) < need:
        raise CodecError(f"manifest table of {count} entries needs {need} bytes, got {len(data)}", data)
    return [
        decode_manifest_entry(data[8 + i * MANIFEST_ENTRY_SIZE : 8 + (i + 1) * MANIFEST_ENTRY_SIZE])
        for i in range(count)
    ]


# -- USB descriptors --------------------------------------------------------------------

DEVICE_CLASS = (0xEF, 0x02, 0x01)  # miscellaneous / common class / IAD
INTERFACE_CLASS = 0xEF
INTERFACE_SUBCLASS = 0x05


class InterfaceProtocol(IntEnum):
    CONTROL = 0x00
    EVENT = 0x01
    STREAM = 0x02


DEVICE_INFO_TYPE = 0x24
DEVICE_INFO_SUBTYPE = 0x01
_DEVINFO = struct.Struct("<BBBHHHH8BB")  # 20 bytes


@dataclass(frozen=True)
class DeviceInfoDescriptor:
    """U3V device-info descriptor (class-specific, in the control interface): string indices."""

    gencp_version: tuple[int, int] = (1, 2)  # major, minor
    u3v_version: tuple[int, int] = (1, 0)
    i_guid: int = 0
    i_vendor: int = 0
    i_model: int = 0
    i_family: int = 0
    i_device_version: int = 0
    i_manufacturer_info: int = 0
    i_serial: int = 0
    i_user_name: int = 0
    speed_support: int = 0x0C  # bit 2 high speed, bit 3 super speed

    def encode(self) -> bytes:
        return _DEVINFO.pack(
            _DEVINFO.size,
            DEVICE_INFO_TYPE,
            DEVICE_INFO_SUBTYPE,
            self.gencp_version[1],
            self.gencp_version[0],
            self.u3v_version[1],
            self.u3v_version[0],
            self.i_guid,
            self.i_vendor,
            self.i_model,
            self.i_family,
            self.i_device_version,
            self.i_manufacturer_info,
            self.i_serial,
            self.i_user_name,
            self.speed_support,
        )


def decode_device_info(data: bytes) -> DeviceInfoDescriptor:
    data = bytes(data)
    if len(data) < _DEVINFO.size:
        raise CodecError(f"device-info descriptor is {len(data)} bytes, expected 20", data)
    f = _DEVINFO.unpack_from(data)
    if f[0] < _DEVINFO.size or f[1] != DEVICE_INFO_TYPE or f[2] != DEVICE_INFO_SUBTYPE:
        raise CodecError("not a U3V device-info descriptor", data)
    return DeviceInfoDescriptor((f[4], f[3]), (f[6], f[5]), *f[7:16])


def find_device_info(extra: bytes) -> DeviceInfoDescriptor | None:
    """The device-info descriptor among an interface's class-specific descriptors."""
    extra = bytes(extra)
    i = 0
    while i + 2 <= len(extra):
        length = extra[i]
        if length < 2 or i + length > len(extra):
            raise CodecError(f"class-specific descriptor at byte {i} has bad length {length}", extra)
        if extra[i + 1] == DEVICE_INFO_TYPE and length >= 3 and extra[i + 2] == DEVICE_INFO_SUBTYPE:
            return decode_device_info(extra[i : i + length])
        i += length
    return None

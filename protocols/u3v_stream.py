"""USB3 Vision streaming: image leader, trailer, PFNC pixel formats and pixel packing.

A block (one frame) on the stream endpoint is a leader transfer, the payload in
``payload transfer count`` transfers of ``payload transfer size`` bytes plus up to two
final transfers, then a trailer transfer. All fields are little-endian.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from m2s2hil.protocols.errors import CodecError

LEADER_PREFIX = 0x4C563355  # b"U3VL"
TRAILER_PREFIX = 0x54563355  # b"U3VT"
PAYLOAD_IMAGE = 0x0001

IMAGE_LEADER_SIZE = 52
TRAILER_MIN_SIZE = 28
IMAGE_TRAILER_SIZE = 32  # with size_y

# prefix, reserved, leader size, block id, reserved, payload type, timestamp,
# pixel format, size x/y, offset x/y, padding x, reserved
_LEADER = struct.Struct("<IHHQHHQIIIIIHH")
# prefix, reserved, trailer size, block id, status, reserved, valid payload size
_TRAILER = struct.Struct("<IHHQHHQ")
assert _LEADER.size == IMAGE_LEADER_SIZE and _TRAILER.size == TRAILER_MIN_SIZE


class PixelFormat(IntEnum):
    """PFNC codes: bits 16..23 hold the bits per pixel on the wire."""

    Mono8 = 0x01080001
    Mono10 = 0x01100003
    Mono10p = 0x010A0046
    Mono12 = 0x01100005
    Mono16 = 0x01100007

    @property
    def bits_per_pixel(self) -> int:
        """Bits each pixel takes on the wire (16 for Mono10: padded)."""
        return (self.value >> 16) & 0xFF

    @property
    def depth(self) -> int:
        """Significant bits of a pixel."""
        return {"Mono8": 8, "Mono10": 10, "Mono10p": 10, "Mono12": 12, "Mono16": 16}[self.name]


def pixel_format(value: int | str) -> PixelFormat:
    """A PixelFormat from its PFNC code or name; CodecError if unsupported."""
    try:
        return PixelFormat[value] if isinstance(value, str) else PixelFormat(value)
    except (KeyError, ValueError):
        shown = value if isinstance(value, str) else f"0x{value:08X}"
        raise CodecError(f"unsupported pixel format {shown}") from None


def payload_size(fmt: PixelFormat | int, width: int, height: int) -> int:
    """Bytes of one image in ``fmt`` (packed formats round up to whole bytes)."""
    bits = pixel_format(fmt).bits_per_pixel
    return (width * height * bits + 7) // 8


# -- leader / trailer -------------------------------------------------------------------


@dataclass(frozen=True)
class ImageLeader:
    block_id: int
    timestamp: int  # device ticks (see ABRM timestamp increment)
    pixel_format: int
    size_x: int
    size_y: int
    offset_x: int = 0
    offset_y: int = 0
    padding_x: int = 0
    payload_type: int = PAYLOAD_IMAGE

    def encode(self) -> bytes:
        return _LEADER.pack(
            LEADER_PREFIX,
            0,
            IMAGE_LEADER_SIZE,
            self.block_id,
            0,
            self.payload_type,
            self.timestamp,
            self.pixel_format,
            self.size_x,
            self.size_y,
            self.offset_x,
            self.offset_y,
            self.padding_x,
            0,
        )


def _checked_block(data: bytes, what: str, prefix: int, min_size: int) -> tuple[bytes, int]:
    """Leader and trailer share a header (u32 prefix, u16 reserved, u16 size): check it."""
    data = bytes(data)
    if len(data) < 8:
        raise CodecError(f"{what} of {len(data)} bytes", data)
    got, _r, size = struct.unpack_from("<IHH", data)
    if got != prefix:
        raise CodecError(f"{what}: bad prefix 0x{got:08X}", data)
    if size != len(data):
        raise CodecError(f"{what} says {size} bytes, transfer has {len(data)}", data)
    if size < min_size:
        raise CodecError(f"{what} of {size} bytes is shorter than {min_size}", data)
    return data, size


def decode_leader(data: bytes) -> ImageLeader:
    data, _size = _checked_block(data, "leader", LEADER_PREFIX, IMAGE_LEADER_SIZE)
    f = _LEADER.unpack_from(data)
    if f[5] != PAYLOAD_IMAGE:
        raise CodecError(f"leader: payload type 0x{f[5]:04X} is not an image", data)
    return ImageLeader(
        block_id=f[3],
        timestamp=f[6],
        pixel_format=f[7],
        size_x=f[8],
        size_y=f[9],
        offset_x=f[10],
        offset_y=f[11],
        padding_x=f[12],
        payload_type=f[5],
    )


@dataclass(frozen=True)
class Trailer:
    block_id: int
    status: int
    valid_payload_size: int
    size_y: int | None = None

    def encode(self) -> bytes:
        size = TRAILER_MIN_SIZE if self.size_y is None else IMAGE_TRAILER_SIZE
        body = _TRAILER.pack(TRAILER_PREFIX, 0, size, self.block_id, self.status, 0, self.valid_payload_size)
        return body if self.size_y is None else body + struct.pack("<I", self.size_y)


def decode_trailer(data: bytes) -> Trailer:
    data, size = _checked_block(data, "trailer", TRAILER_PREFIX, TRAILER_MIN_SIZE)
    f = _TRAILER.unpack_from(data)
    size_y = struct.unpack_from("<I", data, TRAILER_MIN_SIZE)[0] if size >= IMAGE_TRAILER_SIZE else None
    return Trailer(block_id=f[3], status=f[4], valid_payload_size=f[6], size_y=size_y)


def stream_prefix(data: bytes | memoryview) -> int | None:
    """The U3VL/U3VT prefix of a transfer, or None for payload bytes."""
    if len(data) >= 4:
        (p,) = struct.unpack_from("<I", data)
        if p in (LEADER_PREFIX, TRAILER_PREFIX):
            return p
    return None


# -- pixels -----------------------------------------------------------------------------


def pack_mono10p(pixels: np.ndarray) -> bytes:
    """PFNC Mono10p: 10-bit values packed LSB first, 4 pixels in 5 bytes."""
    flat = np.ascontiguousarray(pixels, dtype=np.uint16).reshape(-1)
    n = flat.size
    nbytes = (n * 10 + 7) // 8
    pad = (-n) % 4
    if pad:
        flat = np.concatenate([flat, np.zeros(pad, np.uint16)])
    q = (flat & 0x3FF).reshape(-1, 4)
    out = np.empty((q.shape[0], 5), np.uint8)
    out[:, 0] = q[:, 0] & 0xFF
    out[:, 1] = (q[:, 0] >> 8) | ((q[:, 1] & 0x3F) << 2)
    out[:, 2] = (q[:, 1] >> 6) | ((q[:, 2] & 0x0F) << 4)
    out[:, 3] = (q[:, 2] >> 4) | ((q[:, 3] & 0x03) << 6)
    out[:, 4] = q[:, 3] >> 2
    return out.reshape(-1)[:nbytes].tobytes()


def unpack_mono10p(data: bytes | memoryview | np.ndarray, count: int) -> np.ndarray:
    """``count`` uint16 pixels out of Mono10p bytes."""
    need = (count * 10 + 7) // 8
    raw = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1)
    if raw.size < need:
        raise CodecError(f"Mono10p: {count} pixels need {need} bytes, got {raw.size}")
    groups = (count + 3) // 4
    if raw.size >= groups * 5:
        b = raw[: groups * 5]
    else:
        b = np.zeros(groups * 5, np.uint8)
        b[:need] = raw[:need]
    b = b.reshape(-1, 5).astype(np.uint16)
    out = np.empty((groups, 4), np.uint16)
    out[:, 0] = b[:, 0] | ((b[:, 1] & 0x03) << 8)
    out[:, 1] = (b[:, 1] >> 2) | ((b[:, 2] & 0x0F) << 6)
    out[:, 2] = (b[:, 2] >> 4) | ((b[:, 3] & 0x3F) << 4)
    out[:, 3] = (b[:, 3] >> 6) | (b[:, 4] << 2)
    return out.reshape(-1)[:count]


def encode_image(pixels: np.ndarray, fmt: PixelFormat | int) -> bytes | memoryview:
    """The payload bytes of a uint16 image in ``fmt`` (values must fit the format).

    Unpacked 16-bit formats come back as a zero-copy memoryview when possible.
    """
    fmt = pixel_format(fmt)
    if fmt is PixelFormat.Mono10p:
        return pack_mono10p(pixels)
    if fmt is PixelFormat.Mono8:
        return np.ascontiguousarray(pixels, dtype=np.uint8).tobytes()
    arr = np.ascontiguousarray(pixels, dtype="<u2")
    return memoryview(arr.data).cast("B")


def decode_image(
    payload: bytes | memoryview | np.ndarray, fmt: PixelFormat | int, width: int, height: int
) -> np.ndarray:
    """A (height, width) uint16 image from payload bytes; CodecError if short or out of range."""
    fmt = pixel_format(fmt)
    count = width * height
    need = payload_size(fmt, width, height)
    raw = np.frombuffer(payload, np.uint8) if not isinstance(payload, np.ndarray) else payload.reshape(-1)
    if raw.size < need:
        raise CodecError(f"{fmt.name} {width}x{height} needs {need} payload bytes, got {raw.size}")
    if fmt is PixelFormat.Mono10p:
        img = unpack_mono10p(raw, count)
    elif fmt is PixelFormat.Mono8:
        img = raw[:count].astype(np.uint16)
    else:
        img = raw[:need].view("<u2").astype(np.uint16, copy=True)
        if fmt.depth < 16 and count and int(img.max()) >> fmt.depth:
            raise CodecError(f"{fmt.name} payload holds values above {(1 << fmt.depth) - 1}")
    return img.reshape(height, width)

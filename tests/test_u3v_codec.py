"""USB3 Vision codec: hand-checked bytes, round trips, and garbage that must raise CodecError."""

from __future__ import annotations

import contextlib
import hashlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from m2s2hil.protocols import u3v
from m2s2hil.protocols.errors import CodecError

# -- hand-checked bytes (layouts from hardware-notes.md, little-endian) ----------------


def test_readmem_command_bytes():
    raw = u3v.read_mem(0x01D8, 8, request_id=1).encode()
    assert raw == bytes.fromhex(
        "55335643"  # "U3VC"
        "0040"  # flags: request ack
        "0008"  # READMEM_CMD
        "0c00"  # 12 payload bytes
        "0100"  # request id 1
        "d801000000000000"  # address
        "0000"  # reserved
        "0800"  # length 8
    )


def test_writemem_resend_command_bytes():
    raw = u3v.write_mem(0x10014, b"\x01\x00\x00\x00", request_id=0x1234, resend=True).encode()
    assert raw == bytes.fromhex("5533564300c002080c003412140001000000000001000000")


def test_ack_bytes_decode():
    ack = u3v.decode_ack(bytes.fromhex("553356430380010800000500"))
    assert (ack.status, ack.command_id, ack.request_id, ack.payload) == (0x8003, 0x0801, 5, b"")
    assert ack.status_name == "INVALID_ADDRESS" and not ack.ok


def test_pending_ack_bytes():
    raw = u3v.pending_ack(1000, request_id=9).encode()
    assert raw == bytes.fromhex("5533564300000508040009000000e803")
    assert u3v.parse_pending_ack(u3v.decode_ack(raw)) == 1000


def test_writemem_ack_bytes():
    raw = u3v.write_mem_ack(4, request_id=2).encode()
    assert raw == bytes.fromhex("55335643000003080400020000000400")
    assert u3v.parse_write_mem_ack(u3v.decode_ack(raw)) == 4


def test_event_command_uses_u3ve_prefix():
    cmd = u3v.event_command(u3v.Event(0x9001, 123456, b"\xaa"), request_id=3)
    raw = cmd.encode()
    assert raw[:4] == b"U3VE" and raw[6:8] == b"\x00\x0c"
    ev = u3v.parse_event(u3v.decode_command(raw))
    assert ev == u3v.Event(0x9001, 123456, b"\xaa")


def test_ack_matching_rule():
    cmd = u3v.read_mem(0, 4, request_id=7)
    assert u3v.ack_matches(u3v.read_mem_ack(b"abcd", 7), cmd)
    assert not u3v.ack_matches(u3v.read_mem_ack(b"abcd", 8), cmd)  # other request
    assert not u3v.ack_matches(u3v.write_mem_ack(4, 7), cmd)  # other command
    assert not u3v.ack_matches(u3v.pending_ack(100, 7), cmd)
    assert u3v.is_pending_for(u3v.pending_ack(100, 7), cmd)
    assert not u3v.is_pending_for(u3v.pending_ack(100, 6), cmd)


def test_request_ids_wrap_and_skip_zero():
    ids = u3v.RequestIds(last=0xFFFE)
    assert [ids.next() for _ in range(3)] == [0xFFFF, 1, 2]
    assert u3v.next_request_id(0) == 1
    with pytest.raises(ValueError):
        u3v.next_request_id(0x10000)


def test_status_names():
    assert u3v.Status(0xA004).name == "STREAM_REGISTERS_INCONSISTENT"
    assert u3v.status_name(0x8006) == "ACCESS_DENIED"
    assert u3v.status_name(0x1234) == "0x1234"


def test_image_leader_bytes():
    leader = u3v.ImageLeader(
        block_id=5,
        timestamp=0x0102030405060708,
        pixel_format=u3v.PixelFormat.Mono10p,
        size_x=2048,
        size_y=1024,
    )
    raw = leader.encode()
    assert len(raw) == 52
    assert raw[0:4] == b"U3VL"
    assert raw[6:8] == bytes.fromhex("3400")  # leader size 52
    assert raw[8:16] == bytes.fromhex("0500000000000000")
    assert raw[18:20] == bytes.fromhex("0100")  # image payload
    assert raw[20:28] == bytes.fromhex("0807060504030201")
    assert raw[28:32] == bytes.fromhex("46000a01")  # Mono10p 0x010A0046
    assert raw[32:36] == bytes.fromhex("00080000") and raw[36:40] == bytes.fromhex("00040000")
    assert u3v.decode_leader(raw) == leader


def test_trailer_bytes():
    raw = u3v.Trailer(block_id=5, status=0xA100, valid_payload_size=5242880, size_y=2048).encode()
    assert len(raw) == 32
    assert raw[0:4] == b"U3VT" and raw[6:8] == bytes.fromhex("2000")
    assert raw[8:16] == bytes.fromhex("0500000000000000")
    assert raw[16:18] == bytes.fromhex("00a1")
    assert raw[20:28] == (5242880).to_bytes(8, "little")
    assert raw[28:32] == bytes.fromhex("00080000")
    short = u3v.decode_trailer(u3v.Trailer(1, 0, 10).encode())
    assert short.size_y is None and short.valid_payload_size == 10


def test_manifest_entry_bytes():
    sha = hashlib.sha1(b"xml").digest()
    entry = u3v.ManifestEntry(
        address=0x100000,
        size=1234,
        file_format=u3v.FileFormat.ZIP,
        version=(1, 2, 3),
        schema=(1, 1),
        sha1=sha,
    )
    raw = entry.encode()
    assert len(raw) == 64
    assert raw[0:4] == bytes.fromhex("03000201")  # subminor, minor, major
    info = int.from_bytes(raw[4:8], "little")
    assert (info >> 10) & 0x1F == 1  # ZIP
    assert raw[8:16] == (0x100000).to_bytes(8, "little") and raw[16:24] == (1234).to_bytes(8, "little")
    assert raw[24:44] == sha
    assert u3v.decode_manifest_entry(raw) == entry
    table = u3v.encode_manifest([entry, u3v.ManifestEntry(address=0x200000, size=5)])
    assert table[:8] == (2).to_bytes(8, "little")
    decoded = u3v.decode_manifest(table)
    assert decoded[0].is_zip and not decoded[1].is_zip and decoded[1].sha1 is None


def test_mono10p_known_bytes():
    pixels = np.array([0x3FF, 0x000, 0x155, 0x2AA], np.uint16)
    assert u3v.pack_mono10p(pixels) == bytes.fromhex("ff035095aa")
    assert u3v.unpack_mono10p(bytes.fromhex("ff035095aa"), 4).tolist() == pixels.tolist()
    # a partial group: 5 pixels take ceil(50 / 8) = 7 bytes
    assert len(u3v.pack_mono10p(np.arange(5, dtype=np.uint16))) == 7
    assert u3v.payload_size(u3v.PixelFormat.Mono10p, 2048, 2048) == 5_242_880
    assert u3v.payload_size(u3v.PixelFormat.Mono10, 2048, 2048) == 8_388_608


def test_device_info_descriptor_round_trip_in_extra_bytes():
    info = u3v.DeviceInfoDescriptor(i_guid=4, i_vendor=1, i_model=2, i_serial=3)
    raw = info.encode()
    assert raw[:3] == bytes([20, 0x24, 0x01])
    other = bytes([5, 0x24, 0x02, 0, 0])  # another class-specific descriptor first
    assert u3v.find_device_info(other + raw) == info
    assert u3v.find_device_info(other) is None


def test_sirm_info_alignment():
    assert u3v.sirm_alignment(u3v.sirm_info(1024)) == 1024
    assert u3v.sirm_alignment(0) == 1


def test_decode_image_rejects_out_of_range_and_short():
    raw = np.array([0, 1024], "<u2").tobytes()
    with pytest.raises(CodecError):
        u3v.decode_image(raw, u3v.PixelFormat.Mono10, 2, 1)
    with pytest.raises(CodecError):
        u3v.decode_image(raw[:3], u3v.PixelFormat.Mono12, 2, 1)
    with pytest.raises(CodecError):
        u3v.pixel_format(0x12345678)


# -- round trips -----------------------------------------------------------------------

u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
u64 = st.integers(0, (1 << 64) - 1)


@given(
    cid=st.integers(0, 0x7FFF).map(lambda x: x * 2),
    rid=u16,
    flags=st.sampled_from([0, 0x4000, 0x8000, 0xC000]),
    payload=st.binary(max_size=300),
    prefix=st.sampled_from([u3v.CONTROL_PREFIX, u3v.EVENT_PREFIX]),
)
def test_command_round_trip(cid, rid, flags, payload, prefix):
    cmd = u3v.Command(cid, rid, payload, flags, prefix)
    assert u3v.decode_command(cmd.encode()) == cmd


@given(
    status=u16, cid=st.integers(0, 0x7FFF).map(lambda x: x * 2 + 1), rid=u16, payload=st.binary(max_size=300)
)
def test_ack_round_trip(status, cid, rid, payload):
    ack = u3v.Ack(status, cid, rid, payload)
    assert u3v.decode_ack(ack.encode()) == ack


@given(address=u64, length=u16, rid=u16, resend=st.booleans())
def test_readmem_round_trip(address, length, rid, resend):
    cmd = u3v.decode_command(u3v.read_mem(address, length, rid, resend=resend).encode())
    assert u3v.parse_read_mem(cmd) == (address, length)
    assert cmd.is_resend is resend and cmd.request_id == rid


@given(address=u64, data=st.binary(max_size=1000), rid=u16)
def test_writemem_round_trip(address, data, rid):
    cmd = u3v.decode_command(u3v.write_mem(address, data, rid).encode())
    assert u3v.parse_write_mem(cmd) == (address, data)


@given(
    block_id=u64,
    timestamp=u64,
    fmt=st.sampled_from(list(u3v.PixelFormat)),
    sx=u32,
    sy=u32,
    ox=u32,
    oy=u32,
    px=u16,
)
def test_leader_round_trip(block_id, timestamp, fmt, sx, sy, ox, oy, px):
    leader = u3v.ImageLeader(block_id, timestamp, int(fmt), sx, sy, ox, oy, px)
    assert u3v.decode_leader(leader.encode()) == leader


@given(block_id=u64, status=u16, size=u64, size_y=st.none() | u32)
def test_trailer_round_trip(block_id, status, size, size_y):
    trailer = u3v.Trailer(block_id, status, size, size_y)
    assert u3v.decode_trailer(trailer.encode()) == trailer


@given(
    address=u64,
    size=u64,
    fmt=st.sampled_from(list(u3v.FileFormat)),
    version=st.tuples(st.integers(0, 255), st.integers(0, 255), u16),
    schema=st.tuples(st.integers(0, 255), st.integers(0, 255)),
    sha=st.none() | st.binary(min_size=20, max_size=20).filter(lambda b: any(b)),
)
def test_manifest_entry_round_trip(address, size, fmt, version, schema, sha):
    entry = u3v.ManifestEntry(address, size, fmt, version, schema, sha)
    assert u3v.decode_manifest_entry(entry.encode()) == entry


@given(values=st.lists(st.integers(0, 1023), max_size=257))
def test_mono10p_round_trip(values):
    pixels = np.array(values, np.uint16)
    packed = u3v.pack_mono10p(pixels)
    assert len(packed) == (len(values) * 10 + 7) // 8
    assert u3v.unpack_mono10p(packed, len(values)).tolist() == values


@settings(max_examples=25)
@given(
    fmt=st.sampled_from([f for f in u3v.PixelFormat]),
    shape=st.tuples(st.integers(1, 9), st.integers(1, 9)),
    data=st.data(),
)
def test_image_round_trip(fmt, shape, data):
    top = (1 << fmt.depth) - 1
    values = data.draw(
        st.lists(st.integers(0, top), min_size=shape[0] * shape[1], max_size=shape[0] * shape[1])
    )
    img = np.array(values, np.uint16).reshape(shape)
    payload = bytes(u3v.encode_image(img, fmt))
    assert len(payload) == u3v.payload_size(fmt, shape[1], shape[0])
    assert np.array_equal(u3v.decode_image(payload, fmt, shape[1], shape[0]), img)


# -- garbage raises CodecError and nothing else -----------------------------------------


def _only_codec_error(fn, *args):
    # Any other exception type fails the test.
    with contextlib.suppress(CodecError):
        fn(*args)


def _with_prefix(prefix: bytes):
    return st.binary(max_size=120).map(lambda b: prefix + b)


garbage = st.one_of(
    st.binary(max_size=120),
    _with_prefix(b"U3VC"),
    _with_prefix(b"U3VE"),
    _with_prefix(b"U3VL"),
    _with_prefix(b"U3VT"),
)


@given(raw=garbage)
def test_garbage_control_packets(raw):
    _only_codec_error(u3v.decode_command, raw)
    _only_codec_error(u3v.decode_ack, raw)
    try:
        cmd = u3v.decode_command(raw)
    except CodecError:
        return
    for parse in (u3v.parse_read_mem, u3v.parse_write_mem, u3v.parse_event):
        _only_codec_error(parse, cmd)


@given(raw=garbage)
def test_garbage_acks_payloads(raw):
    try:
        ack = u3v.decode_ack(raw)
    except CodecError:
        return
    _only_codec_error(u3v.parse_pending_ack, ack)
    _only_codec_error(u3v.parse_write_mem_ack, ack)


@given(raw=garbage)
def test_garbage_stream_and_tables(raw):
    for fn in (
        u3v.decode_leader,
        u3v.decode_trailer,
        u3v.decode_manifest_entry,
        u3v.decode_manifest,
        u3v.decode_device_info,
        u3v.find_device_info,
        u3v.decode_string,
    ):
        _only_codec_error(fn, raw)


@given(raw=st.binary(max_size=200), fmt=u32, w=st.integers(0, 20), h=st.integers(0, 20))
def test_garbage_images(raw, fmt, w, h):
    _only_codec_error(u3v.decode_image, raw, fmt, w, h)
    _only_codec_error(u3v.unpack_mono10p, raw, w * h)
    _only_codec_error(u3v.sirm_alignment, fmt)


# -- ABRM device capability (GenCP 1.x layout, bit 0 = least significant) ----------------------
def test_device_capability_bits_hand_checked():
    from m2s2hil.protocols.u3v_bootstrap import (
        DeviceCapability,
        StringEncoding,
        decode_device_capability,
        encode_device_capability,
    )

    # user name (0), timestamp (3), family name (8), SBRM (9), endianness (10), written length (11)
    value = encode_device_capability(
        DeviceCapability.USER_DEFINED_NAME | DeviceCapability.TIMESTAMP | DeviceCapability.FAMILY_NAME
        | DeviceCapability.SBRM | DeviceCapability.ENDIANNESS_REGISTER | DeviceCapability.WRITTEN_LENGTH_FIELD
    )
    assert value == 0x0F09
    flags, encoding = decode_device_capability(0x0F09 | (1 << 4) | (1 << 40))  # UTF-8, a reserved bit
    assert encoding == StringEncoding.UTF8 and DeviceCapability.SBRM in flags
    assert DeviceCapability.MESSAGE_CHANNEL not in flags and int(flags) == 0x0F09
    with pytest.raises(CodecError, match="string encoding 7"):
        decode_device_capability(0x70)
    with pytest.raises(CodecError, match="u64"):
        decode_device_capability(1 << 64)

"""The Modbus RTU relay codec: spec frames, round trips, any split, garbage."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from m2s2hil.protocols.errors import CodecError
from m2s2hil.protocols.modbus_relay import (
    NEED_DATA,
    CoilStatus,
    CoilsWritten,
    CoilWritten,
    ExceptionReply,
    IllegalRequest,
    ModbusRelayCodec,
    OtherRequest,
    OtherResponse,
    ReadCoils,
    WriteCoil,
    WriteCoils,
    expected_reply_size,
)
from pymodbus.framer import FramerRTU


def crc16_modbus(data: bytes) -> int:
    """Bitwise CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF): an oracle independent
    of pymodbus' table-driven one. Returned low byte first, as it goes on the wire."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return int.from_bytes(crc.to_bytes(2, "little"), "big")


def rtu(body: bytes) -> bytes:
    """A frame with pymodbus' CRC: for hand-made bodies the codec would not encode."""
    return body + FramerRTU.compute_CRC(body).to_bytes(2, "big")


def drain(codec: ModbusRelayCodec) -> tuple[list, int]:
    """All events now decodable, and how many CodecErrors came on the way."""
    events, errors = [], 0
    for _ in range(10_000):
        try:
            ev = codec.next_event()
        except CodecError:
            errors += 1
            continue
        if ev is NEED_DATA:
            return events, errors
        events.append(ev)
    raise AssertionError("next_event never returned NEED_DATA")


def feed_split(codec: ModbusRelayCodec, data: bytes, cuts: list[int]) -> list:
    events: list = []
    prev = 0
    for cut in [*sorted(set(cuts)), len(data)]:
        codec.receive_data(data[prev:cut])
        prev = cut
        got, errors = drain(codec)
        assert errors == 0
        events += got
    return events


# -- the spec's own frame, with an independent CRC ---------------------------------------------------
def test_fc05_coil0_on_unit1_is_the_spec_frame():
    wire = ModbusRelayCodec("client").send(WriteCoil(unit=1, address=0, on=True))
    assert wire == bytes.fromhex("01 05 00 00 FF 00 8C 3A")


def test_independent_crc_agrees_with_frames():
    assert crc16_modbus(bytes.fromhex("01 05 00 00 FF 00")) == 0x8C3A
    client = ModbusRelayCodec("client")
    for ev in (ReadCoils(1, 0, 8), WriteCoils(3, 0, (True, False, True)), WriteCoil(7, 5, False)):
        wire = client.send(ev)
        assert int.from_bytes(wire[-2:], "big") == crc16_modbus(wire[:-2])


def test_fc0f_layout():
    wire = ModbusRelayCodec("client").send(WriteCoils(1, 0, (True, False, True) + (False,) * 5))
    # unit, FC, address, quantity, byte count, coils 0..7 LSB first, CRC
    assert wire[:-2] == bytes.fromhex("01 0F 0000 0008 01 05")


def test_reply_sizes():
    assert expected_reply_size(ReadCoils(1, 0, 8)) == 6
    assert expected_reply_size(ReadCoils(1, 0, 9)) == 7
    assert expected_reply_size(WriteCoils(1, 0, (True,))) == 8


# -- strategies --------------------------------------------------------------------------------------
units = st.integers(1, 247)
addresses = st.integers(0, 0xFFFF - 2000)
requests = st.one_of(
    st.builds(ReadCoils, units, addresses, st.integers(1, 2000)),
    st.builds(WriteCoil, units, addresses, st.booleans()),
    st.builds(WriteCoils, units, addresses, st.lists(st.booleans(), min_size=1, max_size=80).map(tuple)),
)
responses = st.one_of(
    st.builds(
        CoilStatus,
        units,
        st.integers(0, 30)
        .flatmap(lambda n: st.lists(st.booleans(), min_size=8 * n, max_size=8 * n))
        .map(tuple),
    ),
    st.builds(CoilWritten, units, addresses, st.booleans()),
    st.builds(CoilsWritten, units, addresses, st.integers(1, 2000)),
    st.builds(ExceptionReply, units, st.sampled_from([1, 5, 15]), st.integers(1, 11)),
)


@settings(max_examples=150, deadline=None)
@given(requests)
def test_request_round_trip(request):
    wire = ModbusRelayCodec("client").send(request)
    server = ModbusRelayCodec("server")
    server.receive_data(wire)
    assert server.next_event() == request
    assert server.next_event() is NEED_DATA


@settings(max_examples=150, deadline=None)
@given(responses)
def test_response_round_trip(response):
    wire = ModbusRelayCodec("server").send(response)
    client = ModbusRelayCodec("client")
    client.receive_data(wire)
    assert client.next_event() == response
    assert client.next_event() is NEED_DATA


@settings(max_examples=150, deadline=None)
@given(st.lists(responses, min_size=1, max_size=4), st.data())
def test_any_split_of_several_frames_gives_the_same_events(frames, data):
    wire = b"".join(ModbusRelayCodec("server").send(f) for f in frames)
    cuts = data.draw(st.lists(st.integers(0, len(wire)), max_size=12))
    assert feed_split(ModbusRelayCodec("client"), wire, cuts) == frames


@settings(max_examples=100, deadline=None)
@given(st.lists(requests, min_size=1, max_size=4), st.data())
def test_server_any_split(reqs, data):
    wire = b"".join(ModbusRelayCodec("client").send(r) for r in reqs)
    cuts = data.draw(st.lists(st.integers(0, len(wire)), max_size=12))
    assert feed_split(ModbusRelayCodec("server"), wire, cuts) == reqs


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["client", "server"]), st.lists(st.binary(max_size=80), max_size=8))
def test_garbage_never_crashes_and_codec_recovers(role, chunks):
    codec = ModbusRelayCodec(role)
    for chunk in chunks:
        codec.receive_data(chunk)
        drain(codec)  # only CodecError may escape next_event; drain asserts it terminates
    codec.reset()
    if role == "client":
        good = CoilsWritten(1, 0, 8)
        codec.receive_data(ModbusRelayCodec("server").send(good))
    else:
        good = WriteCoil(1, 3, True)
        codec.receive_data(ModbusRelayCodec("client").send(good))
    assert codec.next_event() == good


@settings(max_examples=200, deadline=None)
@given(st.integers(2, 7), st.integers(1, 255))
def test_a_changed_byte_is_a_codec_error(position, flip):
    wire = bytearray(ModbusRelayCodec("client").send(WriteCoil(1, 2, True)))
    wire[position] ^= flip
    server = ModbusRelayCodec("server")
    server.receive_data(bytes(wire))
    with pytest.raises(CodecError, match="CRC mismatch"):
        server.next_event()


def test_leading_noise_is_skipped_and_counted():
    # RTU has no start marker: noise can only be skipped when the byte after it cannot be a
    # function code. Unit 0x30 is no function code, and neither is 0x00.
    client = ModbusRelayCodec("client")
    client.receive_data(b"\x00\x00\x00" + ModbusRelayCodec("server").send(CoilsWritten(0x30, 0, 8)))
    assert client.next_event() == CoilsWritten(0x30, 0, 8)
    assert client.discarded == 3


def test_noise_before_unit_1_makes_the_codec_wait():
    # ...whereas unit 1 reads as FC01 after any noise byte: the codec waits for that
    # would-be frame (the driver's timeout and retry deal with it), and a CRC check ends it.
    client = ModbusRelayCodec("client")
    frame = ModbusRelayCodec("server").send(CoilsWritten(1, 0, 8))
    client.receive_data(b"\x00" + frame)
    assert client.next_event() is NEED_DATA
    client.receive_data(bytes(20))
    events, errors = drain(client)
    assert errors >= 1 and CoilsWritten(1, 0, 8) in events


@settings(max_examples=100, deadline=None)
@given(st.binary(min_size=300, max_size=600))
def test_garbage_never_piles_up(noise):
    client = ModbusRelayCodec("client")
    client.receive_data(noise)
    drain(client)
    assert len(client.buffered) < FramerRTU.MAX_SIZE  # waiting only for one frame's worth


def test_a_claimed_long_frame_waits_then_fails_its_crc():
    client = ModbusRelayCodec("client")
    client.receive_data(b"\x01\x01\xff" + b"\x00" * 200)  # FC01 answer claiming 255 data bytes
    assert client.next_event() is NEED_DATA
    client.receive_data(b"\x00" * 100)
    with pytest.raises(CodecError, match="CRC mismatch"):
        client.next_event()


# -- what the server side makes of odd requests -----------------------------------------------------
def test_server_flags_illegal_coil_value():
    server = ModbusRelayCodec("server")
    server.receive_data(rtu(bytes.fromhex("01 05 0002 1234")))
    ev = server.next_event()
    assert isinstance(ev, IllegalRequest) and ev.function_code == 0x05 and "0x1234" in ev.reason


def test_server_flags_fc0f_byte_count_mismatch():
    server = ModbusRelayCodec("server")
    # 9 coils need 2 bytes; this says 1
    server.receive_data(rtu(bytes.fromhex("01 0F 0000 0009 01 FF")))
    ev = server.next_event()
    assert isinstance(ev, IllegalRequest) and ev.function_code == 0x0F


def test_server_flags_zero_count_read():
    server = ModbusRelayCodec("server")
    server.receive_data(rtu(bytes.fromhex("01 01 0000 0000")))
    assert server.next_event() == IllegalRequest(1, 0x01, "request data pymodbus cannot decode")


def test_server_reports_other_functions():
    server = ModbusRelayCodec("server")
    server.receive_data(rtu(bytes.fromhex("01 03 0000 0001")))  # read holding registers
    assert server.next_event() == OtherRequest(1, 0x03)


def test_client_reports_other_responses_and_exceptions():
    client = ModbusRelayCodec("client")
    client.receive_data(rtu(bytes.fromhex("01 03 02 1234")) + rtu(bytes.fromhex("01 8F 02")))
    assert client.next_event() == OtherResponse(1, 0x03)
    ev = client.next_event()
    assert ev == ExceptionReply(1, 0x0F, 2) and ev.name == "illegal_address"


def test_server_rejects_exception_frames_as_requests():
    server = ModbusRelayCodec("server")
    server.receive_data(rtu(bytes.fromhex("01 81 02")))
    with pytest.raises(CodecError, match="exception response"):
        server.next_event()


def test_roles_only_send_their_side():
    with pytest.raises(ValueError, match="client does not send CoilStatus"):
        ModbusRelayCodec("client").send(CoilStatus(1, (True,) * 8))
    with pytest.raises(ValueError, match="server does not send ReadCoils"):
        ModbusRelayCodec("server").send(ReadCoils(1, 0, 8))
    with pytest.raises(ValueError, match="cannot encode"):
        ModbusRelayCodec("client").send(ReadCoils(1, 0, 0))
    with pytest.raises(ValueError, match="role"):
        ModbusRelayCodec("master")  # type: ignore[arg-type]

"""The Numato-style ASCII relay codec: commands, masks, the reply parser under any split."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from m2s2hil.protocols.ascii_relay import (
    MAX_LINE,
    NEED_DATA,
    Answer,
    Echo,
    EmptyLine,
    Prompt,
    ReadAll,
    RelayOff,
    RelayOn,
    RelayRead,
    ReplyParser,
    Version,
    WriteAll,
    channel_token,
    encode,
    encode_reply,
    format_mask,
    parse_command,
    parse_mask,
)
from m2s2hil.protocols.errors import CodecError


def drain(parser: ReplyParser) -> tuple[list, int]:
    events, errors = [], 0
    for _ in range(10_000):
        try:
            ev = parser.next_event()
        except CodecError:
            errors += 1
            continue
        if ev is NEED_DATA:
            return events, errors
        events.append(ev)
    raise AssertionError("next_event never returned NEED_DATA")


def test_wire_format_of_commands():
    assert encode(RelayOn(0)) == b"relay on 0\r"
    assert encode(RelayOff(7)) == b"relay off 7\r"
    assert encode(RelayRead(10)) == b"relay read A\r"  # Numato letters, not hex: 10 -> A
    assert encode(RelayOn(31)) == b"relay on V\r"
    assert encode(ReadAll()) == b"relay readall\r"
    assert encode(WriteAll(0xA5, 8)) == b"relay writeall a5\r"
    assert encode(WriteAll(0x1, 16)) == b"relay writeall 0001\r"
    assert encode(Version()) == b"ver\r"
    assert encode(EmptyLine()) == b"\r"
    assert encode_reply(["on"]) == b"\n\ron\n\r>"
    assert encode_reply() == b"\n\r>"
    with pytest.raises(ValueError):
        channel_token(32)
    with pytest.raises(ValueError):
        format_mask(0x100, 8)


def test_the_board_ignores_what_it_does_not_understand():
    for line in (
        "relay",
        "relay on",
        "relay on 8",
        "relay on x",
        "relay fly 1",
        "relay writeall zz",
        "relay writeall 123",
        "RELAY ON 0",
        "hello",
    ):
        assert parse_command(line, 8) is None, line
    assert parse_command("relay on 1 junk", 8) == RelayOn(1)  # trailing words are ignored
    assert parse_command("   ", 8) == EmptyLine()


def test_mask_parsing():
    assert parse_mask("a5", 8) == parse_mask("A5", 8) == 0xA5
    for bad in ("", "g0", "100", "-1", " 1"):
        with pytest.raises(CodecError):
            parse_mask(bad, 8)
    with pytest.raises(CodecError, match="beyond"):
        parse_mask("f", 2)


channel_counts = st.integers(1, 32)


@st.composite
def commands(draw, channels=None):
    n = channels if channels is not None else draw(channel_counts)
    ch = st.integers(0, n - 1)
    return draw(
        st.one_of(
            st.builds(RelayOn, ch),
            st.builds(RelayOff, ch),
            st.builds(RelayRead, ch),
            st.just(ReadAll()),
            st.just(Version()),
            st.builds(WriteAll, st.integers(0, (1 << n) - 1), st.just(n)),
        )
    ), n


@settings(max_examples=200, deadline=None)
@given(commands())
def test_command_round_trip(cmd_n):
    cmd, n = cmd_n
    wire = encode(cmd)
    assert wire.endswith(b"\r") and wire.count(b"\r") == 1
    assert parse_command(wire[:-1].decode("ascii"), n) == cmd


@settings(max_examples=200, deadline=None)
@given(channel_counts.flatmap(lambda n: st.tuples(st.just(n), st.integers(0, (1 << n) - 1))))
def test_mask_round_trip(n_mask):
    n, mask = n_mask
    assert parse_mask(format_mask(mask, n), n) == mask


answer_text = st.text(
    alphabet=st.characters(min_codepoint=0x21, max_codepoint=0x7E).filter(lambda c: c != ">"),
    min_size=1,
    max_size=20,
)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(commands(8), st.lists(answer_text, max_size=3)), min_size=1, max_size=4),
    st.data(),
)
def test_any_split_of_a_session_gives_the_same_events(exchanges, data):
    wire = b""
    expected: list = []
    for (cmd, _), answers in exchanges:
        wire += cmd.text.encode() + encode_reply(answers)
        expected += [Echo(cmd.text), *[Answer(a) for a in answers], Prompt()]
    cuts = sorted(set(data.draw(st.lists(st.integers(0, len(wire)), max_size=15))))
    parser = ReplyParser()
    events = []
    prev = 0
    for cut in [*cuts, len(wire)]:
        parser.receive_data(wire[prev:cut])
        prev = cut
        got, errors = drain(parser)
        assert errors == 0
        events += got
    assert events == expected


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=200), max_size=6))
def test_garbage_never_crashes_and_parser_recovers(chunks):
    parser = ReplyParser()
    for chunk in chunks:
        parser.receive_data(chunk)
        drain(parser)
        assert len(parser.buffered) <= MAX_LINE + 1
    parser.reset()
    parser.receive_data(b"relay read 0\n\roff\n\r>")
    assert drain(parser) == ([Echo("relay read 0"), Answer("off"), Prompt()], 0)


def test_garbled_bytes_are_codec_errors_then_parsing_goes_on():
    parser = ReplyParser()
    parser.receive_data(b"rel\xd7y on 0\n\r>")
    with pytest.raises(CodecError, match="0xd7"):
        parser.next_event()
    assert parser.next_event() == Echo("y on 0")
    assert parser.next_event() == Prompt()


def test_overlong_line_is_a_codec_error():
    parser = ReplyParser()
    parser.receive_data(b"x" * (MAX_LINE + 1))
    with pytest.raises(CodecError, match="no line end"):
        parser.next_event()
    assert parser.next_event() is NEED_DATA


def test_crlf_and_lfcr_both_end_lines():
    parser = ReplyParser()
    parser.receive_data(b"ver\r\n00000008\r\n>")
    assert drain(parser) == ([Echo("ver"), Answer("00000008"), Prompt()], 0)

"""Zaber ASCII codec: framing, checksums, message ids, flags; any split, any garbage."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from m2s2hil.protocols.errors import CodecError
from m2s2hil.protocols.zaber import (
    Alert,
    ChecksumMismatch,
    Command,
    CommandParser,
    Info,
    ProtocolViolation,
    ReceivedCommand,
    Reply,
    WarningFlag,
    ZaberReceiver,
    checksum,
    encode_command,
    format_alert,
    format_info,
    format_reply,
    highest_flag,
    parse_command,
)


def test_documented_checksum_example():
    assert encode_command(Command(1, 1, 0, "get pos")) == b"/1 1 00 get pos:2C\n"
    assert checksum(b"1 1 00 get pos") == 0x2C


def test_command_framing_variants():
    assert encode_command(Command(), with_checksum=False) == b"/\n"
    assert encode_command(Command(2), with_checksum=False) == b"/2\n"
    assert encode_command(Command(1, 0, text="  move   abs  5 "), with_checksum=False) == b"/1 0 move abs 5\n"
    assert encode_command(Command(1, 1, 7, "")) == b"/1 1 07:F7\n"


@pytest.mark.parametrize(
    "cmd",
    [Command(None, 1), Command(1, None, 5), Command(1, 1, 100), Command(1, 10), Command(100),
     Command(1, 1, text="get pos:2C"), Command(1, 1, text="5 move"), Command(1, 1, text="caf\u00e9"),
     Command(1, 1, text="get\npos")],
)  # fmt: skip
def test_encoder_refuses_what_cannot_be_framed(cmd):
    with pytest.raises(CodecError):
        encode_command(cmd)


def test_parses_replies_info_and_alerts():
    rx = ZaberReceiver()
    events = rx.feed(
        b"@01 1 12 OK BUSY WR 0:95\r\n@01 0 OK IDLE -- 123 -456\r\n@02 1 05 RJ IDLE FS BADDATA\r\n"
        b"#01 0 12 some info text\r\n!01 1 IDLE NI\r\n"
    )
    assert events == [
        Reply(1, 1, 12, "OK", "BUSY", "WR", "0"),
        Reply(1, 0, None, "OK", "IDLE", "--", "123 -456"),
        Reply(2, 1, 5, "RJ", "IDLE", "FS", "BADDATA"),
        Info(1, 0, 12, "some info text"),
        Alert(1, 1, "IDLE", "NI"),
    ]
    assert events[0].busy and not events[0].fault and events[2].rejected and events[2].fault


def test_bad_checksum_is_typed():
    (ev,) = ZaberReceiver().feed(b"@01 1 12 OK BUSY WR 0:96\r\n")
    assert isinstance(ev, ChecksumMismatch) and isinstance(ev, ProtocolViolation)
    assert isinstance(parse_command(b"/1 1 00 get pos:2D"), ChecksumMismatch)


@pytest.mark.parametrize(
    "line",
    [b"ok", b"@1 1 OK IDLE -- 0", b"@01 x OK IDLE -- 0", b"@01 1 YES IDLE -- 0", b"@01 1 OK NAP -- 0",
     b"@01 1 OK IDLE ?? 0", b"@01 1 OK IDLE --", b"@01 1 OK IDLE -- 0:zz", b"!01 1 SLEEPY --",
     b"@01 1 OK\xff"],
)  # fmt: skip
def test_malformed_replies_are_violations(line):
    (ev,) = ZaberReceiver().feed(line + b"\r\n")
    assert type(ev) is ProtocolViolation


def test_flag_precedence():
    assert highest_flag(["NI", "WR", "FS"]) == "FS"
    assert highest_flag(["NI", "WR"]) == "WR"
    assert highest_flag(["FS", "FQ"]) == "FQ"  # table order within faults
    assert highest_flag(["ZZ", "NI"]) == "NI"
    assert highest_flag([]) == highest_flag(["--"]) == "--"
    assert WarningFlag.FS.value == "stalled and stopped"


def test_device_side_parser():
    p = CommandParser()
    out = p.feed(b"noise/1 1 00 get pos:2C\r\n/\n/2 0 move abs 100\n/1 1 12\n/1 1 get pos:00\n\n")
    assert out[:4] == [
        ReceivedCommand(Command(1, 1, 0, "get pos"), True),
        ReceivedCommand(Command(None, None, None, ""), False),
        ReceivedCommand(Command(2, 0, None, "move abs 100"), False),
        ReceivedCommand(Command(1, 1, 12, ""), False),
    ]
    assert isinstance(out[4], ChecksumMismatch) and len(out) == 5


# -- properties ------------------------------------------------------------------------------
token = st.text("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789.-_", min_size=1, max_size=8)
data = st.lists(token, min_size=1, max_size=4).map(" ".join)
flags = st.sampled_from(["--", *(f.name for f in WarningFlag)])
mid = st.none() | st.integers(0, 99)
text = st.builds(
    lambda a, b: " ".join([a, *b]), token.filter(lambda t: t[0].isalpha()), st.lists(token, max_size=3)
)


replies = st.builds(
    Reply, st.integers(0, 99), st.integers(0, 9), mid, st.sampled_from(["OK", "RJ"]),
    st.sampled_from(["IDLE", "BUSY"]), flags, data,
)  # fmt: skip
infos = st.builds(Info, st.integers(0, 99), st.integers(0, 9), mid, text)
alerts = st.builds(Alert, st.integers(0, 99), st.integers(0, 9), st.sampled_from(["IDLE", "BUSY"]), flags,
                   st.just("") | data)  # fmt: skip


def _frame(ev, cs):
    fmt = {Reply: format_reply, Info: format_info, Alert: format_alert}[type(ev)]
    return fmt(ev, with_checksum=cs)


def _split(blob: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(blob) + 1) for c in cuts})
    return [blob[a:b] for a, b in zip([0, *points], [*points, len(blob)], strict=True)]


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.tuples(replies | infos | alerts, st.booleans()), max_size=8), st.lists(st.integers(0, 10**6))
)
def test_messages_round_trip_under_any_split(items, cuts):
    blob = b"".join(_frame(ev, cs) for ev, cs in items)
    rx = ZaberReceiver()
    assert [e for chunk in _split(blob, cuts) for e in rx.feed(chunk)] == [ev for ev, _ in items]


def _command(address, axis, message_id, text):
    axis = axis if address is not None else None  # an axis needs an address, an id needs an axis
    return Command(address, axis, message_id if axis is not None else None, text)


commands = st.builds(
    _command, st.none() | st.integers(0, 99), st.none() | st.integers(0, 9), mid, st.just("") | text
)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(commands, st.booleans()), max_size=8), st.lists(st.integers(0, 10**6)))
def test_commands_round_trip_under_any_split(items, cuts):
    blob = b"".join(encode_command(c, with_checksum=cs) for c, cs in items)
    parser = CommandParser()
    got = [e for chunk in _split(blob, cuts) for e in parser.feed(chunk)]
    assert got == [ReceivedCommand(c, cs) for c, cs in items]


@settings(max_examples=150, deadline=None)
@given(replies, st.data())
def test_any_single_corruption_of_a_checksummed_reply_is_caught(reply, draw):
    line = format_reply(reply, with_checksum=True)[:-2]
    i = draw.draw(st.integers(1, len(line) - 4))  # a byte the checksum covers
    new = draw.draw(st.integers(0x20, 0x7E).filter(lambda b: b != line[i]))
    bad = line[:i] + bytes([new]) + line[i + 1 :]
    (ev,) = ZaberReceiver().feed(bad + b"\r\n")
    assert isinstance(ev, ChecksumMismatch)


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=400), st.lists(st.integers(0, 10**6), max_size=10))
def test_garbage_never_crashes_and_is_split_invariant(blob, cuts):
    for make in (lambda: ZaberReceiver(max_line=64), lambda: CommandParser(max_line=64)):
        whole = make().feed(blob)
        split = make()
        assert [e for chunk in _split(blob, cuts) for e in split.feed(chunk)] == whole
        assert all(isinstance(e, Reply | Info | Alert | ProtocolViolation | ReceivedCommand) for e in whole)

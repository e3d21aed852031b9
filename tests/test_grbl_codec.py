"""GRBL 1.1 codec: parsing, encoding, flow control, the device-side splitter."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from m2s2hil.protocols.errors import CodecError
from m2s2hil.protocols.grbl import (
    INTEGER_SETTINGS,
    RX_BUFFER_USABLE,
    STATE_NAMES,
    Alarm,
    Banner,
    BufferFull,
    BuildInfo,
    BuildOptions,
    CharacterCounter,
    DeviceLine,
    DeviceLineSplitter,
    Error,
    Feedback,
    GrblAlarm,
    GrblError,
    GrblReceiver,
    Message,
    Ok,
    ProtocolViolation,
    Setting,
    StartupBlock,
    StartupExecuted,
    StatusReport,
    encode_line,
    encode_move,
    format_event,
    is_realtime,
    jog_line,
    move_line,
)

BOOT = b"\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n"


def test_parses_a_boot_and_a_session():
    rx = GrblReceiver()
    events = rx.feed(
        BOOT + b"<Idle|MPos:1.000,-2.500,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n"
        b"ok\r\nerror:15\r\nALARM:2\r\n[MSG:Reset to continue]\r\n"
        b"[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\n$110=500.000\r\n$N0=G20\r\n>G20:ok\r\n"
        b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\n"
    )
    assert events == [
        Banner("1.1h"),
        Message("'$H'|'$X' to unlock"),
        StatusReport("Idle", mpos=(1.0, -2.5, 0.0), feed=0.0, spindle=0.0, wco=(0.0, 0.0, 0.0)),
        Ok(),
        Error(GrblError.JOG_TRAVEL_EXCEEDED),
        Alarm(GrblAlarm.SOFT_LIMIT),
        Message("Reset to continue"),
        BuildInfo("1.1h.20190830", ""),
        BuildOptions("V", 15, 128),
        Setting(110, 500.0),
        StartupBlock(0, "G20"),
        StartupExecuted("G20", "ok"),
        Feedback("GC", "G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0"),
    ]
    assert events[5].critical


def test_named_codes_the_driver_relies_on():
    assert GrblError(5) is GrblError.HOMING_DISABLED
    assert GrblError(8) is GrblError.NOT_IDLE
    assert GrblError(9) is GrblError.LOCKED
    assert GrblError(15) is GrblError.JOG_TRAVEL_EXCEEDED
    assert GrblError(20) is GrblError.UNSUPPORTED_COMMAND
    assert GrblAlarm(1) is GrblAlarm.HARD_LIMIT
    assert GrblAlarm(3) is GrblAlarm.RESET_DURING_MOTION
    assert {GrblAlarm(8), GrblAlarm(9)} == {GrblAlarm.HOMING_FAIL_PULLOFF, GrblAlarm.HOMING_FAIL_APPROACH}


def test_unknown_codes_stay_numbers():
    assert GrblReceiver().feed(b"error:99\r\nALARM:42\r\n") == [Error(99), Alarm(42)]


def test_status_report_states_and_fields():
    rx = GrblReceiver()
    ev = rx.feed(b"<Hold:1|WPos:1.000,2.000,3.000|Bf:15,127|Ln:7|F:500|Pn:XP|Ov:100,50,120|A:SF|Zz:9>\r\n")[0]
    assert ev.state_text == "Hold:1" and ev.moving
    assert ev.wpos == (1.0, 2.0, 3.0) and ev.mpos is None
    assert ev.buffer == (15, 127) and ev.line_number == 7 and ev.feed == 500.0 and ev.spindle is None
    assert ev.pins == "XP" and ev.overrides == (100, 50, 120) and ev.accessories == "SF"
    assert ev.extra == (("Zz", "9"),)
    assert ev.machine_position(wco=(1.0, 1.0, 1.0)) == (2.0, 3.0, 4.0)
    for name in STATE_NAMES:
        assert rx.feed(f"<{name}|MPos:0,0,0>\r\n".encode())[0].state == name
    assert not rx.feed(b"<Hold:0|MPos:0,0,0>\r\n")[0].moving


@pytest.mark.parametrize(
    "line",
    [b"<Walk|MPos:0,0,0>", b"<Idle|MPos:a,b,c>", b"<Idle|FS:0,0>", b"<Idle|MPos:0,0,0|FS:1>", b"ok then",
     b"error:x", b"[NOCOLON]", b"\x00ok", b"Grbl", b"<Idle|MPos:nan,0,0>"],
)  # fmt: skip
def test_malformed_lines_are_violations(line):
    (ev,) = GrblReceiver().feed(line + b"\r\n")
    assert isinstance(ev, ProtocolViolation) and ev.line.startswith(line[:3])


def test_overlong_line_is_one_violation_then_parsing_resumes():
    rx = GrblReceiver(max_line=16)
    events = rx.feed(b"x" * 40 + b"\r\nok\r\n")
    assert [type(e) for e in events] == [ProtocolViolation, Ok]
    assert events[0].line == b"x" * 16


# -- round trips and splits -------------------------------------------------------------
printable = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=30)
word = st.text(
    st.characters(min_codepoint=0x21, max_codepoint=0x7E, exclude_characters=":"), min_size=1, max_size=12
)
grid = st.integers(-(10**7), 10**7).map(lambda k: k / 1000)
axes3 = st.tuples(grid, grid, grid)


@st.composite
def status_reports(draw):
    state = draw(st.sampled_from(STATE_NAMES))
    sub = draw(st.integers(0, 3)) if state in ("Hold", "Door") else None
    machine = draw(st.booleans())
    pos = draw(axes3)
    feed_kind = draw(st.sampled_from(["none", "feed", "both"]))
    feed = draw(st.integers(0, 10**6).map(lambda k: k / 1000)) if feed_kind != "none" else None
    spindle = draw(st.integers(0, 30000).map(float)) if feed_kind == "both" else None
    return StatusReport(
        state=state,
        substate=sub,
        mpos=pos if machine else None,
        wpos=None if machine else pos,
        wco=draw(st.none() | axes3),
        feed=feed,
        spindle=spindle,
        pins=draw(st.none() | st.text("XYZPDHRS", min_size=1, max_size=4)),
        overrides=draw(st.none() | st.tuples(*[st.integers(10, 200)] * 3)),
        buffer=draw(st.none() | st.tuples(st.integers(0, 15), st.integers(0, 127))),
        line_number=draw(st.none() | st.integers(0, 99999)),
        accessories=draw(st.none() | st.text("SCFM", min_size=1, max_size=3)),
    )


@st.composite
def settings_events(draw):
    n = draw(st.integers(0, 140))
    value = draw(st.integers(0, 10**5)) if n in INTEGER_SETTINGS else draw(st.integers(0, 10**8)) / 1000
    return Setting(n, float(value))


events = st.one_of(
    st.just(Ok()),
    st.sampled_from(GrblError).map(Error),
    st.sampled_from(GrblAlarm).map(Alarm),
    st.builds(Banner, st.text("0123456789.abcdefgh", min_size=1, max_size=6), printable),
    st.builds(Message, printable),
    st.builds(BuildInfo, word.filter(lambda t: "]" not in t), printable),
    st.builds(BuildOptions, st.text("VNMHTACDZLS*+", min_size=1, max_size=6), st.integers(1, 40),
              st.integers(1, 1024)),
    settings_events(),
    st.builds(StartupBlock, st.integers(0, 1), printable),
    st.builds(StartupExecuted, word, printable),
    st.builds(Feedback, word.filter(lambda t: t not in ("MSG", "VER", "OPT")), printable),
    status_reports(),
)  # fmt: skip


def _split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    return [data[a:b] for a, b in zip([0, *points], [*points, len(data)], strict=True)]


@settings(max_examples=150, deadline=None)
@given(st.lists(events, max_size=8), st.lists(st.integers(0, 10**6), max_size=10))
def test_round_trip_under_any_split(evs, cuts):
    data = b"".join(format_event(e) for e in evs)
    rx = GrblReceiver()
    got = [e for chunk in _split(data, cuts) for e in rx.feed(chunk)]
    assert got == evs
    assert rx.partial == b""


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=400), st.lists(st.integers(0, 10**6), max_size=10))
def test_garbage_never_crashes_and_is_split_invariant(data, cuts):
    whole = GrblReceiver(max_line=64).feed(data)
    rx = GrblReceiver(max_line=64)
    pieces = [e for chunk in _split(data, cuts) for e in rx.feed(chunk)]
    assert pieces == whole
    for line in data.split(b"\n")[:-1]:  # every complete line with a non-ASCII byte is flagged
        if any(b > 0x7E for b in line) and len(line) <= 64:
            assert any(isinstance(e, ProtocolViolation) and e.line == line for e in whole)


# -- encoders -----------------------------------------------------------------------------
def test_command_lines():
    assert move_line({"X": 90}, feed=3600, machine=True) == "G90 G53 G1 X90 F3600"
    assert move_line({"X": -1.23456, "Y": 0.5}) == "G90 G0 X-1.2346 Y0.5"
    assert move_line({"Z": -0.00001}, incremental=True) == "G91 G0 Z0"
    assert jog_line({"X": -5}, feed=600) == "$J=G91 X-5 F600"
    assert jog_line({"Y": 30}, feed=1200.5, machine=True) == "$J=G53 Y30 F1200.5"
    assert encode_move({"X": 1}) == b"G90 G0 X1\n"
    assert encode_line("$H") == b"$H\n"


@pytest.mark.parametrize("bad", ["G0 X1?", "!", "G0\nX1", "G0 X1~", "caf\u00e9", "X" * 80])
def test_encode_line_refuses_what_grbl_would_mangle(bad):
    with pytest.raises(CodecError):
        encode_line(bad)


def test_encoders_refuse_bad_arguments():
    for call in (
        lambda: move_line({"A": 1}),
        lambda: move_line({}),
        lambda: move_line({"X": 1}, feed=0),
        lambda: move_line({"X": float("nan")}),
        lambda: move_line({"X": 1}, incremental=True, machine=True),
        lambda: jog_line({"X": 1}, feed=-3),
    ):
        with pytest.raises(CodecError):
            call()


# -- character counting ---------------------------------------------------------------------
def test_counter_refuses_overflow_and_retires_in_order():
    c = CharacterCounter()
    assert c.capacity == RX_BUFFER_USABLE == 127
    a, b = b"G1 X1 F100\n", b"G1 X2\n"
    c.sent(a)
    c.sent(b)
    assert c.outstanding == len(a) + len(b) and c.in_flight == 2
    with pytest.raises(BufferFull):
        c.sent(b"G0" + b" " * 120 + b"\n")
    assert c.acknowledged() == len(a)
    assert c.acknowledged() == len(b)
    with pytest.raises(CodecError):
        c.acknowledged()
    with pytest.raises(BufferFull, match="never fit"):
        c.sent(b"x" * 128)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.integers(2, 80), st.booleans()), max_size=60))
def test_counter_never_exceeds_capacity(ops):
    c = CharacterCounter()
    model: list[int] = []
    for length, ack in ops:
        line = b"x" * (length - 1) + b"\n"
        if ack and model:
            assert c.acknowledged() == model.pop(0)
        elif c.fits(line):
            c.sent(line)
            model.append(length)
        else:
            with pytest.raises(BufferFull):
                c.sent(line)
        assert c.outstanding == sum(model) <= c.capacity


# -- device side ------------------------------------------------------------------------------
def test_device_splitter_cleans_lines_like_grbl():
    sp = DeviceLineSplitter()
    assert sp.feed(b"g0 x1 (comment) y2 ; rest\r\n") == [DeviceLine("G0X1Y2"), DeviceLine("")]
    assert sp.feed(b"$J=G91 X") == []
    assert sp.feed(b"-5 F600\n\n") == [DeviceLine("$J=G91X-5F600"), DeviceLine("")]
    (long,) = sp.feed(b"G0" + b"X1" * 60 + b"\n")
    assert long.overflow and len(long.text) == 79


def test_realtime_bytes_are_picked_out():
    assert all(is_realtime(b) for b in b"?!~\x18\x85\x84\x90")
    assert not any(is_realtime(b) for b in b"G0X1$H\r\n ")


def test_format_event_refuses_non_events():
    with pytest.raises(CodecError):
        format_event("ok")  # type: ignore[arg-type]

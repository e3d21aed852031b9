"""The GRBL simulator behaves as GRBL 1.1 does at the byte level, on a virtual clock."""

import itertools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from m2s2hil.protocols.grbl import (
    Alarm,
    Banner,
    BuildInfo,
    CharacterCounter,
    Error,
    GrblAlarm,
    GrblError,
    GrblReceiver,
    Message,
    Ok,
    Setting,
    StatusReport,
)
from m2s2hil.simulators.grbl import GrblSimulator
from m2s2hil.simulators.grbl_settings import GrblAxisSettings
from m2s2hil.simulators.motion_kit import Trapezoid


class Host:
    """Talks to the device the way a serial port would, on the virtual clock."""

    def __init__(self, sim, clock):
        self.sim, self.clock, self.rx = sim, clock, GrblReceiver()

    def io(self, data: bytes = b"", wait: float = 0.0):
        if data:
            self.sim.receive(data)
        self.clock.advance(wait)
        return self.rx.feed(self.sim.take())

    def status(self) -> StatusReport:
        (ev,) = self.io(b"?")
        return ev


def make(vclock, **kw):
    kw.setdefault("axes", {"X": GrblAxisSettings(max_rate=600.0, accel=100.0)})
    sim = GrblSimulator("g", vclock, **kw)
    return sim, Host(sim, vclock)


BANNER_UNLOCK = [Banner("1.1h"), Message("'$H'|'$X' to unlock")]


def test_factory_settings_are_grbl_1_1h_defaults_generic(vclock):
    # DEFAULTS_GENERIC of grbl/defaults.h (gnea/grbl v1.1h), numbered as in "Grbl v1.1 Configuration".
    sim = GrblSimulator("g", vclock)
    host = Host(sim, vclock)
    got = {e.number: e.value for e in host.io(b"$$\n") if isinstance(e, Setting)}
    expected = {
        0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
        20: 0, 21: 0, 22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
        100: 250.0, 101: 250.0, 102: 250.0, 110: 500.0, 111: 500.0, 112: 500.0,
        120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0,
    }  # fmt: skip
    assert got == expected
    # Homing disabled: no boot lock, and $H is "setting disabled".
    assert host.status().state == "Idle"
    assert host.io(b"$H\n") == [Error(GrblError.HOMING_DISABLED)]
    assert host.io(b"\x18") == [Banner("1.1h")]  # not in alarm: no unlock message


def test_motion_is_a_trapezoid_on_the_clock(vclock):
    sim, host = make(vclock)  # 600 units/min = 10 units/s, 100 units/s^2: 0.1 s ramps
    assert host.io(b"G0 X10\n") == [Ok()]
    vclock.advance(0.05)
    assert sim.axis_position("X") == pytest.approx(0.125)
    vclock.advance(0.55)
    st_ = host.status()
    assert (st_.state, st_.mpos[0], st_.feed) == ("Run", pytest.approx(5.5), pytest.approx(600.0))
    vclock.advance(0.5)
    assert host.status().state == "Idle" and sim.axis_position("X") == pytest.approx(10.0)
    # A diagonal is limited by the slower axis (Y keeps the factory 500/min, 10/s^2).
    host.io(b"G91 G1 X3 Y4 F6000\n")
    vclock.advance(10)
    assert sim.machine_position() == pytest.approx((13.0, 4.0, 0.0))


def test_modal_state_units_and_relative_moves(vclock):
    sim, host = make(vclock)
    host.io(b"G20 G91\n")
    host.io(b"G0 X0.1\n", wait=5)
    host.io(b"X0.1\n", wait=5)
    assert sim.axis_position("X") == pytest.approx(5.08)
    (gc, ok) = host.io(b"$G\n")
    assert gc.text.startswith("G0 G54 G17 G20 G91") and ok == Ok()


@pytest.mark.parametrize(
    "line, code",
    [(b"G2 X1\n", GrblError.UNSUPPORTED_COMMAND), (b"G0 G1 X1\n", GrblError.MODAL_GROUP_VIOLATION),
     (b"X1 X2\n", GrblError.WORD_REPEATED), (b"G1 X1\n", GrblError.UNDEFINED_FEED_RATE),
     (b"1G0\n", GrblError.EXPECTED_COMMAND_LETTER), (b"GX\n", GrblError.BAD_NUMBER_FORMAT),
     (b"$J=G91 X1\n", GrblError.UNDEFINED_FEED_RATE), (b"$J=M5 X1 F10\n", GrblError.INVALID_JOG_COMMAND),
     (b"$J=G91 F100\n", GrblError.NO_AXIS_WORDS), (b"$999=1\n", GrblError.INVALID_STATEMENT),
     (b"$110=-5\n", GrblError.NEGATIVE_VALUE), (b"$110=abc\n", GrblError.BAD_NUMBER_FORMAT),
     (b"$H\n", GrblError.HOMING_DISABLED), (b"$20=1\n", GrblError.SOFT_LIMITS_NEED_HOMING),
     (b"G0" + b"X1" * 50 + b"\n", GrblError.LINE_OVERFLOW)],
)  # fmt: skip
def test_error_codes(vclock, line, code):
    _, host = make(vclock)
    assert host.io(line) == [Error(code)]


def test_cr_lf_is_two_lines_and_settings_round_trip(vclock):
    sim, host = make(vclock)
    assert host.io(b"\r\n") == [Ok(), Ok()]
    assert host.io(b"$110=1234.5\n") == [Ok()]
    events = host.io(b"$$\n")
    assert Setting(110, 1234.5) in events and events[-1] == Ok()
    assert sim.settings[110] == 1234.5
    ver, opt, _ = host.io(b"$I\n")
    assert ver == BuildInfo("1.1h.20190830", "") and (opt.planner_blocks, opt.rx_buffer) == (15, 128)


def test_boot_lock_homing_and_unlock(vclock):
    sim, host = make(vclock, settings={22: 1}, axes={"X": GrblAxisSettings(start=25.0)})
    assert host.io(b"\x18") == BANNER_UNLOCK
    assert host.io(b"G0 X1\n") == [Error(GrblError.LOCKED)]
    assert host.io(b"$H\n") == []  # homing takes time: the ok comes when it is done
    assert host.status().state == "Home"
    vclock.advance(30)
    assert host.io() == [Ok()]
    assert sim.axis_position("X") == pytest.approx(0.0) and host.status().mpos[0] == 0.0
    host.io(b"\x18")
    host.io(b"$X\n")  # already unlocked: just ok
    assert host.status().state == "Idle"


def test_soft_limit_alarm_is_critical_until_reset(vclock):
    _, host = make(vclock, settings={22: 1, 20: 1}, axes={"X": GrblAxisSettings(max_travel=100.0)})
    host.io(b"$X\n")
    assert host.io(b"$J=G91 X5 F100\n") == [Error(GrblError.JOG_TRAVEL_EXCEEDED)]  # travel is [-100, 0]
    assert host.io(b"G0 X-50\n") == [Ok()]
    assert host.io(b"G0 X-150\n") == [Alarm(GrblAlarm.SOFT_LIMIT), Message("Reset to continue")]
    assert host.io(b"?", wait=1) == []  # GRBL ignores everything but a reset now
    assert host.io(b"$X\n", wait=1) == []
    # The offending line's mc_line returns after the reset: its ok, then the banner.
    assert host.io(b"\x18") == [Ok(), *BANNER_UNLOCK]
    assert host.status().state == "Alarm"
    assert host.io(b"$X\n") == [Message("Caution: Unlocked"), Ok()]


def test_soft_limit_while_moving_stops_under_control_first(vclock):
    x = GrblAxisSettings(max_rate=600.0, accel=100.0, max_travel=100.0)
    sim, host = make(vclock, settings={22: 1, 20: 1}, axes={"X": x})
    host.io(b"$X\n")
    assert host.io(b"G0 X-50\n", wait=1) == [Ok()]  # cruising at 10 units/s by now
    assert host.io(b"G0 X-150\n") == []  # feed hold first: no alarm, no ok yet
    assert host.status().state_text == "Hold:1"
    vclock.advance(0.2)  # 0.1 s to brake from 10 units/s at 100 units/s^2
    assert host.io() == [Alarm(GrblAlarm.SOFT_LIMIT), Message("Reset to continue")]
    stopped = sim.axis_position("X")
    assert stopped == pytest.approx(-10.0)  # 0.5 ramping up + 9 cruising + 0.5 braking
    assert host.io(b"\x18") == [Ok(), *BANNER_UNLOCK]
    assert sim.axis_position("X") == stopped


def test_reset_during_soft_limit_stop_is_alarm_3_then_the_ok(vclock):
    _, host = make(vclock, settings={22: 1, 20: 1}, axes={"X": GrblAxisSettings(max_travel=100.0)})
    host.io(b"$X\n")
    host.io(b"G0 X-50\n", wait=1)
    host.io(b"G0 X-150\n")
    assert host.io(b"\x18") == [Alarm(GrblAlarm.RESET_DURING_MOTION), Ok(), *BANNER_UNLOCK]


def test_hold_resume_and_jog_cancel(vclock):
    _, host = make(vclock)
    host.io(b"G0 X10\n", wait=0.5)
    host.io(b"!")
    assert host.status().state_text == "Hold:1"
    vclock.advance(0.5)
    held = host.status()
    assert held.state_text == "Hold:0" and held.mpos[0] < 10
    vclock.advance(1)
    assert host.status().mpos == held.mpos
    host.io(b"~", wait=5)
    assert host.status().mpos[0] == pytest.approx(10.0)
    host.io(b"$J=G91 X100 F600\n", wait=1)
    assert host.status().state == "Jog"
    assert host.io(b"G0 X0\n") == [Error(GrblError.LOCKED)]
    host.io(b"\x85", wait=1)
    stopped = host.status()
    assert stopped.state == "Idle" and 15 < stopped.mpos[0] < 30


def test_reset_while_moving_alarms(vclock):
    sim, host = make(vclock)
    host.io(b"G0 X10\n", wait=0.3)
    assert host.io(b"\x18") == [Alarm(GrblAlarm.RESET_DURING_MOTION), *BANNER_UNLOCK]
    x = sim.axis_position("X")
    vclock.advance(2)
    assert sim.axis_position("X") == x and host.status().state == "Alarm"


def test_stall_and_alarm_faults(vclock):
    sim, host = make(vclock)
    sim.faults.add("stall", fraction=0.25)
    host.io(b"G0 X20\n", wait=5)
    st_ = host.status()
    assert (
        st_.state == "Idle"
        and st_.mpos[0] == pytest.approx(5.0)
        and sim.axis_position("X") == pytest.approx(5.0)
    )
    sim.faults.add("alarm")
    host.io(b"G0 X25\n")
    vclock.advance(5)
    assert host.io() == [Alarm(GrblAlarm.HARD_LIMIT), Message("Reset to continue")]
    assert sim.axis_position("X") == pytest.approx(15.0)
    assert host.io(b"\x18") == BANNER_UNLOCK  # no line was executing: no ok


def test_hard_limit_with_a_line_blocked_on_the_planner_owes_its_ok(vclock):
    sim, host = make(vclock)
    sim.faults.add("alarm", at=0.5)
    lines = b"".join(f"G1 X{i % 2 + 1} F60\n".encode() for i in range(16))  # one more than the planner
    assert sum(isinstance(e, Ok) for e in host.io(lines)) == 15
    vclock.advance(1)
    assert host.io() == [Alarm(GrblAlarm.HARD_LIMIT), Message("Reset to continue")]
    assert host.io(b"\x18") == [Ok(), *BANNER_UNLOCK]


def test_homing_failure_alarm_resets_the_controller(vclock):
    sim, host = make(vclock, settings={22: 1}, axes={"X": GrblAxisSettings(start=10.0)})
    sim.faults.add("alarm")
    # limits_go_home resets the controller itself; $H still returns STATUS_OK (system.c).
    assert host.io(b"$H\n", wait=10) == [Alarm(GrblAlarm.HOMING_FAIL_APPROACH), Ok(), *BANNER_UNLOCK]


def test_reset_during_homing_is_alarm_6_then_the_ok_of_h(vclock):
    _, host = make(vclock, settings={22: 1}, axes={"X": GrblAxisSettings(start=10.0)})
    host.io(b"$H\n", wait=0.5)
    assert host.io(b"\x18") == [Alarm(GrblAlarm.HOMING_FAIL_RESET), Ok(), *BANNER_UNLOCK]


def test_g10_l20_sets_a_persistent_work_origin(vclock):
    sim, host = make(vclock)
    host.io(b"G0 X7\n", wait=5)
    assert host.io(b"G10 L20 P1 X0\n") == [Ok()]
    events = host.io(b"$#\n")
    assert events[0].tag == "G54" and events[0].text == "7.000,0.000,0.000" and events[-1] == Ok()
    report = host.status()
    assert report.mpos[0] == pytest.approx(7.0) and report.wco == (7.0, 0.0, 0.0)
    host.io(b"G0 X3\n", wait=5)  # absolute targets are work coordinates now
    assert sim.axis_position("X") == pytest.approx(10.0)
    host.io(b"G53 G0 X1\n", wait=5)  # G53: machine coordinates
    assert sim.axis_position("X") == pytest.approx(1.0)
    assert host.io(b"$10=0\n") == [Ok()]
    assert host.status().wpos[0] == pytest.approx(-6.0)
    # EEPROM: survives a soft reset and a power cycle (where MPos restarts at 0).
    host.io(b"\x18")
    sim.vanish(0.1)
    vclock.advance(0.2)
    host.io()
    assert host.io(b"$#\n")[0].text == "7.000,0.000,0.000"
    assert host.io(b"G10 L2 P1 X-2.5\n") == [Ok()]
    assert host.io(b"$#\n")[0].text == "-2.500,0.000,0.000"
    assert host.io(b"G10 L20 Y1\n") == [Ok()]  # no P: the active system (G54)
    assert host.io(b"G10 L2 P2 Z4\n") == [Ok()]  # G55 is stored, though only G54 can be active here
    g54, g55 = host.io(b"$#\n")[:2]
    assert (g54.text, g55.tag, g55.text) == ("-2.500,-1.000,0.000", "G55", "0.000,0.000,4.000")
    assert host.io(b"$RST=#\n") == [Message("Restoring defaults"), Ok(), Banner("1.1h")]
    assert host.io(b"$#\n")[0].text == "0.000,0.000,0.000"
    host.io(b"$110=123\n$I=bench\nG10 L2 P1 X4\n")
    host.io(b"$RST=$\n")  # settings only (GRBL upper-cases every line, $I text too)
    assert sim.settings[110] == 600.0 and sim.coord_data[54][0] == 4.0 and sim.eeprom.build_text == "BENCH"
    host.io(b"$RST=*\n")  # everything in EEPROM
    assert sim.coord_data[54][0] == 0.0 and sim.eeprom.build_text == ""


def test_g10_waits_for_motion_to_finish(vclock):
    sim, host = make(vclock)
    assert host.io(b"G0 X10\nG10 L20 P1 X0\n") == [Ok()]  # the G10 waits (buffer sync)
    assert host.io(wait=5) == [Ok()]
    assert sim.coord_data[54][0] == pytest.approx(10.0)


@pytest.mark.parametrize(
    "line, code",
    [(b"G10 X0\n", GrblError.VALUE_WORD_MISSING), (b"G10 P1 X0\n", GrblError.UNSUPPORTED_COMMAND),
     (b"G10 L20 P7 X0\n", GrblError.UNSUPPORTED_COORD_SYSTEM), (b"G10 L2 P9\n", GrblError.NO_AXIS_WORDS),
     (b"G10 L1 P1 X0\n", GrblError.UNSUPPORTED_COMMAND), (b"G10 L20 P1\n", GrblError.NO_AXIS_WORDS),
     (b"G0 G10 L20 P1 X0\n", GrblError.AXIS_COMMAND_CONFLICT),
     (b"G10 L20 P-1 X0\n", GrblError.NEGATIVE_VALUE)],
)  # fmt: skip
def test_g10_errors(vclock, line, code):
    _, host = make(vclock)
    assert host.io(line) == [Error(code)]



def test_receive_buffer_loses_bytes_unless_the_host_counts(vclock):
    lines = [f"G1 X{i % 2} F6000\n".encode() for i in range(40)]  # many short moves fill the planner
    sim, host = make(vclock)
    sim.receive(b"".join(lines))  # a naive sender: everything at once
    assert sim.rx_overflow > 0
    oks = sum(isinstance(e, Ok) for e in host.io(wait=60))
    assert oks < len(lines)

    sim, host = make(vclock)
    counter, pending, acked = CharacterCounter(), list(lines), 0
    while acked < len(lines):
        while pending and counter.fits(pending[0]):
            counter.sent(pending[0])
            sim.receive(pending.pop(0))
        for ev in host.io(wait=0.01):
            assert ev == Ok()
            counter.acknowledged()
            acked += 1
    assert sim.rx_overflow == 0


def test_replies_stay_in_order_with_a_late_reply(vclock):
    sim, host = make(vclock)
    sim.faults.add("late_reply", delay_s=1.0)
    assert host.io(b"$I\n") == []
    assert host.io(b"G4\n") == []  # its error waits behind the late reply
    events = host.io(wait=1.0)
    assert isinstance(events[0], BuildInfo) and events[-1] == Error(GrblError.UNSUPPORTED_COMMAND)


def test_power_cycle_loses_position_not_the_axis(vclock):
    sim, host = make(vclock, settings={22: 1})
    host.io(b"$X\n")
    host.io(b"G0 X7\n", wait=5)
    sim.vanish(0.5)
    vclock.advance(0.6)
    assert host.io() == BANNER_UNLOCK
    assert host.status().mpos[0] == 0.0 and sim.axis_position("X") == pytest.approx(7.0)


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0, 1000),
    st.floats(0.1, 100),
    st.floats(0.1, 100),
    st.floats(0, 100),
    st.lists(st.floats(0, 1), min_size=2, max_size=6),
)
def test_trapezoid_profile_is_consistent(length, v_max, accel, v0, fractions):
    p = Trapezoid(length, v_max, accel, v0=v0)
    times = sorted(f * p.duration for f in fractions)
    dist = [p.distance(t) for t in times]
    assert all(b >= a - 1e-9 for a, b in itertools.pairwise(dist))
    assert p.distance(p.duration + 1) == length and p.distance(-1) == 0
    assert all(p.speed(t) <= max(v_max, v0) + 1e-9 for t in times)
    for s in (length * f for f in fractions):
        assert p.distance(p.time_at(s)) == pytest.approx(s, abs=1e-6 * max(1, length))


def test_rig_options_commission_the_simulated_controller(vclock):
    from types import SimpleNamespace

    from m2s2hil.simulators.grbl import grbl_sim_for

    turntable = SimpleNamespace(axis="x", units_per_degree=2.0, max_speed_dps=60.0, accel_dps2=120.0,
                                min_deg=-370.0, max_deg=370.0)
    axes = {"turntable": turntable}
    factory = grbl_sim_for("g1", axes, vclock, None, None, {"factory_rates": True})
    assert (factory.settings[22], factory.settings[110], factory.settings[120]) == (0, 500.0, 10.0)
    assert factory.state == "Idle"
    rig = grbl_sim_for("g2", axes, vclock, None, None,
                       {"homing_switches": True, "settings": {"$111": 99, "25": 1000}, "version": "1.1f"})
    # Commissioned to the rig file: 60°/s × 2 units/° × 60 s/min, 120°/s² × 2, twice the widest limit.
    assert (rig.settings[110], rig.settings[120], rig.settings[130]) == (7200.0, 240.0, 1480.0)
    assert (rig.settings[22], rig.settings[111], rig.settings[25], rig.version) == (1.0, 99.0, 1000.0, "1.1f")
    assert rig.state == "Alarm"  # homing on: boots locked
    for bad, match in (({"homing": True}, "unknown GRBL simulator option"),
                       ({"settings": {"$110": "fast"}}, "expected a number"),
                       ({"settings": {"$999": 1}}, "no setting"), ({"settings": [1]}, "table")):
        with pytest.raises(ValueError, match=match):
            grbl_sim_for("g3", axes, vclock, None, None, bad)

"""The GRBL driver: byte-exact command sequences, the simulator in-process and over a pty,
and every injected fault ending in its typed error or a recovery."""

import itertools
from types import SimpleNamespace

import pytest
import serial
from m2s2hil.drivers.clock import SYSTEM_CLOCK, SystemClock
from m2s2hil.drivers.errors import (
    CommandRejected,
    ControllerLocked,
    DeviceGone,
    DeviceTimeout,
    MoveNotVerified,
    ProtocolError,
    SoftLimitError,
    StageAlarm,
)
from m2s2hil.drivers.grbl import GrblController
from m2s2hil.drivers.interfaces import RotaryAxis
from m2s2hil.protocols.grbl import GrblAlarm, GrblError
from m2s2hil.simulators import registry
from m2s2hil.simulators.grbl import GrblSimulator
from m2s2hil.simulators.grbl_settings import GrblAxisSettings
from m2s2hil.simulators.pty import PtyServer
from m2s2hil.simulators.scripted import ScriptedDevice
from m2s2hil.simulators.world import World

from m2s2hil.rig.manual import ManualControl

_names = itertools.count()
BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"
UNLOCK_MSG = b"[MSG:'$H'|'$X' to unlock]\r\n"
TURNTABLE = dict(
    units_per_degree=1.0, min_deg=-370, max_deg=370, max_speed_dps=60, accel_dps2=120, tolerance_deg=0.05
)
TILT = dict(
    units_per_degree=1.0, min_deg=-30, max_deg=30, max_speed_dps=20, accel_dps2=40, tolerance_deg=0.05
)


def status(state: str, x: float = 0.0, y: float = 0.0, feed: int = 0) -> bytes:
    return f"<{state}|MPos:{x:.3f},{y:.3f},0.000|FS:{feed},0>\r\n".encode()


CONNECT = [
    (b"\x18", BANNER + UNLOCK_MSG),
    (b"$I\n", b"[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n"),
    (b"$$\n", b"$22=1\r\n$110=3600.000\r\n$111=1200.000\r\n$120=120.000\r\n$121=40.000\r\nok\r\n"),
    (b"?", status("Alarm")),
]


@pytest.fixture
def scripted(vclock):
    made = []

    def make(script, *, connect=True):
        name = f"grbl-script-{next(_names)}"
        dev = ScriptedDevice(name, vclock, (CONNECT if connect else []) + script)
        registry.register(name, dev)
        ctl = GrblController(f"sim://{name}", device="stage", clock=vclock)
        if connect:
            ctl.connect()
        else:
            ctl.link.open()
        made.append((name, ctl))
        return dev, ctl

    yield make
    for name, ctl in made:
        ctl.close()
        registry.unregister(name)


def test_connect_is_byte_exact(scripted):
    dev, ctl = scripted([])
    dev.verify()
    assert ctl.version == "1.1h.20190830"
    assert ctl.settings == {22: 1.0, 110: 3600.0, 111: 1200.0, 120: 120.0, 121: 40.0}
    assert "'$H'|'$X' to unlock" in ctl.messages


def test_connect_without_reset_wakes_with_an_empty_line(scripted):
    dev, ctl = scripted([(b"\n", b"ok\r\n"), *CONNECT[1:]], connect=False)
    ctl.link.close()
    assert ctl.connect(reset=False).state == "Alarm"
    dev.verify()


def test_home_and_verified_move_are_byte_exact(scripted, vclock):
    dev, ctl = scripted(
        [
            (b"$H\n", b"ok\r\n"),
            (b"?", status("Idle")),
            (b"?", status("Idle")),  # where the move starts from (for its time budget)
            (b"G90 G53 G1 X90 F3600\n", b"ok\r\n"),
            (b"?", status("Run", 45.0, feed=3600)),
            (b"?", status("Idle", 90.0)),
            (b"?", status("Idle", 90.0)),  # read-back
        ]
    )
    axis = ctl.axis("X", name="turntable", **TURNTABLE)
    assert isinstance(axis, RotaryAxis)
    axis.home()
    assert axis.move_to(90.0) == 90.0
    dev.verify()


def test_rotate_and_stop_sequences_are_byte_exact(scripted):
    dev, ctl = scripted(
        [
            (b"$J=G53 X-370 F1800\n", b"ok\r\n"),
            (b"?", status("Jog", -20.0, feed=1800)),
            (b"\x85", b""),
            (b"?", status("Idle", -21.0)),
            (b"G90 G53 G1 X10 F3600\n", b"ok\r\n"),
            (b"?", status("Run", 5.0, feed=3600)),
            (b"!", b""),
            (b"?", status("Hold:1", 6.0, feed=1000)),
            (b"?", status("Hold:0", 6.5)),
            (b"\x18", BANNER),
            (b"?", status("Idle", 6.5)),
        ]
    )
    axis = ctl.axis("X", name="turntable", **TURNTABLE)
    axis.rotate(30.0, direction=-1)
    axis.stop()  # a jog: jog cancel, wait for Idle
    axis.move_to(10.0, wait=False)
    axis.stop()  # a G-code move: feed hold, then a reset flushes the planner without an alarm
    dev.verify()


def test_soft_limits_are_enforced_before_anything_is_sent(scripted):
    dev, ctl = scripted([], connect=False)
    axis = ctl.axis("Y", name="tilt", **TILT)
    for call in (lambda: axis.move_to(31.0), lambda: axis.move_to(-90), lambda: axis.rotate(25.0)):
        with pytest.raises(SoftLimitError, match="tilt"):
            call()
    assert dev.received == b""


def test_error_replies_become_command_rejected(scripted):
    dev, ctl = scripted(
        [(b"$H\n", b"error:5\r\n"), (b"?", status("Alarm")), (b"G90 G53 G1 X10 F3600\n", b"error:9\r\n")]
    )
    axis = ctl.axis("X", name="turntable", **TURNTABLE)
    with pytest.raises(CommandRejected) as exc:
        axis.home()
    assert exc.value.code is GrblError.HOMING_DISABLED and exc.value.command == "$H"
    assert exc.value.fault_class == "protocol"
    with pytest.raises(ControllerLocked) as exc:
        axis.move_to(10)
    assert exc.value.code is GrblError.LOCKED and exc.value.device == "stage"
    # a locked controller is an alarm to recover from (home or unlock), not a command to retry
    assert isinstance(exc.value, CommandRejected) and exc.value.fault_class == "alarm"
    dev.verify()


def test_wrong_firmware_is_refused(scripted):
    dev, ctl = scripted(
        [(b"\x18", b"\r\nGrbl 0.9j ['$' for help]\r\n"), (b"$I\n", b"[VER:0.9j.20160303:]\r\nok\r\n")],
        connect=False,
    )
    ctl.link.close()
    with pytest.raises(ProtocolError, match="not GRBL 1.1"):
        ctl.connect()
    dev.verify()


def test_critical_alarm_blocks_until_reset(scripted):
    dev, ctl = scripted(
        [
            (b"?", b"ALARM:1\r\n[MSG:Reset to continue]\r\n"),
            (b"\x18", BANNER + UNLOCK_MSG),
            (b"$X\n", b"[MSG:Caution: Unlocked]\r\nok\r\n"),
            (b"?", status("Idle", 3.0)),
            (b"?", status("Idle", 3.0)),
        ]
    )
    axis = ctl.axis("X", name="turntable", **TURNTABLE)
    with pytest.raises(StageAlarm) as exc:
        axis.position()
    assert exc.value.code is GrblAlarm.HARD_LIMIT
    with pytest.raises(StageAlarm, match="clear_alarm"):
        axis.is_moving()  # refused without writing: GRBL would not answer
    axis.stop()  # already stopped by the alarm: a no-op, not an error
    assert ctl.clear_alarm().state == "Idle"
    assert axis.position() == 3.0
    dev.verify()


# -- against the simulator, in-process on a virtual clock -----------------------------------
@pytest.fixture
def stage(vclock):
    name = f"grbl-sim-{next(_names)}"
    sim = GrblSimulator(
        name,
        vclock,
        axes={
            "X": GrblAxisSettings(max_rate=3600, accel=120, start=40.0),
            "Y": GrblAxisSettings(max_rate=1200, accel=40),
        },
        settings={22: 1},  # commissioned with home switches (the factory has homing off)
    )
    registry.register(name, sim)
    ctl = GrblController(f"sim://{name}", clock=vclock)
    ctl.connect()
    turntable = ctl.axis("X", name="turntable", **TURNTABLE)
    tilt = ctl.axis("Y", name="tilt", **TILT)
    turntable.home()
    yield sim, ctl, turntable, tilt
    ctl.close()
    registry.unregister(name)


def test_session_against_the_simulator(stage, vclock):
    sim, _, turntable, tilt = stage
    world = World(vclock)
    world.attach_axis("turntable", lambda: sim.axis_position("X") / TURNTABLE["units_per_degree"])
    world.attach_axis("tilt", lambda: sim.axis_position("Y") / TILT["units_per_degree"])
    assert sim.axis_position("X") == pytest.approx(0.0)  # homing found the switch
    t0 = vclock.monotonic()
    assert turntable.move_to(90.0) == pytest.approx(90.0)
    assert vclock.monotonic() - t0 == pytest.approx(90 / 60 + 60 / 120, abs=0.1)  # trapezoid + polling
    assert tilt.move_to(-15.0) == pytest.approx(-15.0)
    assert (world.pose().azimuth_deg, world.pose().tilt_deg) == (pytest.approx(90.0), pytest.approx(-15.0))
    turntable.rotate(30.0)
    vclock.advance(2.0)
    assert turntable.is_moving() and 140 < turntable.position() < 150
    moving, degrees = turntable.motion()  # one report gives both
    assert moving and degrees == pytest.approx(turntable.position(), abs=1e-6)
    turntable.stop()
    assert not turntable.is_moving() and sim.state == "Idle"
    assert turntable.motion() == (False, pytest.approx(turntable.position(), abs=1e-6))
    turntable.move_to(10.0, wait=False)
    assert turntable.is_moving()
    turntable.wait_until_idle(10.0)
    assert turntable.position() == pytest.approx(10.0)
    turntable.close()
    tilt.close()  # both axes may close the shared controller


def test_settle_time_is_waited_on_the_clock(stage, vclock):
    _, ctl, _, _ = stage
    z = ctl.axis("Z", name="focus", **{**TILT, "settle_s": 0.75})
    ctl.home()
    t0 = vclock.monotonic()
    z.move_to(0.0)  # no motion at all: only the settle time passes (and one poll)
    assert 0.75 <= vclock.monotonic() - t0 < 0.8


def test_stall_is_caught_by_read_back(stage):
    sim, _, turntable, _ = stage
    sim.faults.add("stall", fraction=0.5)
    with pytest.raises(MoveNotVerified) as exc:
        turntable.move_to(100.0)
    assert exc.value.target == 100.0 and exc.value.actual == pytest.approx(50.0)
    assert sim.state == "Idle"
    assert turntable.move_to(100.0) == pytest.approx(100.0)


def test_alarm_mid_move_then_recovery(stage):
    sim, ctl, turntable, _ = stage
    sim.faults.add("alarm")
    with pytest.raises(StageAlarm) as exc:
        turntable.move_to(60.0)
    assert exc.value.code is GrblAlarm.HARD_LIMIT and exc.value.device == "stage"
    with pytest.raises(StageAlarm):
        turntable.position()
    ctl.clear_alarm(home=True)
    assert turntable.move_to(60.0) == pytest.approx(60.0)


def test_homing_failure_is_a_stage_alarm(stage):
    sim, ctl, turntable, _ = stage
    turntable.move_to(30.0)
    sim.faults.add("alarm")
    with pytest.raises(StageAlarm) as exc:
        turntable.home()
    assert exc.value.code is GrblAlarm.HOMING_FAIL_APPROACH
    turntable.home()  # the controller reset itself; homing again works
    assert turntable.position() == 0.0 and ctl.restarts >= 1


@pytest.mark.parametrize("kind", ["drop_reply", "late_reply", "garble"])
def test_lost_or_mangled_query_replies_are_retried(stage, kind):
    sim, _, turntable, _ = stage
    turntable.move_to(20.0)
    sim.faults.add(kind, delay_s=1.5)
    assert turntable.position() == pytest.approx(20.0)
    assert sim.faults.log[-1][0] == kind
    assert turntable.move_to(25.0) == pytest.approx(25.0)  # and the stream is still in step


def test_retries_run_out(stage):
    sim, ctl, turntable, _ = stage
    sim.faults.add("drop_reply", count=3)
    with pytest.raises(DeviceTimeout) as exc:
        turntable.position()
    assert exc.value.attempt == ctl.retries + 1 == 3 and exc.value.command == "?"
    assert turntable.position() == pytest.approx(0.0)


@pytest.mark.parametrize(
    "kind, error", [("drop_reply", DeviceTimeout), ("late_reply", DeviceTimeout), ("garble", DeviceTimeout)]
)
def test_lost_move_replies_are_not_retried(stage, kind, error):
    sim, _, turntable, _ = stage
    turntable.position()
    sim.faults.add(kind, delay_s=1.5)
    with pytest.raises(error) as exc:
        turntable.move_to(45.0, wait=False)  # the first reply the fault hits is the move's ok
    assert exc.value.command == "G90 G53 G1 X45 F3600" and exc.value.attempt == 1
    assert sim.received.count(b"G90 G53 G1 X45 F3600\n") == 1  # a move is never re-sent
    assert turntable.move_to(50.0) == pytest.approx(50.0)  # the late/lost ok is settled first


def test_garbled_multi_line_reply_is_a_protocol_error_then_retried(stage):
    sim, ctl, _, _ = stage
    sim.faults.add("garble")
    assert ctl.read_settings()[110] == 3600.0  # the first $$ reply was mangled, the retry was not
    assert sim.received.count(b"$$\n") == 3  # connect + garbled + retry


def test_vanished_port_and_reconnect(stage):
    sim, ctl, turntable, _ = stage
    turntable.move_to(30.0)
    sim.faults.add("vanish", duration_s=1.0)
    with pytest.raises(DeviceGone) as exc:
        turntable.move_to(40.0)
    assert exc.value.device == "stage"
    report = ctl.reconnect(interval_s=0.3)
    assert report.reset and report.status.state == "Alarm"  # a USB-powered board lost power
    assert sim.axis_position("X") == pytest.approx(30.0)  # the axis itself did not move
    turntable.home()
    assert turntable.move_to(40.0) == pytest.approx(40.0)


# -- over a pseudo-terminal, in real time ---------------------------------------------------------
FAST = {
    "X": GrblAxisSettings(max_rate=60000, accel=20000),
    "Y": GrblAxisSettings(max_rate=60000, accel=20000),
}


@pytest.mark.timeout(20)
def test_driver_over_a_pty():
    sim = GrblSimulator("grbl-pty", SystemClock(), axes=FAST, settings={22: 1})
    with PtyServer(sim) as srv:
        ctl = GrblController(srv.path, clock=SYSTEM_CLOCK, timeout_s=0.5, poll_interval_s=0.01)
        try:
            ctl.connect()
            axis = ctl.axis("X", name="turntable", **{**TURNTABLE, "max_speed_dps": 500, "accel_dps2": 5000})
            axis.home()
            assert axis.move_to(12.5) == pytest.approx(12.5)
            axis.rotate(200.0)
            axis.stop()
            assert not axis.is_moving()
            sim.faults.add("drop_reply")
            assert axis.position() == pytest.approx(sim.axis_position("X"), abs=1e-3)  # recovered by a retry
        finally:
            ctl.close()


@pytest.mark.timeout(20)
def test_third_party_client_speaks_grbl_to_the_simulator():
    """Plain pyserial, the way a GRBL sender would, against the simulator on a pty."""
    sim = GrblSimulator("grbl-3p", SystemClock(), axes=FAST)  # factory: homing off
    with PtyServer(sim) as srv:
        port = serial.Serial(srv.path, 115200, timeout=1)
        try:
            port.write(b"\x18")
            assert port.readline() == b"\r\n"
            assert port.readline() == b"Grbl 1.1h ['$' for help]\r\n"
            port.write(b"$I\n")
            assert port.readline().startswith(b"[VER:1.1h")
            assert port.readline() == b"[OPT:V,15,128]\r\n"
            assert port.readline() == b"ok\r\n"
            port.write(b"G91 G0 X5\n")
            assert port.readline() == b"ok\r\n"
            for _ in range(200):
                port.write(b"?")
                report = port.readline()
                if report.startswith(b"<Idle"):
                    break
            assert report.startswith(b"<Idle|MPos:5.000,0.000,0.000|FS:0,0")
        finally:
            port.close()


def test_threads_share_the_line_one_transaction_at_a_time():
    """The engine polls status while the API reads it: replies must never cross."""
    import threading

    sim = GrblSimulator("locked", SystemClock())
    with PtyServer(sim) as srv:
        ctl = GrblController(srv.path, device="stage", timeout_s=2.0, retries=0)
        ctl.connect()
        errors: list[BaseException] = []

        def hammer(fn) -> None:
            try:
                for _ in range(40):
                    fn()
            except BaseException as exc:  # collected and asserted below
                errors.append(exc)

        threads = [
            threading.Thread(target=hammer, args=(ctl.status,)),
            threading.Thread(target=hammer, args=(lambda: ctl.command("G90", idempotent=True),)),
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=60)
        ctl.close()
    assert errors == []


def test_factory_controller_refuses_homing_with_a_typed_error(vclock):
    name = f"grbl-factory-{next(_names)}"
    sim = GrblSimulator(name, vclock)  # GRBL 1.1h defaults: $22=0
    registry.register(name, sim)
    ctl = GrblController(f"sim://{name}", clock=vclock)
    try:
        assert ctl.connect().state == "Idle"  # no boot lock without homing
        assert (ctl.settings[22], ctl.settings[110], ctl.settings[120]) == (0.0, 500.0, 10.0)
        with pytest.raises(CommandRejected) as err:
            ctl.home()
        assert err.value.code == GrblError.HOMING_DISABLED and "$H" in str(err.value)
        ctl.command("G10 L20 P1 X0")  # the operator's origin instead
        assert sim.coord_data[54] == [0.0, 0.0, 0.0]
    finally:
        ctl.close()
        registry.unregister(name)


def test_clear_alarm_after_a_soft_limit_copes_with_the_late_ok(vclock):
    """After ALARM:2 GRBL answers the offending line's ok only after the reset, before the
    banner: the driver must not take that ok for the answer to its next line."""
    name = f"grbl-softlimit-{next(_names)}"
    sim = GrblSimulator(name, vclock, axes={"X": GrblAxisSettings(max_rate=3600, accel=120, max_travel=100)},
                        settings={22: 1, 20: 1})
    registry.register(name, sim)
    ctl = GrblController(f"sim://{name}", clock=vclock)
    try:
        ctl.connect()
        ctl.home()
        with pytest.raises(StageAlarm) as err:
            ctl.command("G53 G0 X-150")
        assert err.value.code == GrblAlarm.SOFT_LIMIT and ctl.critical
        assert ctl.clear_alarm().state == "Idle"
        assert ctl.command("$I")  # answered by its own [VER:] lines and ok, nothing left over
        assert ctl.command("G53 G0 X-10") == [] and ctl.wait_until_idle(5).mpos[0] == pytest.approx(-10.0)
    finally:
        ctl.close()
        registry.unregister(name)


class _StalledBetweenPolls(GrblSimulator):
    """A controller seen from a loaded host: a second passes after every status report."""

    def _realtime(self, b: int, now: float) -> None:
        super()._realtime(b, now)
        if b == 0x3F:
            self.clock.advance(1.0)


def test_axis_view_is_one_status_report(vclock):
    """The console's axis view: polled as position() then is_moving(), a move that ends between
    the two reads as standing mid-way (CI saw 2.9° for a 15° jog); one report cannot tear."""
    name = f"grbl-stalled-{next(_names)}"
    sim = _StalledBetweenPolls(name, vclock, axes={"X": GrblAxisSettings(max_rate=3600, accel=120)})
    registry.register(name, sim)
    ctl = GrblController(f"sim://{name}", clock=vclock)
    try:
        ctl.connect()
        axis = ctl.axis("X", name="turntable", **TURNTABLE)
        rig = SimpleNamespace(axis=lambda role: axis, config=SimpleNamespace(
            axes={"turntable": SimpleNamespace(min_deg=-370, max_deg=370, max_speed_dps=60)}))
        axis.move_to(15.0, wait=False)
        torn = (axis.position(), axis.is_moving())
        assert torn[0] < 15.0 - 1 and not torn[1]  # the tear this test is about
        axis.move_to(0.0)
        axis.move_to(15.0, wait=False)
        view = ManualControl(rig).axis_view("turntable")
        assert view.moving and view.position_deg < 15.0  # mid-move, and said so
    finally:
        ctl.close()
        registry.unregister(name)

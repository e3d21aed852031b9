"""The Zaber driver: byte-exact sequences (ids + checksums), the simulator in-process and over
a pty, and every injected fault ending in its typed error or a recovery."""

import itertools

import pytest
from m2s2hil.drivers.clock import SYSTEM_CLOCK, SystemClock
from m2s2hil.drivers.errors import (
    CommandRejected,
    DeviceGone,
    DeviceTimeout,
    MoveNotVerified,
    ProtocolError,
    SoftLimitError,
    StageAlarm,
)
from m2s2hil.drivers.interfaces import RotaryAxis
from m2s2hil.drivers.zaber import ZaberDevice, open_zaber_axes
from m2s2hil.protocols.zaber import RejectReason, WarningFlag
from m2s2hil.simulators import registry
from m2s2hil.simulators.pty import PtyServer
from m2s2hil.simulators.scripted import ScriptedDevice
from m2s2hil.simulators.world import World
from m2s2hil.simulators.zaber import ZaberAxisSettings, ZaberSimulator, zaber_sim_for

from m2s2hil.config import AxisConfig, DeviceConfig

_names = itertools.count()


def _framed(lead: bytes, body: str, end: bytes) -> bytes:
    raw = body.encode()
    return lead + raw + b":%02X" % ((-sum(raw)) % 256) + end


def cmd(body: str) -> bytes:
    return _framed(b"/", body, b"\n")


def rep(body: str) -> bytes:
    return _framed(b"@", body, b"\r\n")


CONNECT = [
    (cmd("1 0 00 get deviceid"), rep("01 0 00 OK IDLE WR 50000")),
    (cmd("1 0 01 get system.serial"), rep("01 0 01 OK IDLE WR 12345")),
    (cmd("1 0 02 get version"), rep("01 0 02 OK IDLE WR 7.38")),
    (cmd("1 0 03 get system.axiscount"), rep("01 0 03 OK IDLE WR 1")),
    (cmd("1 0 04 get comm.word.size.max"), rep("01 0 04 RJ IDLE WR BADCOMMAND")),  # older firmware
]
# 10 microsteps/degree: 100 °/s → maxspeed 1638, 200 °/s² → accel 1, ±360° → ±3600
AXIS = dict(
    units_per_degree=10.0, min_deg=-360, max_deg=360, max_speed_dps=100, accel_dps2=200, tolerance_deg=0.2
)
CONFIGURE = [
    (cmd("1 1 05 set maxspeed 1638"), rep("01 1 05 OK IDLE WR 0")),
    (cmd("1 1 06 set accel 1"), rep("01 1 06 OK IDLE WR 0")),
    (cmd("1 1 07 set limit.min -3600"), rep("01 1 07 OK IDLE WR 0")),
    (cmd("1 1 08 set limit.max 3600"), rep("01 1 08 OK IDLE WR 0")),
]


@pytest.fixture
def scripted(vclock):
    made = []

    def make(script):
        name = f"zaber-script-{next(_names)}"
        dev = ScriptedDevice(name, vclock, CONNECT + script)
        registry.register(name, dev)
        zd = ZaberDevice(f"sim://{name}", device="rot", clock=vclock)
        zd.connect()
        made.append((name, zd))
        return dev, zd

    yield make
    for name, zd in made:
        zd.close()
        registry.unregister(name)


def test_documented_example_is_what_the_helper_frames():
    assert cmd("1 1 00 get pos") == b"/1 1 00 get pos:2C\n"


def test_session_is_byte_exact(scripted):
    dev, zd = scripted(
        [
            *CONFIGURE,
            (cmd("1 1 09 home"), rep("01 1 09 OK BUSY WR 0")),
            (cmd("1 1 10"), rep("01 1 10 OK BUSY WR 0")),
            (cmd("1 1 11"), rep("01 1 11 OK IDLE -- 0")),
            (cmd("1 1 12 get pos"), rep("01 1 12 OK IDLE -- 0")),
            (cmd("1 1 13 move abs 900"), rep("01 1 13 OK BUSY -- 0")),
            # The wait polls ``get pos``: its reply carries BUSY/IDLE and the position together.
            (cmd("1 1 14 get pos"), rep("01 1 14 OK BUSY -- 450")),
            (cmd("1 1 15 get pos"), rep("01 1 15 OK IDLE -- 900")),
            (cmd("1 1 16 get pos"), rep("01 1 16 OK IDLE -- 900")),  # read-back
            (cmd("1 1 17 move vel -819"), rep("01 1 17 OK BUSY -- 0")),
            (cmd("1 1 18 stop"), rep("01 1 18 OK BUSY NI 0")),
            (cmd("1 1 19 get pos"), rep("01 1 19 OK IDLE NI -300")),
        ]
    )
    assert zd.info == {
        "deviceid": "50000",
        "system.serial": "12345",
        "version": "7.38",
        "system.axiscount": "1",
    }
    axis = zd.axis(1, name="turntable", **AXIS)
    assert isinstance(axis, RotaryAxis)
    axis.home()
    assert axis.move_to(90.0) == 90.0
    axis.rotate(50.0, direction=-1)
    axis.stop()
    dev.verify()


def test_rejections_faults_checksums_and_stale_replies(scripted):
    dev, zd = scripted(
        [
            (cmd("1 1 05 get pos"), rep("01 1 03 OK IDLE -- 77") + rep("01 1 05 OK IDLE -- 123")),
            (cmd("1 1 06 move abs 99999999"), rep("01 1 06 RJ IDLE -- BADDATA")),
            (cmd("1 1 07 get pos"), rep("01 1 07 OK IDLE FS 600")),
            (cmd("1 0 08 warnings clear"), rep("01 0 08 OK IDLE FS 01 FS")),
            (cmd("1 1 09 get pos"), b"@01 1 09 OK IDLE -- 600:00\r\n"),
            (cmd("1 1 10 get pos"), rep("01 1 10 OK IDLE -- 600")),
        ]
    )
    assert zd.request(1, "get pos").data == "123"  # the reply with the stale id 03 was skipped
    with pytest.raises(CommandRejected) as exc:
        zd.request(1, "move abs 99999999")
    assert (
        exc.value.code is RejectReason.BADDATA
        and exc.value.command == cmd("1 1 06 move abs 99999999").decode().strip()
    )
    with pytest.raises(StageAlarm) as exc:
        zd.get("pos", 1)
    assert exc.value.code is WarningFlag.FS and exc.value.device == "rot"
    assert zd.clear_faults() == ["FS"]
    assert zd.get("pos", 1) == "600"  # the bad checksum was retried
    dev.verify()


def test_soft_limits_are_enforced_before_anything_is_sent(scripted):
    dev, zd = scripted(list(CONFIGURE))
    axis = zd.axis(1, name="tilt", **AXIS)
    sent = bytes(dev.received)
    for call in (lambda: axis.move_to(361), lambda: axis.move_to(-400), lambda: axis.rotate(150)):
        with pytest.raises(SoftLimitError, match="tilt"):
            call()
    assert dev.received == sent
    dev.verify()


# -- against the simulator on a virtual clock ---------------------------------------------------
UPD = 4266.6667  # microsteps per degree of a 0.000234375° microstep
ROT = dict(
    units_per_degree=UPD, min_deg=-370, max_deg=370, max_speed_dps=60, accel_dps2=120, tolerance_deg=0.01
)


@pytest.fixture
def rotary(vclock):
    name = f"zaber-sim-{next(_names)}"
    sim = ZaberSimulator(name, vclock, axes=[ZaberAxisSettings(start=20000), ZaberAxisSettings()])
    registry.register(name, sim)
    zd = ZaberDevice(f"sim://{name}", clock=vclock)
    zd.connect()
    axis = zd.axis(1, name="turntable", **ROT)
    axis.home()
    yield sim, zd, axis
    zd.close()
    registry.unregister(name)


def test_session_against_the_simulator(rotary, vclock):
    sim, zd, axis = rotary
    assert zd.info["deviceid"] == "50000" and zd.info["system.axiscount"] == "2"
    world = World(vclock)
    world.attach_axis("turntable", lambda: sim.axis_position(1) / UPD)
    t0 = vclock.monotonic()
    assert axis.move_to(90.0) == pytest.approx(90.0, abs=1e-3)
    assert vclock.monotonic() - t0 == pytest.approx(90 / 60 + 60 / 120, abs=0.1)
    assert world.pose().azimuth_deg == pytest.approx(90.0, abs=1e-3)
    axis.rotate(30.0)
    vclock.advance(2.0)
    assert axis.is_moving() and 140 < axis.position() < 150
    moving, degrees = axis.motion()  # one reply gives both
    assert moving and degrees == pytest.approx(axis.position(), abs=1e-6)
    axis.stop()
    assert not axis.is_moving()
    assert axis.motion() == (False, pytest.approx(axis.position(), abs=1e-6))
    axis.rotate(60.0, direction=-1)
    vclock.advance(60)
    assert axis.position() == pytest.approx(-370.0, abs=1e-3)  # the device stops at the soft limit
    tilt = zd.axis(2, name="tilt", **{**ROT, "min_deg": -30, "max_deg": 30})
    tilt.home()
    assert tilt.move_to(-15.0) == pytest.approx(-15.0, abs=1e-3)
    assert zd.get("pos") == f"{round(-370 * UPD)} {round(-15 * UPD)}"
    axis.close()
    tilt.close()


def test_stall_is_a_stage_alarm_until_cleared(rotary):
    sim, zd, axis = rotary
    sim.faults.add("stall")
    with pytest.raises(StageAlarm) as exc:
        axis.move_to(100.0)
    assert exc.value.code is WarningFlag.FS
    assert zd.clear_faults(1) == ["FS"]
    assert axis.position() == pytest.approx(50.0, abs=1e-3)
    assert axis.move_to(100.0) == pytest.approx(100.0, abs=1e-3)


def test_alarm_fault_flag(rotary):
    sim, zd, axis = rotary
    sim.faults.add("alarm", flag="FQ")
    with pytest.raises(StageAlarm) as exc:
        axis.move_to(40.0)
    assert exc.value.code is WarningFlag.FQ
    axis.stop()  # stopping is always allowed
    zd.clear_faults()
    assert axis.move_to(40.0) == pytest.approx(40.0, abs=1e-3)


def test_tolerance_violation_is_move_not_verified(rotary):
    _, _, axis = rotary
    axis.tolerance_deg = 1e-6  # finer than one microstep: the read-back cannot match
    with pytest.raises(MoveNotVerified) as exc:
        axis.move_to(10.00001)
    assert exc.value.target == 10.00001 and exc.value.actual == pytest.approx(10.0, abs=1e-4)


@pytest.mark.parametrize("kind", ["drop_reply", "late_reply", "garble"])
def test_query_faults_are_retried(rotary, kind):
    sim, _, axis = rotary
    axis.move_to(20.0)
    sim.faults.add(kind, delay_s=1.5)
    assert axis.position() == pytest.approx(20.0, abs=1e-3)
    assert sim.faults.log[-1][0] == kind
    assert axis.move_to(25.0) == pytest.approx(25.0, abs=1e-3)


@pytest.mark.parametrize("kind, error", [("drop_reply", DeviceTimeout), ("late_reply", DeviceTimeout)])
def test_move_faults_are_not_retried(rotary, kind, error):
    sim, _, axis = rotary
    sim.faults.add(kind, delay_s=1.5)
    with pytest.raises(error) as exc:
        axis.move_to(45.0, wait=False)
    assert exc.value.attempt == 1 and b"move abs" in sim.received
    assert sim.received.count(b"move abs 192000") == 1
    assert axis.move_to(50.0) == pytest.approx(50.0, abs=1e-3)  # a late reply's stale id is skipped


def test_garbled_move_reply_is_a_protocol_error(rotary):
    sim, _, axis = rotary
    sim.faults.add("garble")
    with pytest.raises(ProtocolError):
        axis.move_to(45.0, wait=False)
    axis.wait_until_idle(5.0)
    assert axis.position() == pytest.approx(45.0, abs=1e-3)  # the device did move


def test_retries_run_out(rotary):
    sim, zd, axis = rotary
    sim.faults.add("drop_reply", count=3)
    with pytest.raises(DeviceTimeout) as exc:
        axis.position()
    assert exc.value.attempt == zd.retries + 1


def test_vanished_port_and_reconnect(rotary):
    sim, zd, axis = rotary
    axis.move_to(30.0)
    sim.faults.add("vanish", duration_s=1.0)
    with pytest.raises(DeviceGone):
        axis.position()
    reply = zd.reconnect(interval_s=0.3)
    assert reply.status == "IDLE" and reply.warning == "WR"  # axis 2 was never homed
    assert axis.position() == pytest.approx(30.0, abs=1e-3)  # own power supply: position kept


@pytest.mark.timeout(20)
def test_driver_over_a_pty():
    fast = ZaberAxisSettings(maxspeed=10**7, accel=10**4)
    sim = ZaberSimulator("zaber-pty", SystemClock(), axes=[fast])
    with PtyServer(sim) as srv:
        zd = ZaberDevice(srv.path, clock=SYSTEM_CLOCK, timeout_s=0.5, poll_interval_s=0.01)
        try:
            zd.connect()
            axis = zd.axis(1, name="turntable", **{**ROT, "max_speed_dps": 1000, "accel_dps2": 20000})
            axis.home()
            assert axis.move_to(12.5) == pytest.approx(12.5, abs=1e-3)
            sim.faults.add("drop_reply")
            assert axis.position() == pytest.approx(12.5, abs=1e-3)
        finally:
            zd.close()


def test_rig_configuration_helpers(vclock):
    name = f"zaber-rig-{next(_names)}"
    dev = DeviceConfig(protocol="zaber", port=f"sim://{name}", unit=2, timeout_s=0.5)
    axes = {
        "turntable": AxisConfig(device="stage", axis="1", units_per_degree=UPD, min_deg=-370, max_deg=370),
        "tilt": AxisConfig(device="stage", axis="2", units_per_degree=UPD, min_deg=-30, max_deg=30),
    }
    world = World(vclock)
    sim = zaber_sim_for(name, dev, axes, vclock, world, None)
    registry.register(name, sim)
    try:
        zd, made = open_zaber_axes(name, dev, axes, vclock)
        assert zd.address == 2 and set(made) == {"turntable", "tilt"}
        zd.home()
        made["turntable"].move_to(120.0)
        made["tilt"].move_to(-20.0)
        pose = world.pose()
        assert (pose.azimuth_deg, pose.tilt_deg) == (
            pytest.approx(120.0, abs=1e-3),
            pytest.approx(-20.0, abs=1e-3),
        )
        with pytest.raises(SoftLimitError):
            made["tilt"].move_to(31.0)
        zd.close()
    finally:
        registry.unregister(name)

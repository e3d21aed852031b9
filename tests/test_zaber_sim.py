"""The Zaber simulator answers as a Zaber ASCII device does, on a virtual clock."""

import pytest
from m2s2hil.protocols.zaber import Command, Reply, ZaberReceiver, encode_command
from m2s2hil.simulators.zaber import ZaberAxisSettings, ZaberSimulator


class Host:
    def __init__(self, sim, clock):
        self.sim, self.clock, self.rx = sim, clock, ZaberReceiver()

    def raw(self, data: bytes, wait: float = 0.0) -> bytes:
        self.sim.receive(data)
        self.clock.advance(wait)
        return self.sim.take()

    def ask(self, axis: int, text: str, *, mid: int | None = None, address: int = 3) -> list[Reply]:
        return self.rx.feed(
            self.raw(encode_command(Command(address, axis, mid, text), with_checksum=mid is not None))
        )

    def one(self, axis: int, text: str) -> Reply:
        (reply,) = self.ask(axis, text)
        return reply


@pytest.fixture
def dev(vclock):
    # 1000 microsteps/s (data 1638.4 → 1638), 2000 microsteps/s^2 (data 0.32768 → 1 = 6103.5/s^2)
    axes = [
        ZaberAxisSettings(maxspeed=1638, accel=1, start=500),
        ZaberAxisSettings(limit_min=0, limit_max=1000),
    ]
    sim = ZaberSimulator("z", vclock, address=3, axes=axes)
    return sim, Host(sim, vclock)


def test_replies_in_kind(dev):
    sim, host = dev
    assert host.raw(b"/3 1 get pos\n") == b"@03 1 OK IDLE WR 0\r\n"
    assert (
        host.raw(b"/3 1 42 get pos:%02X\n" % ((-sum(b"3 1 42 get pos")) % 256))
        == b"@03 1 42 OK IDLE WR 0:B5\r\n"
    )
    assert host.raw(b"/3 1 42 get pos:00\n") == b""  # a bad checksum: dropped
    assert sim.ignored == 1
    assert host.raw(b"/4 1 get pos\n") == b""  # another device's address
    assert host.raw(b"/\r\n") == b"@03 0 OK IDLE WR 0\r\n"  # everybody, status
    assert host.raw(b"/0 0 get system.axiscount\n") == b"@03 0 OK IDLE WR 2\r\n"


@pytest.mark.parametrize(
    "axis, text, reason",
    [(3, "get pos", "BADAXIS"), (1, "jump", "BADCOMMAND"), (1, "move abs x", "BADDATA"),
     (1, "move abs 2000000000", "BADDATA"), (2, "move abs 1001", "BADDATA"), (1, "get deviceid", "BADAXIS"),
     (1, "set resolution 8", "BADCOMMAND"), (1, "move vel 99999", "BADDATA"),
     (1, "move sideways 3", "BADCOMMAND"), (1, "set maxspeed 0", "BADDATA")],
)  # fmt: skip
def test_rejections(dev, axis, text, reason):
    _, host = dev
    reply = host.one(axis, text)
    assert (reply.flag, reply.data) == ("RJ", reason)


def test_homing_motion_and_flags(dev, vclock):
    sim, host = dev
    assert host.one(1, "warnings").data == "01 WR"
    assert host.one(1, "home").status == "BUSY"
    vclock.advance(0.1)
    assert sim.axis_position(1) < 500  # driving to the home sensor at physical 0
    vclock.advance(5)
    reply = host.one(1, "")
    assert (reply.status, reply.warning, sim.axis_position(1)) == ("IDLE", "--", 0.0)
    assert host.one(1, "move abs 600").busy
    vclock.advance(0.3)  # ramp 0.164 s to 1000/s, then cruise
    assert host.one(1, "get pos").data == str(round(sim.axis_position(1)))
    vclock.advance(1)
    assert host.one(1, "get pos").data == "600"
    assert host.one(0, "get pos").data == "600 0"  # the device answers for all axes
    host.one(1, "move rel -100")
    vclock.advance(1)
    assert host.one(1, "get pos").data == "500"


def test_stop_sets_ni_and_velocity_moves_stop_at_the_limit(dev, vclock):
    _, host = dev
    host.one(2, "home")
    vclock.advance(1)
    host.one(2, "move vel 1638")
    vclock.advance(0.3)
    reply = host.one(2, "stop")
    assert reply.warning == "NI" and reply.busy
    vclock.advance(1)
    assert not host.one(2, "").busy
    host.one(2, "move vel 1638")
    vclock.advance(5)
    assert host.one(2, "get pos").data == "1000"  # limit.max
    assert host.one(2, "warnings clear").data == "00"


def test_set_pos_renumbers_the_same_place(dev):
    sim, host = dev
    assert host.one(1, "set pos 1234").flag == "OK"
    assert host.one(1, "get pos").data == "1234" and sim.axis_position(1) == 500


def test_stall_and_alarm_faults_set_fault_flags(dev, vclock):
    sim, host = dev
    host.one(1, "home")
    vclock.advance(2)
    sim.faults.add("stall", fraction=0.5)
    host.one(1, "move abs 800")
    vclock.advance(3)
    reply = host.one(1, "get pos")
    assert (reply.status, reply.warning, reply.data) == ("IDLE", "FS", "400")
    assert host.one(1, "warnings clear").data == "01 FS"
    sim.faults.add("alarm", flag="FQ")
    host.one(1, "move abs 0")
    vclock.advance(3)
    reply = host.one(1, "get pos")
    assert reply.warning == "FQ" and reply.data == "200"


def test_reply_ids_stay_in_order_when_one_is_late(dev, vclock):
    sim, host = dev
    sim.faults.add("late_reply", delay_s=1.0)
    assert host.ask(1, "get pos", mid=1) == []
    assert host.ask(1, "get pos", mid=2) == []
    replies = host.rx.feed(host.raw(b"", wait=1.0))
    assert [r.message_id for r in replies] == [1, 2]


def test_identity_settings_that_zaber_motion_reads(dev):
    from m2s2hil.simulators.zaber import DEVICE_ID, FIRMWARE_BUILD, FIRMWARE_VERSION

    sim, host = dev
    got = {name: host.one(0, f"get {name}") for name in (
        "deviceid", "device.id", "system.serial", "version", "version.build", "device.hw.modified",
        "comm.packet.size.max", "comm.command.packets.max", "comm.word.size.max", "get.settings.max")}
    assert not any(r.rejected for r in got.values())
    assert got["deviceid"].data == got["device.id"].data == str(DEVICE_ID)
    assert (got["version"].data, got["version.build"].data) == (FIRMWARE_VERSION, str(FIRMWARE_BUILD))
    # Every setting name the device knows fits in one word of the advertised size.
    longest = max(len(n) for n in (*sim.device_settings, "limit.min", "encoder.pos", "resolution"))
    assert int(got["comm.word.size.max"].data) == longest == len("comm.command.packets.max")
    assert host.one(1, "get peripheralid").data == "BADCOMMAND"  # integrated stage: no peripheral
    other = ZaberSimulator("z2", sim.clock, device_id=12345, version="6.32", build=1234)
    assert (other.device_settings["deviceid"], other.device_settings["version.build"]) == ("12345", "1234")

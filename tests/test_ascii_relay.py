"""The ASCII relay driver: byte-exact scripts, against its simulator (sim:// and pty), faults."""

from __future__ import annotations

import pytest
import serial
from m2s2hil.drivers.ascii_relay import AsciiRelayBoard
from m2s2hil.drivers.errors import DeviceGone, DeviceTimeout, ProtocolError, RelayNotSwitched
from m2s2hil.drivers.interfaces import LightBank
from m2s2hil.simulators import registry
from m2s2hil.simulators.ascii_relay import AsciiRelaySim
from m2s2hil.simulators.clock import RealClock
from m2s2hil.simulators.pty import PtyServer
from m2s2hil.simulators.scripted import ScriptedDevice
from m2s2hil.simulators.world import World

pytestmark = pytest.mark.timeout(30)


def scripted(name, clock, script, **kw) -> tuple[ScriptedDevice, AsciiRelayBoard]:
    dev = ScriptedDevice(name, clock, script)
    registry.register(name, dev)
    return dev, AsciiRelayBoard(f"sim://{name}", clock=clock, **kw)


def board_says(line: bytes, *answers: bytes) -> bytes:
    """What a Numato board prints for ``line``: echo, LF CR, answers, prompt."""
    return line + b"\n\r" + b"".join(a + b"\n\r" for a in answers) + b">"


@pytest.fixture
def rig(vclock):
    world = World(vclock)
    sim = AsciiRelaySim("ascii-relays", vclock, on_change=world.set_lamp)
    registry.register("ascii-relays", sim)
    board = AsciiRelayBoard("sim://ascii-relays", clock=vclock)
    yield board, sim, world
    board.close()
    registry.unregister("ascii-relays")


# -- byte-exact ----------------------------------------------------------------------------------
def test_scripted_connect_set_switch_version(vclock):
    dev, board = scripted(
        "as-s1",
        vclock,
        [
            (b"\r", b"\n\r>"),
            (b"relay readall\r", board_says(b"relay readall", b"00")),
            (b"relay writeall 25\r", board_says(b"relay writeall 25")),
            (b"relay readall\r", board_says(b"relay readall", b"25")),
            (b"relay off 5\r", board_says(b"relay off 5")),
            (b"relay read 5\r", board_says(b"relay read 5", b"off")),
            (b"ver\r", board_says(b"ver", b"00000008")),
        ],
    )
    board.connect()
    board.set([0, 2, 5])
    board.switch(5, False)
    assert board.version() == "00000008"
    dev.verify()


def test_scripted_sixteen_channels_use_letters_and_four_digits(vclock):
    dev, board = scripted(
        "as-s2",
        vclock,
        [
            (b"relay on B\r", board_says(b"relay on B")),
            (b"relay read B\r", board_says(b"relay read B", b"on")),
            (b"relay writeall 8001\r", board_says(b"relay writeall 8001")),
            (b"relay readall\r", board_says(b"relay readall", b"8001")),
        ],
        channels=16,
    )
    board.switch(11, True)
    board.set([0, 15])
    dev.verify()


def test_scripted_wrong_echo_is_protocol_error(vclock):
    dev, board = scripted(
        "as-s3", vclock, [(b"relay readall\r", board_says(b"relay readal", b"00"))], retries=0
    )
    with pytest.raises(ProtocolError, match="echo") as err:
        board.state()
    assert err.value.command == "relay readall"
    dev.verify()


def test_scripted_silent_board_is_protocol_error(vclock):
    # An older firmware without readall ignores the line: echo and prompt, no answer.
    dev, board = scripted("as-s4", vclock, [(b"relay readall\r", board_says(b"relay readall"))], retries=0)
    with pytest.raises(ProtocolError, match="no answer"):
        board.state()
    dev.verify()


def test_scripted_bad_mask_is_protocol_error(vclock):
    dev, board = scripted("as-s5", vclock, [(b"relay readall\r", board_says(b"relay readall", b"zz"))])
    with pytest.raises(ProtocolError, match="hex"):
        board.state()
    dev.verify()


def test_scripted_missing_prompt_is_timeout(vclock):
    dev, board = scripted("as-s6", vclock, [(b"ver\r", b"ver\n\r00000008\n\r")], retries=0, timeout_s=0.25)
    with pytest.raises(DeviceTimeout, match="no prompt") as err:
        board.version()
    assert vclock.monotonic() == pytest.approx(0.25)
    assert err.value.attempt == 1
    dev.verify()


# -- against the simulator, virtual time ------------------------------------------------------------
def test_driver_is_a_lightbank(rig):
    assert isinstance(rig[0], LightBank)


def test_set_state_switch_and_world_mirror(rig, vclock):
    board, sim, world = rig
    board.connect()
    board.set([0, 1, 2, 3, 4])
    assert board.state() == {0, 1, 2, 3, 4} == sim.on_channels == world.lamps_on()
    board.set([5])
    board.switch(6, True)
    assert world.lamps_on() == {5, 6}
    board.all_off()
    assert world.lamps_on() == frozenset() and sim.relays == (False,) * 8
    assert board.version() == "00000008"
    assert vclock.monotonic() < 0.5


def test_bad_channels_are_refused_before_sending(rig):
    board, sim, _ = rig
    for bad in ([8], [-1], [False], [1.0]):
        with pytest.raises(ValueError, match="channel"):
            board.set(bad)
    assert sim.received == b""


def test_sim_echoes_and_ignores_unknown_lines(vclock):
    sim = AsciiRelaySim("as-raw", vclock)
    registry.register("as-raw", sim)
    port = serial.serial_for_url("sim://as-raw", timeout=0.1)
    port.write(b"relay fly 3\r")
    vclock.advance(0.01)
    assert port.read(100) == b"relay fly 3\n\r>"
    port.write(b"relay on 2 please\r")  # trailing words: still executed
    vclock.advance(0.01)
    assert port.read(100) == b"relay on 2 please\n\r>"
    port.write(b"rel")
    port.write(b"ay read 2\r")
    vclock.advance(0.01)
    assert port.read(100) == b"relay read 2\n\ron\n\r>"
    assert sim.ignored_lines == ["relay fly 3"] and sim.on_channels == {2}
    port.close()


# -- faults -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["drop_reply", "garble", "late_reply"])
def test_one_off_faults_are_recovered(rig, kind):
    board, sim, world = rig
    sim.faults.add(kind)
    board.set([1, 3])
    assert board.state() == {1, 3} == world.lamps_on()
    assert [k for k, _ in sim.faults.log] == [kind]


@pytest.mark.parametrize(
    ("kind", "error"),
    [("drop_reply", DeviceTimeout), ("garble", ProtocolError), ("late_reply", DeviceTimeout)],
)
def test_persistent_faults_end_in_typed_errors(rig, kind, error):
    board, sim, _ = rig
    sim.faults.add(kind, count=-1)
    with pytest.raises(error) as err:
        board.set([2])
    assert err.value.attempt == 3 and err.value.device == "relays"
    assert err.value.command == "relay writeall 04"


def test_relay_stuck_is_relay_not_switched(rig):
    board, sim, world = rig
    sim.faults.add("relay_stuck", channel=5)
    with pytest.raises(RelayNotSwitched, match=r"stuck: \[5\]"):
        board.set([5, 6])
    assert sim.on_channels == {6} == world.lamps_on()
    sim.faults.add("relay_stuck", channel=6)
    with pytest.raises(RelayNotSwitched, match="relay 6 reads on"):
        board.switch(6, False)


def test_vanish_is_recovered_by_reconnecting(rig, vclock):
    board, sim, world = rig
    board.connect()
    sim.faults.add("vanish", duration_s=1.0)
    board.set([7])
    assert world.lamps_on() == {7}
    assert vclock.monotonic() >= 1.0


def test_vanish_for_good_is_device_gone(rig):
    board, sim, _ = rig
    board.connect()
    sim.faults.add("vanish", duration_s=1e6)
    with pytest.raises(DeviceGone) as err:
        board.set([1])
    assert err.value.attempt == 3


def test_missing_port_is_device_gone_at_once(vclock):
    with pytest.raises(DeviceGone, match="no-such-ascii"):
        AsciiRelayBoard("sim://no-such-ascii", clock=vclock).connect()
    assert vclock.monotonic() == 0.0


# -- over a pseudo-terminal, in real time --------------------------------------------------------------
def test_driver_against_simulator_on_a_pty():
    clock = RealClock()
    world = World(clock)
    sim = AsciiRelaySim("as-pty", clock, on_change=world.set_lamp)
    with PtyServer(sim) as srv:
        board = AsciiRelayBoard(srv.path, clock=clock, timeout_s=0.5)
        board.connect()
        board.set([0, 1, 2])
        board.switch(5, True)
        assert board.state() == {0, 1, 2, 5} == world.lamps_on()
        sim.faults.add("drop_reply")
        board.set([4])  # retried after one timeout
        assert world.lamps_on() == {4}
        board.close()

"""The ASCII relay driver: byte-exact scripts, against its simulator (sim:// and pty), faults."""

from __future__ import annotations

import pytest
import serial
from m2s2hil.drivers.ascii_relay import AsciiRelayBoard
from m2s2hil.drivers.clock import SystemClock
from m2s2hil.drivers.errors import DeviceGone, DeviceTimeout, ProtocolError
from m2s2hil.drivers.interfaces import LightBank
from m2s2hil.simulators import registry
from m2s2hil.simulators.ascii_relay import AsciiRelaySim
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
# The injected faults of tests/test_relay_faults.py run against this board and the Modbus one.


def test_missing_port_is_device_gone_at_once(vclock):
    with pytest.raises(DeviceGone, match="no-such-ascii"):
        AsciiRelayBoard("sim://no-such-ascii", clock=vclock).connect()
    assert vclock.monotonic() == 0.0


# -- over a pseudo-terminal, in real time --------------------------------------------------------------
def test_driver_against_simulator_on_a_pty():
    clock = SystemClock()
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

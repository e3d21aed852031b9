"""The Modbus relay driver: byte-exact scripts, against its simulator (sim:// and pty), faults."""

from __future__ import annotations

import threading

import pytest
from m2s2hil.drivers.clock import SystemClock
from m2s2hil.drivers.errors import (
    CommandRejected,
    DeviceGone,
    DeviceTimeout,
    ProtocolError,
)
from m2s2hil.drivers.interfaces import LightBank
from m2s2hil.drivers.modbus_relay import ModbusRelayBoard
from m2s2hil.drivers.serial_link import SerialLink
from m2s2hil.protocols.modbus_relay import (
    CoilsWritten,
    ExceptionReply,
    ModbusRelayCodec,
    WriteCoils,
)
from m2s2hil.simulators import registry
from m2s2hil.simulators.modbus_relay import ModbusRelaySim
from m2s2hil.simulators.pty import PtyServer
from m2s2hil.simulators.scripted import ScriptedDevice
from m2s2hil.simulators.world import World
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ExceptionResponse
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadCoilsResponse,
    WriteMultipleCoilsRequest,
    WriteMultipleCoilsResponse,
)

pytestmark = pytest.mark.timeout(30)

# Expected frames built with pymodbus' own framer and PDU classes, not with our codec.
_framer = FramerRTU(DecodePDU(is_server=False))


def frame(pdu) -> bytes:
    return _framer.buildFrame(pdu)


def read8(unit: int = 1) -> bytes:
    return frame(ReadCoilsRequest(address=0, count=8, dev_id=unit))


def coils(mask: int, unit: int = 1) -> bytes:
    return frame(ReadCoilsResponse(bits=[bool(mask >> i & 1) for i in range(8)], dev_id=unit))


def write8(mask: int, unit: int = 1) -> bytes:
    return frame(
        WriteMultipleCoilsRequest(address=0, bits=[bool(mask >> i & 1) for i in range(8)], dev_id=unit)
    )


def written8(unit: int = 1) -> bytes:
    return frame(WriteMultipleCoilsResponse(address=0, count=8, dev_id=unit))


def scripted(name, clock, script, **kw) -> tuple[ScriptedDevice, ModbusRelayBoard]:
    dev = ScriptedDevice(name, clock, script)
    registry.register(name, dev)
    return dev, ModbusRelayBoard(f"sim://{name}", clock=clock, **kw)


@pytest.fixture
def rig(vclock):
    """Driver + simulator on sim://, with the simulator mirrored into a World."""
    world = World(vclock)
    sim = ModbusRelaySim("mb-relays", vclock, on_change=world.set_lamp)
    registry.register("mb-relays", sim)
    board = ModbusRelayBoard("sim://mb-relays", clock=vclock)
    yield board, sim, world
    board.close()
    registry.unregister("mb-relays")


# -- byte-exact ----------------------------------------------------------------------------------
def test_scripted_connect_set_state(vclock):
    dev, board = scripted(
        "mb-s1",
        vclock,
        [
            (read8(), coils(0x00)),
            (write8(0b0010_0101), written8()),
            (read8(), coils(0b0010_0101)),
        ],
    )
    board.connect()
    board.set([0, 2, 5])
    dev.verify()
    # The board answered at once; only the RTU silence before requests 2 and 3 took time.
    assert vclock.monotonic() == pytest.approx(2 * 3.5 * 11 / 9600)


def test_scripted_switch_uses_fc05_spec_frame(vclock):
    dev, board = scripted(
        "mb-s2",
        vclock,
        [
            (bytes.fromhex("01 05 00 00 FF 00 8C 3A"), bytes.fromhex("01 05 00 00 FF 00 8C 3A")),
            (read8(), coils(0x01)),
        ],
    )
    board.switch(0, True)
    dev.verify()


def test_scripted_other_unit_frames(vclock):
    dev, board = scripted("mb-s3", vclock, [(read8(unit=7), coils(0x80, unit=7))], unit=7)
    assert board.state() == {7}
    dev.verify()


def test_scripted_exception_is_command_rejected_without_retry(vclock):
    exc_reply = frame(ExceptionResponse(0x0F, 0x04, device_id=1))  # server device failure
    dev, board = scripted("mb-s4", vclock, [(write8(0x01), exc_reply)])
    with pytest.raises(CommandRejected) as err:
        board.set([0])
    assert err.value.code == 4 and err.value.attempt == 1 and err.value.device == "relays"
    assert "device_failure" in str(err.value)
    dev.verify()  # one write only: a refusal is not retried


def test_scripted_answer_from_wrong_unit_is_protocol_error(vclock):
    dev, board = scripted("mb-s5", vclock, [(read8(), coils(0x00, unit=2))], retries=0)
    with pytest.raises(ProtocolError, match="unit 2"):
        board.state()
    dev.verify()


def test_scripted_answer_to_another_question_is_protocol_error(vclock):
    dev, board = scripted("mb-s6", vclock, [(read8(), written8())], retries=0)
    with pytest.raises(ProtocolError, match="does not fit"):
        board.state()
    dev.verify()


def test_scripted_wrong_write_echo_is_protocol_error(vclock):
    bad_echo = frame(WriteMultipleCoilsResponse(address=0, count=4, dev_id=1))
    dev, board = scripted("mb-s7", vclock, [(write8(0), bad_echo)])
    with pytest.raises(ProtocolError, match="echo"):
        board.set([])
    dev.verify()


def test_scripted_partial_answer_is_timeout_with_bytes(vclock):
    dev, board = scripted("mb-s8", vclock, [(read8(), coils(0x00)[:4])], retries=0)
    with pytest.raises(DeviceTimeout, match="01 01 01 00") as err:
        board.state()
    assert err.value.command == "read coils"
    dev.verify()


# -- against the simulator, virtual time --------------------------------------------------------------
def test_driver_is_a_lightbank(rig):
    board, _, _ = rig
    assert isinstance(board, LightBank)
    assert board.name == "relays"


def test_set_state_and_world_mirror(rig, vclock):
    board, sim, world = rig
    board.connect()
    board.set([0, 1, 2])
    assert board.state() == {0, 1, 2} == sim.on_channels == world.lamps_on()
    board.set([5])
    assert world.lamps_on() == {5}
    board.switch(7, True)
    board.switch(5, False)
    assert sim.coils == (False,) * 7 + (True,)
    board.all_off()
    assert world.lamps_on() == frozenset()
    assert vclock.monotonic() < 0.5  # no timeout was spent on the way


def test_bad_channels_are_refused_before_sending(rig):
    board, sim, _ = rig
    for bad in ([8], [-1], [True], ["0"]):
        with pytest.raises(ValueError, match="channel"):
            board.set(bad)
    assert sim.received == b""


def test_more_channels_than_the_board_is_illegal_address(vclock):
    sim = ModbusRelaySim("mb-small", vclock, channels=4)
    registry.register("mb-small", sim)
    board = ModbusRelayBoard("sim://mb-small", clock=vclock, channels=8)
    with pytest.raises(CommandRejected) as err:
        board.set([6])
    assert err.value.code == 0x02 and err.value.attempt == 1
    assert sim.on_channels == frozenset()


def test_other_unit_is_ignored_by_the_board(vclock):
    sim = ModbusRelaySim("mb-u1", vclock, unit=1)
    registry.register("mb-u1", sim)
    board = ModbusRelayBoard("sim://mb-u1", clock=vclock, unit=2, retries=1)
    with pytest.raises(DeviceTimeout) as err:
        board.state()
    assert err.value.attempt == 2 and sim.ignored_frames == 2
    assert 1.0 <= vclock.monotonic() < 1.1  # two timeouts (and the inter-frame gaps)


def test_unsupported_function_and_bad_value_get_exceptions(vclock):
    sim = ModbusRelaySim("mb-raw", vclock)
    registry.register("mb-raw", sim)
    link = SerialLink("sim://mb-raw", device="mb-raw", clock=vclock)
    link.open()
    codec = ModbusRelayCodec("client")

    def ask(raw_body: bytes):
        link.write(raw_body + FramerRTU.compute_CRC(raw_body).to_bytes(2, "big"))
        codec.receive_data(link.read_exact(5))
        return codec.next_event()

    assert ask(bytes.fromhex("01 03 0000 0001")) == ExceptionReply(1, 0x03, 0x01)
    assert ask(bytes.fromhex("01 05 0000 1234")) == ExceptionReply(1, 0x05, 0x03)
    assert ask(bytes.fromhex("01 05 0009 FF00")) == ExceptionReply(1, 0x05, 0x02)
    assert sim.coils == (False,) * 8
    link.close()


def test_broadcast_write_is_executed_silently(vclock):
    sim = ModbusRelaySim("mb-bc", vclock)
    registry.register("mb-bc", sim)
    link = SerialLink("sim://mb-bc", device="mb-bc", clock=vclock, timeout_s=0.2)
    link.open()
    link.write(ModbusRelayCodec("client").send(WriteCoils(0, 0, (True, True))))
    with pytest.raises(DeviceTimeout):
        link.read_exact(1)
    assert sim.on_channels == {0, 1}
    link.close()


def test_sim_answers_any_split_of_a_request(vclock):
    sim = ModbusRelaySim("mb-split", vclock)
    registry.register("mb-split", sim)
    link = SerialLink("sim://mb-split", device="mb-split", clock=vclock)
    link.open()
    for b in write8(0b11):
        link.write(bytes([b]))
    codec = ModbusRelayCodec("client")
    codec.receive_data(link.read_exact(8))
    assert codec.next_event() == CoilsWritten(1, 0, 8)
    assert sim.on_channels == {0, 1}
    link.close()


# -- faults ----------------------------------------------------------------------------------------------
# The injected faults of tests/test_relay_faults.py run against this board and the ASCII one.


def test_missing_port_is_device_gone_at_once(vclock):
    board = ModbusRelayBoard("sim://no-such-board", clock=vclock)
    with pytest.raises(DeviceGone, match="no-such-board") as err:
        board.connect()
    assert err.value.attempt == 1
    assert vclock.monotonic() == 0.0


# -- over a pseudo-terminal, in real time --------------------------------------------------------------
def test_driver_against_simulator_on_a_pty():
    clock = SystemClock()
    log: list[tuple[int, bool]] = []
    sim = ModbusRelaySim("mb-pty", clock, on_change=lambda ch, on: log.append((ch, on)))
    with PtyServer(sim) as srv:
        board = ModbusRelayBoard(srv.path, clock=clock, timeout_s=1.0)
        board.connect()
        board.set([0, 5])
        board.switch(3, True)
        assert board.state() == {0, 3, 5}
        sim.faults.add("garble")
        board.set([1])  # retried after the garbled answer
        assert sim.on_channels == {1}
        board.close()
    assert log == [(0, True), (5, True), (3, True), (0, False), (1, True), (3, False), (5, False)]


def test_concurrent_callers_do_not_interleave_transactions():
    # Real time on a pty, no retries: without the driver's lock the threads' requests and
    # read-backs cross on the line and a caller gets a reply meant for another.
    clock = SystemClock()
    sim = ModbusRelaySim("mb-threads", clock, response_delay_s=0.002)
    errors: list[Exception] = []
    with PtyServer(sim) as srv:
        board = ModbusRelayBoard(srv.path, clock=clock, retries=0, timeout_s=1.0)

        def worker(channel: int) -> None:
            try:
                for _ in range(10):
                    board.set([channel])
                    board.state()
            except Exception as exc:
                errors.append(exc)

        threads = [threading.Thread(target=worker, args=(ch,)) for ch in (1, 2, 3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=20)
        board.close()
    assert errors == []
    assert sim.on_channels in ({1}, {2}, {3})

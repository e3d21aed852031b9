"""Peer test: ``minimalmodbus`` (PyPI), a Modbus RTU master many lab scripts use, against the
simulated relay board on a pseudo-terminal, in real time: coils, exception replies and a
wrong unit id."""

from __future__ import annotations

from collections.abc import Iterator

import minimalmodbus
import pytest
from m2s2hil.drivers.clock import SystemClock
from m2s2hil.simulators.modbus_relay import ModbusRelaySim
from m2s2hil.simulators.pty import PtyServer

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def board() -> Iterator[tuple[ModbusRelaySim, str, list[tuple[int, bool]]]]:
    changes: list[tuple[int, bool]] = []
    sim = ModbusRelaySim(
        "relays-peer", SystemClock(), unit=1, on_change=lambda ch, on: changes.append((ch, on))
    )
    with PtyServer(sim) as srv:
        yield sim, srv.path, changes


def _master(port: str, unit: int = 1) -> minimalmodbus.Instrument:
    inst = minimalmodbus.Instrument(port, unit, mode=minimalmodbus.MODE_RTU, close_port_after_each_call=True)
    inst.serial.baudrate = 9600
    inst.serial.timeout = 0.3
    return inst


def test_read_and_write_coils(board):
    _, port, changes = board
    relays = _master(port)
    assert relays.read_bits(0, 8, functioncode=1) == [0] * 8
    relays.write_bit(2, 1, functioncode=5)
    relays.write_bits(4, [1, 0, 1])  # FC15
    assert relays.read_bits(0, 8, functioncode=1) == [0, 0, 1, 0, 1, 0, 1, 0]
    assert relays.read_bit(6, functioncode=1) == 1
    relays.write_bit(2, 0, functioncode=5)
    assert relays.read_bits(0, 8, functioncode=1) == [0, 0, 0, 0, 1, 0, 1, 0]
    assert changes == [(2, True), (4, True), (6, True), (2, False)]


def test_illegal_address_is_an_exception_reply(board):
    _, port, _ = board
    relays = _master(port)
    with pytest.raises(minimalmodbus.IllegalRequestError):  # exception code 2, illegal data address
        relays.write_bit(8, 1, functioncode=5)  # 8 coils: 0..7
    with pytest.raises(minimalmodbus.IllegalRequestError):
        relays.read_bits(6, 4, functioncode=1)
    assert relays.read_bits(0, 8, functioncode=1) == [0] * 8  # nothing changed, still answering


def test_a_wrong_unit_id_gets_no_answer(board):
    sim, port, changes = board
    with pytest.raises(minimalmodbus.NoResponseError):
        _master(port, unit=7).write_bit(0, 1, functioncode=5)
    assert bytes(sim.received[:1]) == b"\x07"  # the request reached the board, which kept quiet
    assert changes == [] and _master(port).read_bits(0, 8, functioncode=1) == [0] * 8

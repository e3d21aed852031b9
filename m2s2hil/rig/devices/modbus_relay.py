"""Modbus RTU relay boards: driver, simulator and ``rig probe`` (the channel count).

No recognition on a wrong port: a Modbus board answers only frames with its unit id and a
valid CRC, so it is silent to the other kinds' probes and they are silent to it.
"""

from __future__ import annotations

from typing import Any

from m2s2hil.drivers.interfaces import LightBank
from m2s2hil.errors import ConfigError
from m2s2hil.rig.devices.findings import ProbeReport
from m2s2hil.rig.devices.kind import RelayKind, Setup, SimParts, close_quietly, connect_or_close
from m2s2hil.rig.devices.relays import add_channels_finding, channels_needed
from m2s2hil.rig.open_errors import opening


def _simulator(setup: Setup, parts: SimParts) -> Any:
    from m2s2hil.simulators.modbus_relay import ModbusRelaySim

    return ModbusRelaySim(setup.name, setup.clock, parts.faults, unit=setup.device.unit,
                          on_change=parts.world.set_lamp)


def _board(setup: Setup, **extra: Any) -> Any:
    from m2s2hil.drivers.modbus_relay import ModbusRelayBoard

    dev = setup.device
    return ModbusRelayBoard(dev.port, device=setup.name, unit=dev.unit, baudrate=dev.baudrate,
                            timeout_s=dev.timeout_s, clock=setup.clock, retries=dev.retries,
                            parity=dev.parity, stopbits=dev.stopbits, **extra)


def _open_lights(setup: Setup) -> LightBank:
    if setup.device.unit == 0:
        raise ConfigError(
            "rig", f"devices.{setup.name}.unit", "unit 0 is broadcast: a relay board never answers it"
        )
    board = _board(setup)
    connect_or_close(board)
    return board


def _count_coils(board: Any) -> int:
    """How many coils a Modbus board has: the largest count (1..64) it reads without refusing.

    A Modbus RTU relay board answers a read beyond its coils with exception 02, ILLEGAL DATA
    ADDRESS (Modbus Application Protocol V1.1b3, 6.1 Read Coils), which the driver raises as
    CommandRejected; six reads find the count by bisection.
    """
    from m2s2hil.drivers.errors import CommandRejected

    lo, hi = 1, 64
    board.channels = 1
    board.state()
    while lo < hi:
        mid = (lo + hi + 1) // 2
        board.channels = mid
        try:
            board.state()
            lo = mid
        except CommandRejected:
            hi = mid - 1
    board.channels = lo
    return lo


def _probe(setup: Setup, report: ProbeReport, apply: bool) -> None:
    dev = setup.device
    needed = channels_needed(setup.config)
    board = _board(setup, channels=1)
    try:
        with opening(setup.name, dev.port, dev.protocol, dev.baudrate):
            board.connect()
            count = _count_coils(board)
        add_channels_finding(report, setup.name, setup.config, str(count), count >= needed)
    finally:
        close_quietly(board)


KIND = RelayKind(
    protocol="modbus-rtu",
    title="Modbus RTU relay",
    make_simulator=_simulator,
    open_lights=_open_lights,
    probe=_probe,
)

"""Interoperability with stock pymodbus, over real pseudo-terminals.

(a) pymodbus' ModbusSerialClient drives our simulated relay board;
(b) our driver drives pymodbus' own serial server (ModbusSerialServer).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import threading
import tty
from collections.abc import Iterator

import pytest
from m2s2hil.drivers.clock import SystemClock
from m2s2hil.drivers.errors import CommandRejected
from m2s2hil.drivers.modbus_relay import ModbusRelayBoard
from m2s2hil.simulators.modbus_relay import ModbusRelaySim
from m2s2hil.simulators.pty import PtyServer
from m2s2hil.simulators.world import World
from pymodbus.client import ModbusSerialClient
from pymodbus.server import ModbusSerialServer
from pymodbus.simulator import DataType, SimData, SimDevice

pytestmark = pytest.mark.timeout(30)


# -- (a) stock client, our simulator ------------------------------------------------------------------
def test_stock_pymodbus_client_drives_our_simulator():
    clock = SystemClock()
    world = World(clock)
    sim = ModbusRelaySim("interop-a", clock, unit=1, on_change=world.set_lamp)
    with PtyServer(sim) as srv:
        client = ModbusSerialClient(srv.path, baudrate=9600, timeout=1, retries=0)
        assert client.connect()
        try:
            rr = client.read_coils(0, count=8, device_id=1)
            assert not rr.isError() and rr.bits[:8] == [False] * 8

            assert not client.write_coil(2, True, device_id=1).isError()
            assert not client.write_coils(4, [True, False, True], device_id=1).isError()
            assert sim.on_channels == {2, 4, 6} == world.lamps_on()

            rr = client.read_coils(0, count=8, device_id=1)
            assert rr.bits[:8] == [False, False, True, False, True, False, True, False]

            rr = client.read_coils(6, count=4, device_id=1)  # coils 8, 9 do not exist
            assert rr.isError() and rr.exception_code == 0x02
            rr = client.read_holding_registers(0, count=1, device_id=1)
            assert rr.isError() and rr.exception_code == 0x01
        finally:
            client.close()


# -- (b) our driver, stock server --------------------------------------------------------------------
@contextlib.contextmanager
def pty_bridge() -> Iterator[tuple[str, str]]:
    """Two pty pairs joined master to master: a null-modem cable between two /dev/pts paths.

    pyserial (and so pymodbus' server) can only open a path, and a pty master has none,
    so each side gets a slave end. The slave ends stay open here so neither master sees
    EIO when a client closes.
    """
    pairs = [os.openpty() for _ in range(2)]
    for master, slave in pairs:
        tty.setraw(master)
        tty.setraw(slave)
    (m1, s1), (m2, s2) = pairs
    stop = threading.Event()

    def pump() -> None:
        peer = {m1: m2, m2: m1}
        while not stop.is_set():
            ready, _, _ = select.select([m1, m2], [], [], 0.05)
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                    os.write(peer[fd], data)
                except OSError:
                    return

    thread = threading.Thread(target=pump, name="pty-bridge", daemon=True)
    thread.start()
    try:
        yield os.ttyname(s1), os.ttyname(s2)
    finally:
        stop.set()
        thread.join(timeout=2)
        for fd in (m1, s1, m2, s2):
            with contextlib.suppress(OSError):
                os.close(fd)


@contextlib.contextmanager
def stock_server(port: str, unit: int) -> Iterator[SimDevice]:
    """pymodbus' ModbusSerialServer on ``port``, in a thread with its own event loop.

    The coils live in a pymodbus SimDevice block (one 16-bit register = 16 coils with
    bit addressing), so coils 0..15 exist and 16 up are ILLEGAL_ADDRESS.
    """
    device = SimDevice(
        id=unit,
        simdata=(
            [SimData(0, count=1, values=False, datatype=DataType.BITS)],
            [SimData(0, values=False, datatype=DataType.BITS)],
            [SimData(0, values=0, datatype=DataType.REGISTERS)],
            [SimData(0, values=0, datatype=DataType.REGISTERS)],
        ),
    )
    loop = asyncio.new_event_loop()
    started = threading.Event()
    box: dict[str, object] = {}

    async def serve() -> None:
        server = ModbusSerialServer(device, port=port, baudrate=9600)
        box["server"] = server
        try:
            await server.serve_forever(background=True)
        except Exception as exc:  # reported to the test thread below
            box["error"] = exc
            started.set()
            return
        started.set()
        await server.serving

    def run() -> None:
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(serve())
        finally:
            loop.close()

    thread = threading.Thread(target=run, name="pymodbus-server", daemon=True)
    thread.start()
    try:
        assert started.wait(5), "pymodbus server did not start"
        assert "error" not in box, box.get("error")
        yield device
    finally:
        server = box.get("server")
        if server is not None and not loop.is_closed():
            asyncio.run_coroutine_threadsafe(server.shutdown(), loop).result(timeout=5)
        thread.join(timeout=5)
        assert not thread.is_alive(), "pymodbus server thread did not stop"


def test_our_driver_drives_a_stock_pymodbus_server():
    with pty_bridge() as (server_port, driver_port), stock_server(server_port, unit=1):
        board = ModbusRelayBoard(driver_port, clock=SystemClock(), timeout_s=1.0)
        try:
            board.connect()
            assert board.state() == frozenset()
            board.set([1, 3, 7])
            assert board.state() == {1, 3, 7}
            board.switch(0, True)
            board.switch(3, False)
            assert board.state() == {0, 1, 7}
            board.all_off()
            assert board.state() == frozenset()

            # 17 coils: coil 16 is past the server's block -> its exception code, typed
            wide = ModbusRelayBoard(driver_port, clock=SystemClock(), timeout_s=1.0, channels=17)
            board.close()
            with pytest.raises(CommandRejected) as err:
                wide.state()
            assert err.value.code == 0x02
            wide.close()
        finally:
            board.close()

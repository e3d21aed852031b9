"""Injected faults against both relay boards' drivers, one parametrized set of tests.

Each board runs against its simulator on ``sim://`` (virtual clock), mirrored into a World
so a test sees which lamps are really lit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pytest
from m2s2hil.drivers.ascii_relay import AsciiRelayBoard
from m2s2hil.drivers.errors import DeviceGone, DeviceTimeout, ProtocolError, RelayNotSwitched
from m2s2hil.drivers.modbus_relay import ModbusRelayBoard
from m2s2hil.simulators import registry
from m2s2hil.simulators.ascii_relay import AsciiRelaySim
from m2s2hil.simulators.fault_injection import FaultPlan
from m2s2hil.simulators.modbus_relay import ModbusRelaySim
from m2s2hil.simulators.world import World

pytestmark = pytest.mark.timeout(30)


@dataclass(frozen=True)
class Board:
    name: str
    sim_cls: type
    driver_cls: type
    set_2_command: str  # what the driver reports as the command of set([2])


BOARDS = [
    Board("modbus", ModbusRelaySim, ModbusRelayBoard, "set [2]"),
    Board("ascii", AsciiRelaySim, AsciiRelayBoard, "relay writeall 04"),
]


@dataclass
class Bench:
    board: Any
    sim: Any
    world: World


@pytest.fixture(params=BOARDS, ids=[b.name for b in BOARDS])
def kind_of_board(request) -> Board:
    return request.param


def _bench(kind: Board, vclock, faults: FaultPlan | None = None) -> Bench:
    name = f"relay-faults-{kind.name}"
    world = World(vclock)
    sim = kind.sim_cls(name, vclock, faults, on_change=world.set_lamp)
    registry.register(name, sim)
    return Bench(kind.driver_cls(f"sim://{name}", clock=vclock), sim, world)


@pytest.fixture
def bench(kind_of_board, vclock):
    b = _bench(kind_of_board, vclock)
    yield b
    b.board.close()
    registry.unregister(f"relay-faults-{kind_of_board.name}")


@pytest.mark.parametrize("kind", ["drop_reply", "garble", "late_reply"])
def test_one_off_faults_are_recovered(bench, kind):
    bench.sim.faults.add(kind)
    bench.board.set([1, 3])
    assert bench.board.state() == {1, 3} == bench.world.lamps_on()
    assert [k for k, _ in bench.sim.faults.log] == [kind]


@pytest.mark.parametrize(
    ("kind", "error"),
    [("drop_reply", DeviceTimeout), ("garble", ProtocolError), ("late_reply", DeviceTimeout)],
)
def test_persistent_faults_end_in_typed_errors(bench, kind_of_board, kind, error):
    bench.sim.faults.add(kind, count=-1)
    with pytest.raises(error) as err:
        bench.board.set([2])
    assert err.value.attempt == 3 and err.value.device == "relays"
    assert err.value.command == kind_of_board.set_2_command


def test_a_stuck_relay_is_relay_not_switched_once(bench):
    bench.board.set([4])
    bench.sim.faults.add("relay_stuck", channel=4)
    with pytest.raises(RelayNotSwitched, match=r"stuck: \[4\]") as err:
        bench.board.set([0])
    assert err.value.fault_class == "protocol"
    assert bench.sim.on_channels == {0, 4} == bench.world.lamps_on()  # the board answered, relay 4 stayed on
    bench.board.set([0])  # a one-off: the next write goes through
    assert bench.world.lamps_on() == {0}


def test_a_stuck_relay_on_switch(bench):
    bench.sim.faults.add("relay_stuck", channel=6)
    with pytest.raises(RelayNotSwitched, match="6 reads off"):
        bench.board.switch(6, True)


def test_vanish_is_recovered_by_reconnecting(bench, vclock):
    bench.board.connect()
    bench.sim.faults.add("vanish", duration_s=1.0)
    bench.board.set([7])
    assert bench.board.state() == {7} == bench.world.lamps_on()
    assert vclock.monotonic() >= 1.0


def test_vanish_for_good_is_device_gone(bench):
    bench.board.connect()
    bench.sim.faults.add("vanish", duration_s=1e6)
    with pytest.raises(DeviceGone) as err:
        bench.board.set([1])
    assert err.value.attempt == 3 and err.value.fault_class == "device_gone"


def test_a_fault_plan_from_configuration_reaches_the_board(kind_of_board, vclock):
    plan = FaultPlan.from_config([{"kind": "relay_stuck", "channel": 3, "count": -1}])
    b = _bench(kind_of_board, vclock, plan)
    try:
        b.board.set([1])
        for _ in range(2):  # forever: every write that touches relay 3
            with pytest.raises(RelayNotSwitched):
                b.board.set([3])
        assert b.world.lamps_on() == set()
    finally:
        b.board.close()
        registry.unregister(f"relay-faults-{kind_of_board.name}")


def test_a_seeded_rate_garbles_some_replies_and_the_driver_recovers(kind_of_board, vclock):
    plan = FaultPlan(seed=11)
    plan.add("garble", rate=0.2)
    b = _bench(kind_of_board, vclock, plan)
    try:
        for i in range(20):
            b.board.set([i % 8])
            assert b.world.lamps_on() == {i % 8}
        assert 0 < len(plan.log) < 20  # some replies garbled, every one retried
    finally:
        b.board.close()
        registry.unregister(f"relay-faults-{kind_of_board.name}")

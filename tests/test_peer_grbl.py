"""Peer test: ``pygrbl-streamer`` (PyPI), a maintained GRBL G-code streamer, against the GRBL
simulator on a pseudo-terminal, in real time. It resets, unlocks, streams with character
counting, and recovers from an alarm with its own reset sequence, none of it our code."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from m2s2hil.drivers.clock import SystemClock
from m2s2hil.simulators.grbl import GrblSimulator
from m2s2hil.simulators.grbl_settings import GrblAxisSettings
from m2s2hil.simulators.pty import PtyServer
from pygrbl_streamer import GrblStreamer, State

pytestmark = pytest.mark.timeout(30)
FAST = {axis: GrblAxisSettings(max_rate=60000, accel=20000) for axis in "XY"}


class Recorder(GrblStreamer):
    """The streamer, keeping what its callbacks report."""

    def __init__(self, port: str) -> None:
        super().__init__(port)
        self.lines: list[str] = []
        self.alarms: list[str] = []
        self.errors: list[str] = []
        self._seen = threading.Condition()

    # Callbacks run on the streamer's own thread: record, then wake whoever waits.
    def _record(self, into: list[str], line: str) -> None:
        with self._seen:
            into.append(line)
            self._seen.notify_all()

    def receive_callback(self, data: str) -> None:
        self._record(self.lines, data)

    def alarm_callback(self, line: str) -> None:
        self._record(self.alarms, line)

    def error_callback(self, line: str) -> None:
        self._record(self.errors, line)

    def wait_for(self, text: str, where: list[str] | None = None, timeout: float = 3.0) -> None:
        lines = self.lines if where is None else where
        with self._seen:
            assert self._seen.wait_for(lambda: any(text in line for line in lines), timeout), text


@pytest.fixture
def served() -> Iterator[Callable[..., tuple[GrblSimulator, Recorder]]]:
    made: list[tuple[PtyServer, Recorder]] = []

    def make(**kw: Any) -> tuple[GrblSimulator, Recorder]:
        sim = GrblSimulator(f"grbl-peer-{len(made)}", SystemClock(), axes=FAST, **kw)
        srv = PtyServer(sim).start()
        host = Recorder(srv.path)
        made.append((srv, host))
        host.connect()
        return sim, host

    yield make
    for srv, host in made:
        host.disconnect()
        srv.close()


@pytest.mark.slow  # ~2 s in real time
def test_factory_controller_connects_streams_and_refuses_homing(served):
    sim, host = served()
    assert host.state == State.IDLE
    host.wait_for("Grbl 1.1h ['$' for help]")
    assert host.home() is False  # $22=0: homing disabled
    host.wait_for("error:5", host.errors)
    moves = [f"G1 X{i % 7 + 1} Y{i % 5} F30000" for i in range(60)]  # > 128 bytes: counting matters
    assert host.stream([*moves, "G0 X12.5 Y-3"], total=61, completion_timeout=10)
    assert sim.rx_overflow == 0
    assert sim.machine_position() == pytest.approx((12.5, -3.0, 0.0))
    assert host.command("G10 L20 P1 X0 Y0")  # the work origin where the stage stands
    host.lines.clear()
    assert host.command("$#")
    host.wait_for("[G54:")  # callbacks run on their own thread, maybe after the ok returned
    assert "[G54:12.500,-3.000,0.000]" in host.lines


def test_soft_limit_alarm_and_its_reset_sequence(served):
    sim, host = served(settings={22: 1, 20: 1})
    assert host.state == State.IDLE  # connect() unlocked the boot lock with $X
    assert host.stream(["G0 X-5"], completion_timeout=5)  # waits for Idle
    host.lines.clear()
    host.write_line("G0 X-500")  # outside the default 200-unit travel
    host.wait_for("ALARM:2", host.alarms)
    host.wait_for("[MSG:Reset to continue]")
    assert host.alarms == ["ALARM:2"] and host.state == State.ALARM
    assert host.reset()  # 0x18, drain, $X, status: back to Idle
    host.wait_for("[MSG:Caution: Unlocked]")
    after = host.lines[host.lines.index("[MSG:Reset to continue]") + 1:]
    assert after[:3] == ["ok", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert sim.state == "Idle" and sim.axis_position("X") == pytest.approx(-5.0)

"""The sim:// transport, the pty server and the serial link, with a scripted device."""

import pytest
import serial
from m2s2hil.drivers.clock import SystemClock
from m2s2hil.drivers.errors import DeviceGone, DeviceTimeout
from m2s2hil.drivers.serial_link import SerialLink
from m2s2hil.simulators import registry
from m2s2hil.simulators.pty import PtyServer
from m2s2hil.simulators.scripted import ScriptedDevice, ScriptError


def test_scripted_pairs_and_virtual_time(vclock):
    dev = ScriptedDevice("scr", vclock, [(b"a\n", b"A\n"), (b"b\n", b"B\n")], delay=0.25)
    registry.register("scr", dev)
    link = SerialLink("sim://scr", device="scr", clock=vclock)
    link.open()
    link.write(b"a\n")
    assert link.read_until(b"\n") == b"A\n"
    assert vclock.monotonic() == pytest.approx(0.25)
    with pytest.raises(ScriptError):
        dev.verify()  # pair 1 unused
    link.write(b"b\n")
    assert link.read_until(b"\n") == b"B\n"
    dev.verify()
    with pytest.raises(ScriptError, match="unscripted write"):
        link.write(b"c\n")


def test_timeout_costs_virtual_time_only(vclock):
    dev = ScriptedDevice("silent", vclock, [(b"?", b"")])
    registry.register("silent", dev)
    link = SerialLink("sim://silent", device="silent", clock=vclock, timeout_s=5.0)
    link.open()
    link.write(b"?")
    with pytest.raises(DeviceTimeout, match="silent"):
        link.read_until(b"\n")
    assert vclock.monotonic() == pytest.approx(5.0)


def test_vanish_and_reconnect(vclock):
    dev = ScriptedDevice("v", vclock, [(b"x\n", b"ok\n")])
    registry.register("v", dev)
    link = SerialLink("sim://v", device="v", clock=vclock)
    link.open()
    dev.vanish(1.0)
    with pytest.raises(DeviceGone):
        link.write(b"x\n")
    link.reconnect(interval_s=0.4)
    link.write(b"x\n")
    assert link.read_until(b"\n") == b"ok\n"
    assert vclock.monotonic() >= 1.0


def test_pty_serves_stock_pyserial():
    dev = ScriptedDevice("p", SystemClock(), [(b"ping\n", b"pong\n")])
    with PtyServer(dev) as srv:
        port = serial.Serial(srv.path, 115200, timeout=2)
        port.write(b"ping\n")
        assert port.readline() == b"pong\n"
        port.close()
    dev.verify()

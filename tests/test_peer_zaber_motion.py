"""Peer test: Zaber's own Python library (``zaber-motion``, from PyPI) against the Zaber
simulator on a pseudo-terminal, in real time.

Where it stops: ``identify()`` (also run by ``detect_devices()``) reads every setting it
needs from the simulator and then asks Zaber's device database for the device id and
firmware version (``GET <source>/device/<deviceid>?fw=<version>.<build>``). The database
is an online web service or a file downloaded from Zaber; neither is available offline, so
identification ends there with ``DeviceDbFailedException``, and without an identified
device the library cannot convert units (degrees). Everything in native units works.
The test points the library at a local stand-in for the web service that answers 404, so
it never depends on the network and can see exactly what the library asked for.
"""

from __future__ import annotations

import http.server
import threading
import time
from collections.abc import Iterator
from typing import Any, ClassVar

import pytest
import zaber_motion
from m2s2hil.drivers.clock import SystemClock
from m2s2hil.simulators.pty import PtyServer
from m2s2hil.simulators.zaber import (
    DEVICE_ID,
    FIRMWARE_BUILD,
    FIRMWARE_VERSION,
    ZaberAxisSettings,
    ZaberSimulator,
)
from zaber_motion import DeviceDbSourceType, Library, LogOutputMode, Units
from zaber_motion.ascii import Connection

pytestmark = pytest.mark.timeout(30)


class RecordingZaber(ZaberSimulator):
    """The simulator, keeping every line it answered."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.answered: list[str] = []
        super().__init__(*args, **kwargs)

    def send(self, data: bytes, delay: float = 0.0, *, reply: bool = True) -> None:
        self.answered.append(data.decode().strip())
        super().send(data, delay, reply=reply)


class _NoDatabase(http.server.BaseHTTPRequestHandler):
    asked: ClassVar[list[str]] = []

    def do_GET(self) -> None:
        type(self).asked.append(self.path)
        self.send_error(404, "no device database here")

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture(scope="module")
def no_db() -> Iterator[type[_NoDatabase]]:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _NoDatabase)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    Library.set_log_output(LogOutputMode.OFF)
    Library.disable_device_db_store()  # no cache: every identify asks the source
    Library.set_device_db_source(DeviceDbSourceType.WEB_SERVICE, f"http://127.0.0.1:{server.server_port}")
    yield _NoDatabase
    server.shutdown()
    Library.set_device_db_source(DeviceDbSourceType.WEB_SERVICE)  # back to Zaber's service


@pytest.fixture
def stage() -> Iterator[tuple[RecordingZaber, Connection]]:
    # Fast settings so real-time moves take milliseconds (native units: microsteps).
    sim = RecordingZaber("zaber-peer", SystemClock(), axes=[ZaberAxisSettings(maxspeed=10**7, accel=10**4,
                                                                            start=3000)])
    with PtyServer(sim) as srv, Connection.open_serial_port(srv.path) as conn:
        yield sim, conn


def test_identify_reads_every_setting_then_stops_at_the_device_database(stage, no_db):
    sim, conn = stage
    no_db.asked.clear()
    with pytest.raises(zaber_motion.DeviceDbFailedException):
        conn.detect_devices()  # identify_devices=True
    sent = sim.received.decode()
    for setting in ("comm.packet.size.max", "deviceid", "system.serial", "version", "version.build",
                    "device.hw.modified", "comm.command.packets.max", "comm.word.size.max",
                    "get.settings.max", "system.axiscount", "resolution"):
        assert f" get {setting}:" in sent, setting
    rejected = [line for line in sim.answered if " RJ " in line]
    assert len(rejected) == 1 and "BADCOMMAND" in rejected[0]  # peripheralid: an integrated stage
    assert no_db.asked == [f"/device/{DEVICE_ID}?fw={FIRMWARE_VERSION}.{FIRMWARE_BUILD}"]


def test_native_units_work_degrees_need_the_database(stage, no_db):
    sim, conn = stage
    (device,) = conn.detect_devices(identify_devices=False)
    # device.device_id would need identify(); the settings are there without it.
    assert device.settings.get("deviceid") == DEVICE_ID and device.settings.get("system.serial") == 12345
    axis = device.get_axis(1)
    assert "WR" in {str(f) for f in axis.warnings.get_flags()}  # never homed since power-up
    axis.home()
    assert axis.get_position() == 0 and sim.axis_position(1) == 0
    axis.move_absolute(4266)  # about 1 degree of an X-RSW60A
    axis.move_relative(-1000)
    assert axis.get_position() == 3266 and sim.axis_position(1) == pytest.approx(3266)
    assert axis.settings.get("maxspeed") == 10**7
    axis.settings.set("maxspeed", 5 * 10**6)
    assert axis.settings.get("maxspeed") == 5 * 10**6 and sim.device_settings["version"] == FIRMWARE_VERSION
    axis.move_velocity(200000)
    time.sleep(0.05)
    assert axis.is_busy()
    axis.stop()
    assert not axis.is_busy()
    stopped = axis.get_position()
    time.sleep(0.05)
    assert axis.get_position() == stopped > 3266
    # Units other than native ones need the identification the device database would give.
    with pytest.raises(zaber_motion.DeviceNotIdentifiedException):
        axis.move_absolute(10, Units.ANGLE_DEGREES)
    with pytest.raises(zaber_motion.DeviceDbFailedException):
        device.identify()

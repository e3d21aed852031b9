"""`m2s2hil sim serve`: the simulated rig on ptys, driven by our drivers and by plain pyserial."""

import tomllib

import pytest
import serial

from m2s2hil.config import parse_rig
from m2s2hil.rig.factory import open_rig
from m2s2hil.rig.pty_serve import SimServer


def test_plain_pyserial_talks_grbl_on_the_pty():
    with SimServer() as srv:
        stage = next(d for d in srv.devices if d.name == "stage")
        port = serial.Serial(stage.path, 115200, timeout=2)
        port.write(b"\x18")  # soft reset -> banner
        assert b"Grbl 1.1h" in port.read_until(b"]\r\n")
        port.write(b"$I\n")
        reply = port.read_until(b"ok\r\n")
        assert b"[VER:1.1h" in reply
        port.close()


@pytest.mark.slow  # moves over ptys in real time: ~2 s
def test_generated_rig_file_drives_the_pty_devices(tmp_path):
    with SimServer() as srv:
        text = srv.rig_toml()
        data = tomllib.loads(text)
        paths = {d.name: d.path for d in srv.devices}
        assert data["devices"]["stage"]["port"] == paths["stage"]
        assert data["devices"]["relays"]["port"] == paths["relays"]
        cfg = parse_rig(data, "served.toml")
        rig = open_rig(cfg)  # motion + lights over ptys, camera in-process
        try:
            assert not rig.simulated
            rig.lights.set(cfg.lamp_channels("weak"))
            assert srv.world.lamps_on() == frozenset(cfg.lamp_channels("weak"))
            assert rig.tilt.move_to(2.0) == pytest.approx(2.0, abs=rig.config.axes["tilt"].tolerance_deg)
            assert abs(srv.world.pose().tilt_deg - 2.0) <= rig.config.axes["tilt"].tolerance_deg
            # The camera is simulated here, the stage is not: the camera's world follows
            # the pty stage through the driver's read-back.
            rig.turntable.move_to(30.0)
            local = rig.world
            assert local is not srv.world
            assert abs(local.pose().azimuth_deg - 30.0) <= rig.config.axes["turntable"].tolerance_deg
            assert local.lamps_on() == frozenset(cfg.lamp_channels("weak"))
        finally:
            rig.safe()
            rig.close()
        assert srv.world.lamps_on() == frozenset()


def test_generated_rig_file_keeps_everything_but_the_ports(tmp_path):
    """Whatever TOML style the source file uses (dotted keys, inline tables), the served
    rig file is the same configuration with only the serial ports changed."""
    from importlib import resources

    from m2s2hil.config import load_rig

    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    start, end = text.index("[devices.stage]"), text.index("# GRBL machine units")
    inline = (
        "[devices]\n"
        'stage = { protocol = "grbl", port = "sim://stage", baudrate = 115200, timeout_s = 1.0 }\n'
        'relays = { protocol = "modbus-rtu", port = "sim://relays", baudrate = 9600, unit = 1 }\n\n'
    )
    text = text[:start] + inline + text[end:]
    src = tmp_path / "dotted.toml"
    src.write_text(text)
    cfg = load_rig(src)
    with SimServer(cfg) as srv:
        out = parse_rig(tomllib.loads(srv.rig_toml()), "served.toml")
        paths = {d.name: d.path for d in srv.devices}
    assert {n: d.port for n, d in out.devices.items()} == paths
    expected = cfg.model_copy(update={"devices": {
        n: d.model_copy(update={"port": paths[n]}) for n, d in cfg.devices.items()}})
    assert out == expected

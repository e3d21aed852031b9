"""Axes without home switches: a factory GRBL (``$22=0``) on a pseudo-terminal, the operator's
origin (``G10 L20``, recorded next to the rig file), and a capture that never sends ``$H``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import serial
from rig_files import write_rig

from m2s2hil.config import load_rig
from m2s2hil.rig.factory import open_rig
from m2s2hil.rig.open_errors import EXIT_UNUSABLE, RigOpenError
from m2s2hil.rig.operations import RigOps
from m2s2hil.rig.origin import AxisOrigin, RigState, set_origin, state_path
from m2s2hil.rig.pty_serve import SimServer


def _served(tmp_path: Path, srv: SimServer) -> Path:
    path = tmp_path / "bench.toml"
    path.write_text(srv.rig_toml())
    return path


def _raw(path: str, line: bytes) -> bytes:
    """What another program would send: one line on the pty, its reply up to ``ok``."""
    with serial.Serial(path, 115200, timeout=2) as port:
        port.write(line)
        return port.read_until(b"ok\r\n")


@pytest.fixture
def factory_grbl(tmp_path):
    """The simulators on ptys, the GRBL in its factory state: homing off, no switches."""
    cfg = load_rig(write_rig(tmp_path / "src.toml", homing="none"))
    with SimServer(cfg) as srv:
        assert srv.sims["stage"].settings[22] == 0
        yield srv, _served(tmp_path, srv)


def test_no_switches_and_no_origin_is_one_clear_error(factory_grbl):
    _srv, rig_file = factory_grbl
    with pytest.raises(RigOpenError) as info:
        open_rig(load_rig(rig_file))
    err = info.value
    assert err.cause == "no origin" and err.exit_code == EXIT_UNUSABLE
    assert "rig origin turntable" in str(err) and str(rig_file.with_suffix(".state.json")) in str(err)


def test_origin_is_set_where_the_axis_stands_and_moves_count_from_it(factory_grbl):
    srv, rig_file = factory_grbl
    stage = next(d for d in srv.devices if d.name == "stage")
    # The operator has turned the table 37 units off the power-up position (a jog).
    assert _raw(stage.path, b"G53 G0 X37 Y-4\n").endswith(b"ok\r\n")
    sim = srv.sims["stage"]
    deadline = 50
    while sim.state != "Idle" and deadline:
        srv.clock.sleep(0.05)
        deadline -= 1
    config = load_rig(rig_file)
    turntable = set_origin(config, "turntable")
    tilt = set_origin(config, "tilt")
    assert turntable.offset_units == pytest.approx(37.0) and tilt.offset_units == pytest.approx(-4.0)
    assert sim.coord_data[54][:2] == pytest.approx([37.0, -4.0])  # G10 L20 reached the controller
    doc = json.loads(state_path(config).read_text())
    assert doc["origins"]["turntable"]["axis"] == "X" and doc["origins"]["tilt"]["offset_units"] == -4.0

    rig = open_rig(load_rig(rig_file))
    try:
        assert rig.turntable.position() == pytest.approx(0.0, abs=1e-3)
        assert rig.turntable.move_to(20.0) == pytest.approx(20.0, abs=0.05)
        assert rig.tilt.move_to(5.0) == pytest.approx(5.0, abs=0.05)
        # Physically: the origin plus the angle (1 unit per degree in this rig).
        assert sim.axis_position("X") == pytest.approx(57.0, abs=0.05)
        assert sim.axis_position("Y") == pytest.approx(1.0, abs=0.05)
    finally:
        rig.safe()
        rig.close()


def test_an_origin_changed_behind_our_back_is_refused(factory_grbl):
    srv, rig_file = factory_grbl
    config = load_rig(rig_file)
    set_origin(config, "turntable")
    set_origin(config, "tilt")
    stage = next(d for d in srv.devices if d.name == "stage")
    _raw(stage.path, b"G10 L2 P1 X12\n")  # another program rewrites G54
    with pytest.raises(RigOpenError) as info:
        open_rig(load_rig(rig_file))
    assert info.value.cause == "position unknown" and "recorded one 0" in str(info.value)


def _open_error(tmp_path: Path, **rig: object) -> RigOpenError:
    """Why opening the rig written with ``rig`` options, served on ptys, is refused."""
    with SimServer(load_rig(write_rig(tmp_path / "src.toml", **rig))) as srv:
        rig_file = _served(tmp_path, srv)
        with pytest.raises(RigOpenError) as info:
            open_rig(load_rig(rig_file))
    return info.value


def test_homing_enabled_on_a_controller_the_rig_says_has_no_switches(tmp_path):
    err = _open_error(tmp_path, homing="none", switches_in_sim=True)
    assert err.cause == "alarm" and "$22=1" in str(err)


def test_switches_in_the_rig_file_but_homing_off_in_the_controller(tmp_path):
    err = _open_error(tmp_path, homing="switches", switches_in_sim=False)
    assert err.cause == "homing disabled" and "error:5" in str(err)


def test_alarm_recovery_without_switches_unlocks_and_rereads_never_homes(tmp_path):
    """In-process: a factory GRBL would answer $H with error:5, so a recovery that sent it fails."""
    rig = open_rig(load_rig(write_rig(tmp_path / "r.toml", homing="none")))
    try:
        sim = rig.sims["stage"]
        assert sim.settings[22] == 0
        rig.turntable.move_to(30.0)
        sim.faults.add("alarm", code=3)
        with pytest.raises(Exception) as info:
            rig.turntable.move_to(90.0)
        assert "ALARM" in str(info.value)
        ops = RigOps(rig)
        assert ops.home("stage") == ["turntable", "tilt"]
        assert sim.state == "Idle"
        here = rig.turntable.position()
        assert 30.0 <= here <= 90.0  # the controller's own count, re-read, not a new zero
        assert rig.turntable.move_to(40.0) == pytest.approx(40.0, abs=0.05)
    finally:
        rig.close()


def test_state_file_round_trip_and_a_broken_one_is_a_clear_error(tmp_path):
    path = tmp_path / "x.state.json"
    assert RigState.load(path).origins == {}
    origin = AxisOrigin("stage", "grbl", "X", "GRBL 1.1h.20190830", 37.0, "2026-12-01T00:00:00Z")
    RigState(rig="bench", origins={"turntable": origin}).save(path)
    assert RigState.load(path) == RigState(rig="bench", origins={"turntable": origin})
    path.write_text("{not json")
    with pytest.raises(Exception) as info:
        RigState.load(path)
    assert "not a usable rig state file" in str(info.value) and str(path) in str(info.value)


@pytest.mark.slow
@pytest.mark.timeout(600)  # generous: a loaded machine stretches it, it does not fail it
def test_capture_completes_on_a_factory_grbl_over_a_pty(factory_grbl, tmp_path):
    """The issue's acceptance: `rig origin` for both axes, then `capture --rig` with no homing."""
    _srv, rig_file = factory_grbl

    def cli(*args: str, entry: str = "main") -> subprocess.CompletedProcess:
        code = f"import sys; from m2s2hil.cli import {entry}; sys.argv[0] = 'm2s2hil'; {entry}()"
        return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                              timeout=240)

    for axis in ("turntable", "tilt"):
        res = cli("rig", "origin", axis, "--rig", str(rig_file))
        assert res.returncode == 0, res.stderr
        assert "recorded in" in res.stdout
    out = tmp_path / "sessions"
    res = cli("--rig", str(rig_file), "--out", str(out), "--sat", "hubble", "--build", "B2",
              "--light", "weak", "--tilt", "E1", "--azimuth-step", "120", entry="capture_main")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "Traceback" not in res.stderr
    assert "completed" in res.stdout


def test_a_restarted_controller_under_axes_without_switches_stops_the_run(tmp_path):
    """A power cycle loses the position; without switches nothing may pretend to find it again."""
    from m2s2hil.drivers.errors import DeviceGone

    from m2s2hil.rig.origin import PositionLost

    rig = open_rig(load_rig(write_rig(tmp_path / "r.toml", homing="none")))
    try:
        rig.turntable.move_to(45.0)
        rig.sims["stage"].vanish(0.5)  # unplugged: the USB-powered board loses power
        with pytest.raises(DeviceGone):
            rig.turntable.position()
        rig.clock.sleep(1.0)
        with pytest.raises(PositionLost) as info:
            RigOps(rig).reconnect("stage")
        assert info.value.roles == ["turntable", "tilt"] and "rig origin" in str(info.value)
    finally:
        rig.close()


def test_zaber_axes_without_switches_get_their_origin_from_set_pos(tmp_path):
    from rig_files import zaber_rig_text

    src = tmp_path / "z.toml"
    src.write_text(zaber_rig_text(homing="none"))
    with SimServer(load_rig(src)) as srv:
        rig_file = _served(tmp_path, srv)
        with pytest.raises(RigOpenError) as info:
            open_rig(load_rig(rig_file))
        assert info.value.cause == "no origin"
        config = load_rig(rig_file)
        got = set_origin(config, "turntable")
        set_origin(config, "tilt")
        assert got.controller.startswith("Zaber") and got.axis == "1"
        rig = open_rig(load_rig(rig_file))
        try:
            assert rig.turntable.move_to(20.0) == pytest.approx(20.0, abs=0.05)
            assert srv.sims["stage"].axis_position(1) == pytest.approx(2000.0, abs=1.0)  # 100 usteps/deg
        finally:
            rig.close()

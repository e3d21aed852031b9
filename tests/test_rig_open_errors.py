"""Opening a rig never shows a traceback: each failure is one line naming the device, the port and
the cause, with a hint and an exit code (6: not reachable, 7: reachable but unusable)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import serial
from m2s2hil.drivers.clock import SYSTEM_CLOCK
from m2s2hil.simulators.grbl import GrblSimulator
from m2s2hil.simulators.pty import PtyServer
from m2s2hil.simulators.zaber import ZaberSimulator
from rig_files import rig_text

from m2s2hil.config import load_rig
from m2s2hil.rig.factory import open_rig
from m2s2hil.rig.open_errors import EXIT_UNREACHABLE, EXIT_UNUSABLE, RigOpenError, identify_port
from m2s2hil.rig.pty_serve import SimServer


def _rig(tmp_path: Path, text: str, name: str = "rig.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _open_error(path: Path) -> RigOpenError:
    with pytest.raises(RigOpenError) as info:
        open_rig(load_rig(path))
    return info.value


def _cli(*args: str, entry: str = "main") -> subprocess.CompletedProcess:
    code = f"import sys; from m2s2hil.cli import {entry}; sys.argv[0] = 'm2s2hil'; {entry}()"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120)


def _one_line(res: subprocess.CompletedProcess, *needles: str) -> None:
    assert "Traceback" not in res.stderr, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, res.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def _missing_port_rig(tmp_path: Path) -> Path:
    text = rig_text(homing="switches").replace('port = "sim://stage"', 'port = "/dev/ttyNOPE9"')
    return _rig(tmp_path, text)


def test_missing_port(tmp_path):
    path = _missing_port_rig(tmp_path)
    err = _open_error(path)
    assert (err.device, err.port, err.cause, err.exit_code) == ("stage", "/dev/ttyNOPE9", "missing port",
                                                                EXIT_UNREACHABLE)
    assert "/dev/serial/by-id/" in err.hint


@pytest.mark.slow
def test_missing_port_in_the_cli_and_the_daemon_is_one_line(tmp_path):
    path = _missing_port_rig(tmp_path)
    res = _cli("--rig", str(path), "--out", str(tmp_path / "s"), "--sat", "hubble", "--build", "B2",
               "--light", "weak", entry="capture_main")
    assert res.returncode == EXIT_UNREACHABLE
    _one_line(res, "stage", "/dev/ttyNOPE9", "missing port", "hint:")
    res = _cli("serve", "--rig", str(path), "--data-root", str(tmp_path / "d"), "--port", "0")
    assert res.returncode == EXIT_UNREACHABLE
    _one_line(res, "stage", "/dev/ttyNOPE9", "missing port")


def test_busy_port(tmp_path):
    config = load_rig(_rig(tmp_path, rig_text(homing="switches")))
    with SimServer(config) as srv:
        served = _rig(tmp_path, srv.rig_toml(), "served.toml")
        stage = next(d for d in srv.devices if d.name == "stage")
        with serial.Serial(stage.path, 115200, exclusive=True):  # another program holds the port
            err = _open_error(served)
    assert err.cause == "port busy" and err.device == "stage" and err.exit_code == EXIT_UNREACHABLE
    assert f"fuser -v {stage.path}" in err.hint


def test_a_zaber_where_the_grbl_was_expected(tmp_path):
    text = rig_text(homing="switches").replace("timeout_s = 1.0", "timeout_s = 0.2")
    config = load_rig(_rig(tmp_path, text))
    with SimServer(config) as srv, PtyServer(ZaberSimulator("intruder", srv.clock)) as zaber:
        served = srv.rig_toml().replace(next(d.path for d in srv.devices if d.name == "stage"), zaber.path)
        err = _open_error(_rig(tmp_path, served, "served.toml"))
    assert err.cause == "wrong device" and err.exit_code == EXIT_UNUSABLE
    assert "a Zaber ASCII device answers where the rig file expects GRBL" in str(err)
    assert err.port == zaber.path


def test_a_grbl_where_the_zaber_was_expected(tmp_path):
    text = rig_text(homing="switches").replace('protocol = "grbl"', 'protocol = "zaber"')
    text = text.replace('axis = "X"', 'axis = "1"').replace('axis = "Y"', 'axis = "2"')
    text = text.replace("timeout_s = 1.0", "timeout_s = 0.2")
    text = text.split("[simulation.devices.stage]")[0]  # no GRBL options for a Zaber device
    config = load_rig(_rig(tmp_path, text))
    with SimServer(config) as srv, PtyServer(GrblSimulator("intruder", srv.clock)) as grbl:
        served = srv.rig_toml().replace(next(d.path for d in srv.devices if d.name == "stage"), grbl.path)
        err = _open_error(_rig(tmp_path, served, "served.toml"))
    assert err.cause == "wrong device"
    assert "a GRBL device answers where the rig file expects Zaber" in str(err)


def test_identify_port_tells_the_protocols_apart():
    with PtyServer(ZaberSimulator("z", SYSTEM_CLOCK)) as z, PtyServer(GrblSimulator("g", SYSTEM_CLOCK)) as g:
        assert identify_port(z.path, 115200) == "Zaber ASCII"
        assert identify_port(g.path, 115200) == "GRBL"
    assert identify_port("/dev/ttyNOPE9", 115200) is None


@pytest.mark.slow
def test_controller_in_alarm_through_the_cli(tmp_path):
    # Homing enabled on the controller ($22=1: it boots locked) but the rig file says no switches.
    config = load_rig(_rig(tmp_path, rig_text(homing="none", switches_in_sim=True)))
    with SimServer(config) as srv:
        served = _rig(tmp_path, srv.rig_toml(), "served.toml")
        res = _cli("--rig", str(served), "--out", str(tmp_path / "s"), "--sat", "hubble", "--build", "B2",
                   "--light", "weak", entry="capture_main")
    assert res.returncode == EXIT_UNUSABLE
    _one_line(res, "stage", "alarm", "$22=1", "hint:")


def _usb_camera_rig(tmp_path: Path) -> Path:
    return _rig(tmp_path, rig_text(homing="switches").replace('port = "sim://toucan"', 'port = "usb://"'))


def test_no_usb_backend(tmp_path, monkeypatch):
    import usb.backend.libusb0
    import usb.backend.libusb1
    import usb.backend.openusb

    for mod in (usb.backend.libusb1, usb.backend.libusb0, usb.backend.openusb):
        monkeypatch.setattr(mod, "get_backend", lambda *a, **k: None)  # a machine without libusb
    err = _open_error(_usb_camera_rig(tmp_path))
    assert (err.device, err.cause, err.exit_code) == ("camera", "no USB backend", EXIT_UNREACHABLE)
    assert "libusb" in err.hint


def test_no_camera(tmp_path):
    import usb.backend.libusb1

    if usb.backend.libusb1.get_backend() is None:
        pytest.skip("libusb is not installed here (the no-backend case is tested above)")
    err = _open_error(_usb_camera_rig(tmp_path))
    assert (err.device, err.port, err.cause) == ("camera", "usb://", "no camera")
    assert "lsusb" in err.hint


def test_permission_denied(tmp_path):
    """A port the user may not open (not in the dialout group). Root may open anything, so as root
    the open runs in a child process that has dropped to ``nobody``."""
    from m2s2hil.rig.open_errors import explain  # noqa: F401  (loaded before the fork)

    config = load_rig(_rig(tmp_path, rig_text(homing="switches")))
    with SimServer(config) as srv:
        served = load_rig(_rig(tmp_path, srv.rig_toml(), "served.toml"))
        path = next(d.path for d in srv.devices if d.name == "stage")
        os.chmod(path, 0o600)
        read_fd, write_fd = os.pipe()
        pid = os.fork()
        if pid == 0:  # child: no pytest machinery, report through the pipe and leave
            try:
                if os.geteuid() == 0:
                    os.setgid(65534)
                    os.setuid(65534)
                try:
                    open_rig(served)
                    msg = "opened"
                except RigOpenError as exc:
                    msg = f"{exc.cause}|{exc.exit_code}|{exc}"
                except BaseException as exc:
                    msg = f"unexpected {type(exc).__name__}: {exc}"
                os.write(write_fd, msg.encode())
            finally:
                os._exit(0)
        os.close(write_fd)
        os.waitpid(pid, 0)
        msg = os.read(read_fd, 4096).decode()
        os.close(read_fd)
    cause, code, text = msg.split("|", 2)
    assert cause == "permission denied" and int(code) == EXIT_UNREACHABLE, msg
    assert "dialout" in text and path in text


@pytest.mark.slow  # waits out the reply timeouts: ~2 s
def test_nothing_answers(tmp_path):
    """A port that exists but where nothing listens (a powered-off controller)."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        text = rig_text(homing="switches").replace("timeout_s = 1.0", "timeout_s = 0.2")
        text = text.replace('port = "sim://stage"', f'port = "{os.ttyname(slave)}"')
        err = _open_error(_rig(tmp_path, text))
    finally:
        os.close(master)
        os.close(slave)
    assert (err.device, err.cause, err.exit_code) == ("stage", "no answer", EXIT_UNREACHABLE)
    assert "baud rate" in err.hint

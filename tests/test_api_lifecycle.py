"""The daemon as a process: SIGTERM mid-session parks it safely, a restart with --resume finishes it
with exactly the planned frames."""

from __future__ import annotations

import signal
import subprocess
import sys
from importlib import resources

import pytest
from api_support import DaemonProcess, free_port, quick_rig_file

from m2s2hil.daemon.rootlock import RootLocked, lock_data_root
from m2s2hil.rig.open_errors import EXIT_UNREACHABLE
from m2s2hil.store.session import SessionStore


@pytest.mark.slow  # two daemon processes in real time: ~25 s
@pytest.mark.timeout(600)  # generous: a loaded machine stretches it, it does not fail it
def test_sigterm_parks_safely_and_a_restart_resumes_to_exactly_the_plan(tmp_path) -> None:
    rig = quick_rig_file(tmp_path)
    sweep = {"satellite": "iss", "build": "B2", "lighting": ["weak"], "tilts": ["E1"], "azimuth_step_deg": 30,
             "dark": {"frames": 1}}
    d = DaemonProcess(tmp_path, rig)
    try:
        r = d.http.post("/sessions", json=sweep)
        assert r.status_code == 202
        sid = r.json()["session_id"]
        st = d.wait(sid, lambda s: s["done"] >= 3)  # the dark and two frames
        assert st["state"] == "running"
        log = d.stop(signal.SIGTERM)
    finally:
        if d.proc.poll() is None:
            d.proc.kill()
    assert "SIGTERM: no new sessions start; pausing the running one" in log
    assert f"session {sid} parked at a safe boundary and saved (interrupted)" in log
    assert "rig left safe: lamps off, motion stopped" in log
    assert log.rstrip().endswith("daemon stopped")  # devices closed after the server stopped

    store = SessionStore.open(tmp_path / "data", sid)
    try:
        assert store.state == "interrupted"
        ev = [e for e in store.events() if e["kind"] == "interrupted"]
        assert len(ev) == 1 and ev[0]["payload"]["reason"] == "SIGTERM"
        assert ev[0]["payload"]["rig_safe"] is True and ev[0]["payload"]["lamps_on"] == []
        frames_then = len(store.frames())
        planned = {e.event_id for e in store.sweep.expand(store.rig) if e.kind == "frame"}
    finally:
        store.close()
    assert 2 <= frames_then < len(planned) == 12  # 12 frames: a loaded machine may be slow to stop

    d = DaemonProcess(tmp_path, rig, "--resume")
    try:
        st = d.wait(sid, lambda s: s["state"] in ("completed", "failed", "aborted"))
        assert st["state"] == "completed" and st["done"] == st["total"] == 13
        d.stop()
    finally:
        if d.proc.poll() is None:
            d.proc.kill()
    assert f"resuming 1 interrupted session(s): {sid}" in d.log.read_text()
    store = SessionStore.open(tmp_path / "data", sid)
    try:
        ids = [f.event_id for f in store.frames()]
        runs = [e for e in store.events() if e["kind"] == "run_started"]
        assert store.state == "completed"
    finally:
        store.close()
    assert sorted(ids) == sorted(planned) and len(ids) == 12  # every planned frame once, no duplicate
    assert len(runs) == 2 and runs[1]["payload"]["done_before"] == frames_then + 1  # + the dark


def test_one_daemon_per_data_root(tmp_path) -> None:
    first = lock_data_root(tmp_path / "data")
    try:
        with pytest.raises(RootLocked, match="another m2s2hil daemon is serving"):
            lock_data_root(tmp_path / "data")
    finally:
        first.close()
    lock_data_root(tmp_path / "data").close()  # free again once the first one let go


@pytest.mark.slow  # a daemon process: ~4 s
def test_serve_says_which_device_it_cannot_open(tmp_path) -> None:
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    rig = tmp_path / "rig.toml"
    rig.write_text(text.replace('port = "sim://stage"', f'port = "{tmp_path}/no-such-tty"'))
    p = subprocess.run([sys.executable, "-m", "m2s2hil.commands.serve", "--rig", str(rig), "--data-root",
                        str(tmp_path / "data"), "--port", str(free_port())],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == EXIT_UNREACHABLE  # documented in docs/rig-setup.md
    assert "error: cannot open stage" in p.stderr and "no-such-tty" in p.stderr and "missing port" in p.stderr
    assert "Traceback" not in p.stderr

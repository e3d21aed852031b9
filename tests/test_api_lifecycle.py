"""The daemon as a process: SIGTERM mid-session parks it safely, a restart with --resume finishes it
with exactly the planned frames."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from importlib import resources
from pathlib import Path

import httpx
import pytest
from api_support import free_port

from m2s2hil.api.rootlock import RootLocked, lock_data_root
from m2s2hil.config import load_rig
from m2s2hil.rig.open_errors import EXIT_UNREACHABLE
from m2s2hil.store.session import SessionStore


def _rig_file(tmp: Path) -> Path:
    """The built-in rig with a small sensor and a quicker turntable (a realtime session of ~5 s)."""
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    for old, new in (("width = 2048", "width = 256"), ("height = 2048", "height = 256"),
                     ("max_speed_dps = 60.0", "max_speed_dps = 180.0"),
                     ("accel_dps2 = 120.0", "accel_dps2 = 720.0")):
        assert old in text
        text = text.replace(old, new)
    p = tmp / "rig.toml"
    p.write_text(text)
    load_rig(p)  # still a valid rig
    return p


class _Daemon:
    def __init__(self, tmp: Path, rig: Path, *extra: str) -> None:
        self.port = free_port()
        self.log = tmp / f"daemon-{self.port}.log"
        env = {k: v for k, v in os.environ.items() if k not in ("M2S2HIL_TOKEN", "M2S2HIL_DATA")}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "m2s2hil.commands.serve", "--rig", str(rig),
             "--data-root", str(tmp / "data"), "--host", "127.0.0.1", "--port", str(self.port), "--realtime",
             *extra],
            stdout=subprocess.DEVNULL, stderr=self.log.open("w"), env=env,
        )
        self.http = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=10)
        deadline = time.monotonic() + 60
        while True:
            assert self.proc.poll() is None, f"daemon exited early:\n{self.log.read_text()}"
            try:
                if self.http.get("/healthz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, f"daemon did not come up:\n{self.log.read_text()}"
            time.sleep(0.1)

    def wait(self, sid: str, pred, timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            st = self.http.get(f"/sessions/{sid}").json()
            if pred(st):
                return st
            assert time.monotonic() < deadline, f"timed out: {st}\n{self.log.read_text()}"
            time.sleep(0.05)

    def stop(self, sig: int = signal.SIGTERM) -> str:
        self.http.close()
        self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise
        log = self.log.read_text()
        assert rc == 0, f"exit code {rc}:\n{log}"
        return log


def test_sigterm_parks_safely_and_a_restart_resumes_to_exactly_the_plan(tmp_path) -> None:
    rig = _rig_file(tmp_path)
    sweep = {"satellite": "iss", "build": "B2", "lighting": ["weak"], "tilts": ["E1"], "azimuth_step_deg": 60,
             "dark": {"frames": 1}}
    d = _Daemon(tmp_path, rig)
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
    assert 2 <= frames_then < len(planned) == 6

    d = _Daemon(tmp_path, rig, "--resume")
    try:
        st = d.wait(sid, lambda s: s["state"] in ("completed", "failed", "aborted"))
        assert st["state"] == "completed" and st["done"] == st["total"] == 7
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
    assert sorted(ids) == sorted(planned) and len(ids) == 6  # every planned frame once, no duplicate
    assert len(runs) == 2 and runs[1]["payload"]["done_before"] == frames_then + 1  # + the dark


def test_one_daemon_per_data_root(tmp_path) -> None:
    first = lock_data_root(tmp_path / "data")
    try:
        with pytest.raises(RootLocked, match="another m2s2hil daemon is serving"):
            lock_data_root(tmp_path / "data")
    finally:
        first.close()
    lock_data_root(tmp_path / "data").close()  # free again once the first one let go


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

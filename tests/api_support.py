"""Shared helpers for the API tests (tests/test_api_*.py): a small simulated rig, a daemon
around it (in this process, or as a real ``serve`` process), sweeps, SSE parsing, waiting."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import httpx
from fastapi.testclient import TestClient

from m2s2hil.api import create_app
from m2s2hil.config import RigConfig, default_rig, load_rig, parse_rig
from m2s2hil.daemon.manager import SessionManager
from m2s2hil.rig.factory import open_simulated_rig

TOKEN = "s3cret-token-for-tests-0123456789"
TERMINAL = ("completed", "completed_with_gaps", "failed", "aborted", "cancelled", "estopped")


def small_rig_config(size: int = 256, **simulation: Any) -> RigConfig:
    """The built-in rig with a small sensor (fast frames) and a quicker turntable."""
    d = default_rig().model_dump(mode="json")
    d["camera"]["model"]["width"] = d["camera"]["model"]["height"] = size
    if simulation:
        d["simulation"] = {**d.get("simulation", {}), **simulation}
    return parse_rig(d, "test rig")


def sweep(**kw: Any) -> dict:
    """A short stop-and-go sweep as a JSON body: one lighting, one tilt, 4 azimuths, one dark frame."""
    base = {"satellite": "voyager", "build": "B3", "lighting": ["weak"], "tilts": ["E1"],
            "azimuth_step_deg": 90, "dark": {"frames": 1}}
    return {**base, **kw}


def long_sweep() -> dict:
    """Long enough (wall time, virtual clock) to act on while it runs: 3 tilts x 36 azimuths."""
    return sweep(tilts=["E0", "E1", "E2"], azimuth_step_deg=10)


@dataclass
class Daemon:
    rig: Any
    manager: SessionManager
    client: TestClient
    root: Path

    def wait(self, sid: str, pred: Callable[[dict], bool], timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            st = self.client.get(f"/sessions/{sid}").json()
            if pred(st):
                return st
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting on {sid}: last status {st}")
            time.sleep(0.01)

    def wait_state(self, sid: str, *states: str, timeout: float = 60.0) -> dict:
        return self.wait(sid, lambda st: st["state"] in states, timeout)

    def wait_done(self, sid: str, timeout: float = 60.0) -> dict:
        return self.wait_state(sid, *TERMINAL, timeout=timeout)


@contextlib.contextmanager
def daemon(root: Path, *, token: str | None = None, rig_config: RigConfig | None = None,
           faults: dict | None = None, start: bool = True, **manager_kw: Any) -> Iterator[Daemon]:
    """A manager on a fresh simulated rig (virtual clock) and a TestClient on its app; everything
    is aborted, made safe and closed afterwards."""
    app_kw = {k: manager_kw.pop(k) for k in ("cors_origins", "allowed_hosts", "max_body_bytes")
              if k in manager_kw}
    rig = open_simulated_rig(rig_config or small_rig_config(), faults=faults)
    try:
        mgr = SessionManager(rig, root, **manager_kw)
        if start:
            mgr.start()
        app = create_app(mgr, token=token, **app_kw)
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        headers["X-M2S2HIL"] = "1"  # a script, not a web page (see m2s2hil/api/guards/csrf.py)
        with TestClient(app, base_url="http://127.0.0.1:8750", headers=headers) as client:
            yield Daemon(rig, mgr, client, root)
        mgr.close(abort=True, timeout=30)
    finally:
        rig.close()


def parse_sse(text: str) -> list[dict]:
    """Server-Sent Events text -> [{"id":…, "event":…, "data":…}] (comments and pings dropped)."""
    out: list[dict] = []
    cur: dict = {}
    for line in text.splitlines():
        if not line:
            if cur:
                out.append(cur)
                cur = {}
            continue
        if line.startswith(":"):
            continue
        key, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if key == "data":
            cur["data"] = cur.get("data", "") + value
        else:
            cur[key] = value
    if cur:
        out.append(cur)
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def uvicorn_thread(app: Any) -> Iterator[str]:
    """Serve ``app`` on 127.0.0.1 in a thread (for real streaming); yields the base URL."""
    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                           lifespan="off"))
    t = threading.Thread(target=server.run, daemon=True)
    t.start()
    deadline = time.monotonic() + 20
    while not server.started:
        if time.monotonic() > deadline or not t.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        t.join(timeout=10)


def quick_rig_file(tmp: Path) -> Path:
    """The built-in rig with a 64² sensor (the pixels are not these tests' point) and a quicker
    turntable (a realtime session of ~5 s)."""
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    for old, new in (("width = 2048", "width = 64"), ("height = 2048", "height = 64"),
                     ("max_speed_dps = 60.0", "max_speed_dps = 180.0"),
                     ("accel_dps2 = 120.0", "accel_dps2 = 720.0")):
        assert old in text
        text = text.replace(old, new)
    p = tmp / "rig.toml"
    p.write_text(text)
    load_rig(p)  # still a valid rig
    return p


class DaemonProcess:
    """``python -m m2s2hil.commands.serve`` on ``tmp/data`` (real clock), up once /healthz answers;
    its log (stderr) in ``tmp/daemon-<port>.log``."""

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
        self.http = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=10,
                                 headers={"X-M2S2HIL": "1"})
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

    def wait(self, sid: str, pred: Callable[[dict], bool], timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            st = self.http.get(f"/sessions/{sid}").json()
            if pred(st):
                return st
            assert time.monotonic() < deadline, f"timed out: {st}\n{self.log.read_text()}"
            time.sleep(0.05)

    def stop(self, sig: int = signal.SIGTERM) -> str:
        """Signal it, wait for exit code 0; returns its log."""
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

    def kill(self) -> None:
        """``kill -9``: no shutdown of any kind."""
        self.http.close()
        self.proc.kill()
        self.proc.wait(timeout=30)

    def __enter__(self) -> DaemonProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=30)

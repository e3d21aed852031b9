"""The daemon under soak as a real ``m2s2hil serve`` process (virtual clock, token on, loopback),
the HTTP client the soak talks to it with, and what /proc says about the process."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import httpx

TOKEN = "soak-token-0123456789abcdef"  # >= 16 characters, as the daemon demands off loopback too
START_TIMEOUT_S = 90.0  # a loaded 2-core machine: imports, the rig's homing


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def write_rig_file(work: Path, size: int) -> Path:
    """The built-in simulated rig with a ``size``×``size`` sensor; its motion as shipped (a slow
    turntable is simulated time that costs no wall time)."""
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    for key in ("width", "height"):
        old = f"{key} = 2048"
        if old not in text:
            raise RuntimeError(f"soak: the built-in rig no longer says {old!r}; update write_rig_file")
        text = text.replace(old, f"{key} = {size}")
    path = work / "rig.toml"
    path.write_text(text)
    return path


def write_serve_file(work: Path, rig: Path, seed: int) -> Path:
    """The daemon's settings: the rig, the data root, a virtual clock, the simulated rig's seed."""
    path = work / "serve.toml"
    path.write_text(f'[serve]\nrig = "{rig.name}"\ndata_root = "data"\nhost = "127.0.0.1"\n'
                    f"realtime = false\nseed = {int(seed)}\n")
    return path


@dataclass(frozen=True)
class Sample:
    incarnation: int
    wall_s: float  # since the soak started
    rss_kib: int
    fds: int
    other_fds: int  # descriptors that are not a session journal's (SQLite's file, -wal, -shm)
    journals: int  # sessions whose journal the daemon holds open
    threads: int
    idle: bool  # no session running, no stream or export of ours open
    waiting: int = 0  # sessions queued at the time


@dataclass(frozen=True)
class ProcFigures:
    rss_kib: int
    fds: int
    other_fds: int
    journals: int
    threads: int


def proc_sample(pid: int) -> ProcFigures | None:
    """RSS, open file descriptors (and how many session journals they hold open), threads of
    ``pid`` from /proc; None once it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        names = os.listdir(f"/proc/{pid}/fd")
        targets = []
        for n in names:
            with contextlib.suppress(OSError):  # closed meanwhile
                targets.append(os.readlink(f"/proc/{pid}/fd/{n}"))
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    journal = [t for t in targets if t.endswith(("/journal.sqlite", "/journal.sqlite-wal",
                                                 "/journal.sqlite-shm"))]
    folders = {t.rsplit("/", 1)[0] for t in journal}
    return ProcFigures(int(fields["VmRSS"].split()[0]), len(names), len(names) - len(journal), len(folders),
                       int(fields["Threads"]))


@dataclass
class Traffic:
    """Every answer the soak got, by route and status; the 5xx ones kept whole."""

    by_route: Counter[tuple[str, str, int]] = field(default_factory=Counter)
    server_errors: list[str] = field(default_factory=list)
    cut: int = 0  # transport errors (the daemon being killed, a stream cut by a restart)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def note(self, method: str, route: str, r: httpx.Response | None) -> None:
        with self.lock:
            if r is None:
                self.cut += 1
                return
            self.by_route[(method, route, r.status_code)] += 1
            if r.status_code >= 500:
                self.server_errors.append(f"{method} {route} -> {r.status_code}: {r.text[:300]}")

    @property
    def requests(self) -> int:
        return sum(self.by_route.values()) + self.cut


def client(port: int, timeout: float = 30.0) -> httpx.Client:
    """A client as a script is one to the daemon: the bearer token and ``X-M2S2HIL: 1`` (not a web
    page: no ``Origin``), loopback only."""
    return httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=timeout, trust_env=False,
                        headers={"Authorization": f"Bearer {TOKEN}", "X-M2S2HIL": "1"})


class Daemon:
    """One incarnation of ``python -m m2s2hil.commands.serve``; up once /healthz answers."""

    def __init__(self, work: Path, serve_file: Path, incarnation: int, *, resume: bool) -> None:
        self.incarnation = incarnation
        self.port = free_port()
        self.log_path = work / f"daemon-{incarnation}.log"
        env = {k: v for k, v in os.environ.items() if k not in ("M2S2HIL_DATA",)}
        env["M2S2HIL_TOKEN"] = TOKEN
        argv = [sys.executable, "-m", "m2s2hil.commands.serve", "--config", str(serve_file),
                "--port", str(self.port), "--virtual-clock", "--resume" if resume else "--no-resume"]
        with self.log_path.open("w") as log:
            self.proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=log, env=env)
        self.pid = self.proc.pid
        self.http = client(self.port)
        t0 = time.monotonic()
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"soak: daemon {incarnation} exited with {self.proc.returncode} "
                                   f"at start:\n{self.log()[-2000:]}")
            try:
                if self.http.get("/healthz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() - t0 > START_TIMEOUT_S:
                self.kill9()
                raise RuntimeError(f"soak: daemon {incarnation} not up in {START_TIMEOUT_S:g} s:\n"
                                   f"{self.log()[-2000:]}")
            time.sleep(0.1)
        self.start_s = time.monotonic() - t0

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.proc.poll() is None

    def sample(self) -> ProcFigures | None:
        return proc_sample(self.pid) if self.alive() else None

    def kill9(self) -> None:
        """``kill -9``: no shutdown of any kind; returns once the process is gone."""
        self.http.close()
        if self.alive():
            os.kill(self.pid, signal.SIGKILL)
        self.proc.wait(timeout=60)

    def terminate(self, timeout: float = 120.0) -> int:
        """SIGTERM (a graceful stop: the running session parked, the rig left safe); its exit code."""
        self.http.close()
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill9()
            return -9


def get_json(http: httpx.Client, traffic: Traffic, route: str, path: str, **kw: Any) -> Any:
    """GET ``path``: its JSON on 200, None otherwise (noted in ``traffic`` either way)."""
    try:
        r = http.get(path, **kw)
    except httpx.TransportError:
        traffic.note("GET", route, None)
        return None
    traffic.note("GET", route, r)
    return r.json() if r.status_code == 200 else None


def post(http: httpx.Client, traffic: Traffic, route: str, path: str, **kw: Any) -> httpx.Response | None:
    try:
        r = http.post(path, **kw)
    except httpx.TransportError:
        traffic.note("POST", route, None)
        return None
    traffic.note("POST", route, r)
    return r

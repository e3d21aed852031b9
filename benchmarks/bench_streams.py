"""The daemon under many clients: ``/healthz`` and ``/rig/stop`` latency while 300 SSE subscribers,
60 live-view viewers and 200 slow clients (one header byte a second) hold connections.

Loopback only, bounded: it starts ``m2s2hil serve`` (the built-in simulated rig with a 256²
sensor, real clock) on a free port in a temporary folder, opens the clients, probes for
``--seconds`` (each probe a new connection, as a monitor would), then closes every client,
checks that the daemon counts no viewer and no subscriber any more, and stops the daemon.

    python benchmarks/bench_streams.py [--sse 300] [--viewers 60] [--slow 200] [--seconds 20]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

from m2s2hil.hostinfo import describe_machine

HOST = "127.0.0.1"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return int(s.getsockname()[1])


def _rig_file(tmp: Path) -> Path:
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    text = text.replace("width = 2048", "width = 256").replace("height = 2048", "height = 256")
    p = tmp / "rig.toml"
    p.write_text(text)
    return p


async def _request(port: int, method: str, path: str, body: bytes = b"") -> tuple[int, bytes]:
    reader, writer = await asyncio.open_connection(HOST, port)
    head = (f"{method} {path} HTTP/1.1\r\nHost: {HOST}:{port}\r\nX-M2S2HIL: 1\r\nConnection: close\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n")
    writer.write(head.encode() + body)
    await writer.drain()
    data = await reader.read()
    writer.close()
    status = int(data.split(b" ", 2)[1]) if data.startswith(b"HTTP/") else 0
    return status, data.partition(b"\r\n\r\n")[2]


async def _stream(port: int, path: str, opened: list[int], stop: asyncio.Event) -> None:
    """A client that reads a stream (and discards it) until told to stop."""
    reader, writer = await asyncio.open_connection(HOST, port)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: {HOST}:{port}\r\n\r\n".encode())
    await writer.drain()
    first = await reader.read(4096)
    opened.append(int(first.split(b" ", 2)[1]) if first.startswith(b"HTTP/") else 0)
    while not stop.is_set():
        try:
            if not await asyncio.wait_for(reader.read(65536), 0.5):
                break
        except TimeoutError:
            continue
    writer.close()


async def _slow(port: int, stop: asyncio.Event, dropped: list[int]) -> None:
    """Slowloris: a request line, then one header byte a second, never the end of the headers;
    dropped by the server, it connects again (the pressure stays)."""
    while not stop.is_set():
        reader, writer = await asyncio.open_connection(HOST, port)
        writer.write(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        try:
            while not stop.is_set():
                await writer.drain()
                writer.write(b"a")
                try:
                    await asyncio.wait_for(reader.read(1024), 1.0)  # b"" or the 408: dropped
                    dropped.append(1)
                    break
                except TimeoutError:
                    continue
        except (ConnectionError, OSError):
            dropped.append(1)
        finally:
            writer.close()


def _pct(values: list[float], q: float) -> float:
    values = sorted(values)
    return values[min(len(values) - 1, round(q * (len(values) - 1)))]


async def _run(port: int, args: argparse.Namespace) -> dict:
    status, body = await _request(port, "POST", "/queue/hold?reason=bench")
    assert status == 200, body
    sweep = {"satellite": "voyager", "build": "B3", "lighting": ["weak"], "tilts": ["E1"],
             "azimuth_step_deg": 90}
    status, body = await _request(port, "POST", "/sessions", json.dumps(sweep).encode())
    assert status == 202, body
    sid = json.loads(body)["session_id"]  # queued behind the hold: its event stream stays open
    stop = asyncio.Event()
    sse_open: list[int] = []
    live_open: list[int] = []
    slow_dropped: list[int] = []
    events, live = f"/sessions/{sid}/events", "/camera/live.mjpeg"
    tasks = [asyncio.create_task(_stream(port, events, sse_open, stop)) for _ in range(args.sse)]
    tasks += [asyncio.create_task(_stream(port, live, live_open, stop)) for _ in range(args.viewers)]
    tasks += [asyncio.create_task(_slow(port, stop, slow_dropped)) for _ in range(args.slow)]
    t_open = time.monotonic()
    while len(sse_open) + len(live_open) < args.sse + args.viewers and time.monotonic() - t_open < 60:
        await asyncio.sleep(0.1)
    opened_s = time.monotonic() - t_open
    _, live_body = await _request(port, "GET", "/camera/live")
    counted = json.loads(live_body)["viewers"]
    health: list[float] = []
    stops: list[float] = []
    end = time.monotonic() + args.seconds
    n = 0
    while time.monotonic() < end:
        t0 = time.perf_counter()
        status, _ = await _request(port, "GET", "/healthz")
        health.append(1e3 * (time.perf_counter() - t0))
        assert status == 200, status
        if n % 5 == 0:
            t0 = time.perf_counter()
            status, _ = await _request(port, "POST", "/rig/stop", b"{}")
            stops.append(1e3 * (time.perf_counter() - t0))
            assert status == 200, status
        n += 1
        await asyncio.sleep(0.05)
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)
    t_leave = time.monotonic()
    while True:  # the daemon sees every client go
        _, live_body = await _request(port, "GET", "/camera/live")
        left = json.loads(live_body)["viewers"]
        if left == 0 or time.monotonic() - t_leave > 30:
            break
        await asyncio.sleep(0.1)
    return {"sse_200": sse_open.count(200), "live_200": live_open.count(200), "viewers_counted": counted,
            "open_s": opened_s, "slow_dropped_by_end": len(slow_dropped), "viewers_after_leaving": left,
            "healthz_n": len(health), "healthz_p50": _pct(health, 0.5), "healthz_p99": _pct(health, 0.99),
            "healthz_max": max(health), "stop_n": len(stops), "stop_p50": _pct(stops, 0.5),
            "stop_p99": _pct(stops, 0.99), "stop_max": max(stops), "healthz_mean": statistics.fmean(health)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sse", type=int, default=300)
    ap.add_argument("--viewers", type=int, default=60)
    ap.add_argument("--slow", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-streams-") as tmp:
        tmpdir = Path(tmp)
        port = _free_port()
        env = {k: v for k, v in os.environ.items() if k not in ("M2S2HIL_TOKEN", "M2S2HIL_DATA")}
        log = (tmpdir / "daemon.log").open("w")
        proc = subprocess.Popen([sys.executable, "-m", "m2s2hil.commands.serve", "--rig",
                                 str(_rig_file(tmpdir)), "--data-root", str(tmpdir / "data"), "--host", HOST,
                                 "--port", str(port)], stdout=subprocess.DEVNULL, stderr=log, env=env)
        try:
            deadline = time.monotonic() + 60
            while True:
                up = proc.poll() is None and time.monotonic() < deadline
                assert up, (tmpdir / "daemon.log").read_text()
                try:
                    if asyncio.run(_request(port, "GET", "/healthz"))[0] == 200:
                        break
                except OSError:
                    time.sleep(0.2)
            res = asyncio.run(_run(port, args))
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
    print(describe_machine())
    print(f"clients: {args.sse} SSE ({res['sse_200']} answered 200), {args.viewers} live viewers "
          f"({res['live_200']} answered 200; the daemon counted {res['viewers_counted']}), {args.slow} slow "
          f"header clients; all open after {res['open_s']:.1f} s")
    for key, name in (("healthz", "/healthz "), ("stop", "/rig/stop")):
        print(f"{name} n={res[key + '_n']}  p50 {res[key + '_p50']:.1f} ms  p99 {res[key + '_p99']:.1f} ms  "
              f"max {res[key + '_max']:.1f} ms")
    print(f"slow header clients dropped by the server (and reconnected): {res['slow_dropped_by_end']}; "
          f"viewers counted after every client left: {res['viewers_after_leaving']}")


if __name__ == "__main__":
    main()

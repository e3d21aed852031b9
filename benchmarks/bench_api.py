"""Latency of ``GET /sessions/{id}`` while a 65 frames/s continuous capture runs.

Starts ``m2s2hil serve`` in a subprocess on 127.0.0.1 (simulated rig, real clock), queues a
continuous-rotation session (the camera streams at its 65 frames/s maximum), waits until the
stream runs, then hammers the status endpoint from a local load generator (httpx clients in
threads, keep-alive, bounded in time and count) and reports p50/p95/p99/max. Afterwards it
reads the session's journal: frames the camera streamed during the passes and block ids that
never arrived (dropped). An idle baseline (no session) is measured first.

    .venv/bin/python benchmarks/bench_api.py [--size 1024] [--rate 100] [--clients 2] \\
        [--saturate 4] [--record]

``--record`` writes the result under "## REST API" in docs/benchmarks.md. Only 127.0.0.1 is
ever contacted.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from importlib import resources
from pathlib import Path

import httpx

from m2s2hil.hostinfo import describe_machine

ROOT = Path(__file__).resolve().parent.parent
MAX_REQUESTS = 200_000  # per run, whatever the duration


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rig_toml(size: int, tmp: Path) -> Path:
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    text = text.replace("width = 2048", f"width = {size}").replace("height = 2048", f"height = {size}")
    p = tmp / "rig.toml"
    p.write_text(text)
    return p


def percentile(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))]


def hammer(base: str, path: str, *, rate: float | None, clients: int,
           until: Callable[[], bool]) -> tuple[list[float], int]:
    """Load from ``clients`` keep-alive clients until ``until()`` says stop (checked between requests).

    ``rate``: total requests per second, open loop (each client sends on its own schedule and
    does not wait longer when the server is slow; a send that is already late goes out at once
    and is counted); ``None``: closed loop, each client sends again as soon as it has its answer
    (saturation). Returns (latencies in seconds, late sends)."""
    lat: list[list[float]] = [[] for _ in range(clients)]
    late = [0] * clients
    per_client = MAX_REQUESTS // max(1, clients)
    errors: list[str] = []
    period = clients / rate if rate else 0.0

    def run(i: int) -> None:
        with httpx.Client(base_url=base, timeout=5) as c:
            t_next = time.perf_counter() + i * period / clients
            while not until() and len(lat[i]) < per_client:
                if period:
                    wait = t_next - time.perf_counter()
                    if wait > 0:
                        time.sleep(wait)
                    else:
                        late[i] += wait < -period
                    t_next += period
                t0 = time.perf_counter()
                r = c.get(path)
                dt = time.perf_counter() - t0
                if r.status_code != 200:
                    errors.append(f"{r.status_code} {r.text[:200]}")
                    return
                lat[i].append(dt)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    while not threads and not until():  # no load: just wait (the control run)
        time.sleep(0.05)
    for t in threads:
        t.join()
    if errors:
        raise RuntimeError(f"load generator got errors: {errors[:3]}")
    return [x for xs in lat for x in xs], sum(late)


def timer(seconds: float) -> Callable[[], bool]:
    end = time.monotonic() + seconds
    return lambda: time.monotonic() >= end


def summary(lat: list[float], duration: float) -> dict:
    ms = [x * 1e3 for x in lat]
    if not ms:
        return {"requests": 0, "rps": 0.0, "p50_ms": None, "p95_ms": None, "p99_ms": None, "max_ms": None,
                "mean_ms": None}
    return {"requests": len(ms), "rps": len(ms) / duration, "p50_ms": percentile(ms, 50),
            "p95_ms": percentile(ms, 95), "p99_ms": percentile(ms, 99), "max_ms": max(ms),
            "mean_ms": statistics.fmean(ms)}


SWEEP = {"satellite": "voyager", "build": "B3", "lighting": ["strong"], "tilts": ["E0", "E1", "E2"],
         "azimuth_step_deg": 10, "mode": "continuous", "dark": {"frames": 2}}
TERMINAL = ("completed", "failed", "aborted")


def capture_run(http: httpx.Client, base: str, data: Path, *, rate: float | None, clients: int,
                max_s: float) -> dict:
    """One continuous session (3 passes) with the load on from its first pass to its end."""
    sid = http.post("/sessions", json=SWEEP).json()["session_id"]
    while True:
        st = http.get(f"/sessions/{sid}").json()
        if st["state"] in TERMINAL:
            raise RuntimeError(f"session ended before the load: {st}")
        if st["state"] == "running" and st["done"] >= 1:  # the master dark is stored: passes next
            break
        time.sleep(0.05)
    finished = threading.Event()

    def watch() -> None:
        with httpx.Client(base_url=base, timeout=10) as w:
            end = time.monotonic() + max_s
            while time.monotonic() < end:
                if w.get(f"/sessions/{sid}").json()["state"] in TERMINAL:
                    break
                time.sleep(0.25)
            else:
                w.post(f"/sessions/{sid}/abort", headers={"X-M2S2HIL": "1"})  # see docs/security.md
        finished.set()

    watcher = threading.Thread(target=watch)
    watcher.start()
    t0 = time.monotonic()
    lat, late = hammer(base, f"/sessions/{sid}", rate=rate, clients=clients, until=finished.is_set)
    window = time.monotonic() - t0
    watcher.join()
    while (st := http.get(f"/sessions/{sid}").json())["state"] not in TERMINAL:
        time.sleep(0.1)
    from m2s2hil.store.session import SessionStore

    store = SessionStore.open(data, sid)
    try:
        passes = [e["payload"] for e in store.events() if e["kind"] == "continuous_pass"]
        faults = [e["payload"] for e in store.events() if e["kind"] == "fault"]
        kept = len(store.frames())
    finally:
        store.close()
    read = sum(p.get("frames_read", 0) for p in passes)
    dur = sum(p.get("duration_s", 0.0) for p in passes)
    return {"session_id": sid, "state": st["state"], "load": summary(lat, window), "late_sends": late,
            "rate": rate, "clients": clients, "window_s": window, "passes": len(passes),
            "frames_streamed": read, "stream_fps": read / dur if dur else None,
            "dropped": sum(p.get("dropped", 0) for p in passes), "kept": kept, "planned": st["total"] - 1,
            "faults": len(faults)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1024, help="simulated sensor width = height (px)")
    ap.add_argument("--rate", type=float, default=100.0, help="open-loop requests per second (all clients)")
    ap.add_argument("--clients", type=int, default=2, help="keep-alive clients for the open-loop run")
    ap.add_argument("--saturate", type=int, default=4,
                    help="closed-loop clients for a saturation run (0: skip)")
    ap.add_argument("--repeat", type=int, default=1, help="open-loop capture runs (the machine is noisy)")
    ap.add_argument("--no-control", action="store_true", help="skip the run without API load")
    ap.add_argument("--max-duration", type=float, default=120.0, help="abort a session still running then")
    ap.add_argument("--record", action="store_true", help="write the result into docs/benchmarks.md")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="bench-api-"))
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    env = {k: v for k, v in os.environ.items() if k not in ("M2S2HIL_TOKEN", "M2S2HIL_DATA")}
    log = (tmp / "daemon.log").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "m2s2hil.commands.serve", "--rig", str(rig_toml(args.size, tmp)),
         "--data-root", str(tmp / "data"), "--host", "127.0.0.1", "--port", str(port), "--realtime",
         "--log-level", "warning"], stdout=subprocess.DEVNULL, stderr=log, env=env,
    )
    try:
        http = httpx.Client(base_url=base, timeout=10)
        deadline = time.monotonic() + 60
        while True:
            try:
                if http.get("/healthz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("daemon did not start; see " + str(tmp / "daemon.log"))
            time.sleep(0.2)

        # idle baseline: the status of a finished tiny session, nothing capturing
        idle_sid = http.post("/sessions", json={"satellite": "voyager", "build": "B3", "lighting": ["weak"],
                                                "tilts": ["E1"], "azimuth_step_deg": 180,
                                                "dark": {"frames": 1}}).json()["session_id"]
        while http.get(f"/sessions/{idle_sid}").json()["state"] not in TERMINAL:
            time.sleep(0.2)
        lat, late = hammer(base, f"/sessions/{idle_sid}", rate=args.rate, clients=args.clients,
                           until=timer(5.0))
        idle = {"load": summary(lat, 5.0), "late_sends": late}
        runs = [] if args.no_control else [
            capture_run(http, base, tmp / "data", rate=None, clients=0, max_s=args.max_duration)]
        runs += [capture_run(http, base, tmp / "data", rate=args.rate, clients=args.clients,
                             max_s=args.max_duration) for _ in range(args.repeat)]
        if args.saturate:
            runs.append(capture_run(http, base, tmp / "data", rate=None, clients=args.saturate,
                                    max_s=args.max_duration))
        http.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
    result = {"size": args.size, "idle": idle, "runs": runs,
              "machine": describe_machine(),
              "load_average": os.getloadavg()}
    print(json.dumps(result, indent=2))
    if args.record:
        record(result, args)
    return 0


def _row(name: str, r: dict) -> str:
    x = r["load"]
    return (f"| {name} | {x['requests']} | {x['rps']:.0f} | {x['p50_ms']:.2f} ms | {x['p95_ms']:.2f} ms | "
            f"{x['p99_ms']:.2f} ms | {x['max_ms']:.1f} ms |")


def _capture(name: str, r: dict) -> str:
    return (f"| {name} | {r['state']} | {r['passes']} | {r['frames_streamed']} | **{r['dropped']}** | "
            f"{r['kept']}/{r['planned']} | {r['faults']} | {r['window_s']:.0f} s |")


def record(res: dict, args: argparse.Namespace) -> None:
    runs = res["runs"]
    names = [] if args.no_control else ["control: no API load"]
    names += [f"open loop, {args.rate:g} req/s, {args.clients} clients"
              + (f" (run {i + 1})" if args.repeat > 1 else "") for i in range(args.repeat)]
    if args.saturate:
        names.append(f"closed loop (saturation), {args.saturate} clients")
    loaded = [(n, r) for n, r in zip(names, runs, strict=True) if r["clients"]]
    lat_rows = "\n".join([_row("idle daemon, open loop (5 s)", res["idle"])]
                         + [_row(f"capturing: {n}", r) for n, r in loaded])
    cap_rows = "\n".join(_capture(n, r) for n, r in zip(names, runs, strict=True))
    la = ", ".join(f"{x:.1f}" for x in res["load_average"])
    worst_p99 = max(r["load"]["p99_ms"] for _, r in loaded)
    verdict_p99 = "below 20 ms" if worst_p99 < 20 else "NOT below 20 ms"
    drops_loaded = ", ".join(f"{r['dropped']}" for _, r in loaded) + " of ~1270 streamed"
    drops_control = ", ".join(f"{r['dropped']}" for r in runs if not r["clients"]) or "n/a"
    clean = sum(r["dropped"] == 0 for _, r in loaded)
    stored = "all" if all(r["kept"] == r["planned"] for r in runs) else "NOT all"
    stored += " stored, no pass retried" if all(r["faults"] == 0 for r in runs) else " stored; faults met"
    section = f"""## REST API

`GET /sessions/{{id}}` latency while a continuous-rotation session streams from the simulated
TOUCAN at its 65 frames/s maximum. Command: `benchmarks/bench_api.py --size {res['size']}
--rate {args.rate:g} --clients {args.clients} --repeat {args.repeat} --saturate {args.saturate}`.
The daemon (`m2s2hil serve`, simulated rig on a real clock) runs in one process, the load
generator (keep-alive httpx clients in threads) in another, 127.0.0.1 only. Each capture run
is one session of 3 continuous passes (strong light, E0/E1/E2, 36 marks each; the camera
streams at 65 frames/s during a pass, ~420 frames a pass); the load runs from the first pass
to the end of the session; the control run has no API load. Latency is measured at the
client, send to complete response. "Dropped" counts block ids that never arrived; a pass with
a gap is retried (a fault), so "passes" can exceed 3.

| load | requests | req/s | p50 | p95 | p99 | max |
|---|---|---|---|---|---|---|
{lat_rows}

| capture run | state | passes | frames streamed | dropped | frames stored | faults | duration |
|---|---|---|---|---|---|---|---|
{cap_rows}

**Result:** p99 {verdict_p99} in every loaded run (worst {worst_p99:.1f} ms; goal < 20 ms).
Frames dropped: {drops_loaded} in the loaded runs, {drops_control} in the control, so the
no-drop goal held in {clean} of {len(loaded)} loaded runs; every azimuth mark still got its frame
({stored}). The load generator shares the two cores with the daemon (and so do the other
engineers' jobs).

Simulated sensor {res['size']}×{res['size']} px. Rendering the scene in real time is the
simulator's cost, not the API's: on this machine a bare 2048×2048 stream (no engine, no API)
reached ~54 frames/s with blocks dropped, and at 1024×1024 the daemon dropped frames in the
control run too (no API load) whenever the machine was busy.

Machine: {res['machine']}, shared with other engineers' builds and test
runs while this ran (load average {la} at the end), so the figures are noisy; rerun on an
idle machine for a clean baseline. Date: 2026-11-24.
"""
    path = ROOT / "docs" / "benchmarks.md"
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    start = text.find("## REST API")
    if start >= 0:
        end = text.find("\n## ", start + 1)
        text = text[:start] + section + (text[end + 1:] if end >= 0 else "")
    else:
        text = text.rstrip("\n") + "\n\n" + section
    path.write_text(text)
    print(f"recorded in {path}")


if __name__ == "__main__":
    raise SystemExit(main())

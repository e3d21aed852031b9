"""Operator console: live-view frame rate and latency in a real browser, the daemon's CPU cost while
streaming, and the documentation's screenshots.

Starts ``m2s2hil serve`` on the built-in simulated rig (2048² sensor, real clock) in a subprocess,
opens the console in headless Chromium (Debian's package, through playwright), streams the live view
for ``--seconds`` and records, per frame drawn in the browser: the frame rate and the latency from
the frame reaching the daemon's memory to its pixels drawn on the page's canvas (both clocks are the
same machine's wall clock). The daemon's CPU is read with psutil over the same window. With
``--screenshots DIR`` it then takes a screenshot of every view (a short session is run for the
sessions and browser views).

    .venv/bin/python benchmarks/bench_console.py --seconds 20 --screenshots docs/images
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from browser_support import CHROMIUM_ARGS, chromium_path, start_session_from_form

from m2s2hil.hostinfo import describe_machine

HEADERS = {"X-M2S2HIL": "1"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_up(base: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if httpx.get(base + "/healthz", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError("daemon did not start")


def measure(page, proc: psutil.Process, seconds: float, exposure_ms: float, base: str = "") -> dict:
    page.fill("#live-exposure", str(exposure_ms))
    page.dispatch_event("#live-exposure", "change")
    page.click("#live-toggle")
    page.wait_for_function("window.m2s2hilLive && window.m2s2hilLive.frames >= 5", timeout=60000)
    page.evaluate("""() => { window.m2s2hilSamples = []; const f = window.__m2s2hilHook = () => {
        const l = window.m2s2hilLive; if (l && (!window.m2s2hilSamples.length ||
          window.m2s2hilSamples[window.m2s2hilSamples.length - 1].seq !== l.seq))
          window.m2s2hilSamples.push({seq: l.seq, t: performance.now(), latency: l.latency_ms});
        requestAnimationFrame(f); }; requestAnimationFrame(f); }""")
    proc.cpu_percent(None)
    cpu_t0 = time.monotonic()
    time.sleep(seconds)
    cpu = proc.cpu_percent(None)
    elapsed = time.monotonic() - cpu_t0
    samples = page.evaluate("window.m2s2hilSamples")
    live = httpx.get(base + "/camera/live", headers=HEADERS).json() if base else {}
    page.click("#live-toggle")
    lat = sorted(s["latency"] for s in samples)
    span_s = (samples[-1]["t"] - samples[0]["t"]) / 1000 if len(samples) > 1 else float("nan")
    return {"frames": len(samples), "window_s": round(elapsed, 1),
            "fps": round((len(samples) - 1) / span_s, 1) if len(samples) > 1 else 0.0,
            "latency_ms_median": round(statistics.median(lat), 1) if lat else None,
            "latency_ms_p95": round(lat[int(0.95 * (len(lat) - 1))], 1) if lat else None,
            "daemon_cpu_percent": round(cpu, 1), "exposure_ms": exposure_ms,
            # what the stream asks of the camera, what the daemon produced, the first frame's wait
            "stream_fps": live.get("stream_fps"), "daemon_fps": live.get("fps"),
            "cold_start_s": live.get("cold_start_s"),
            # the last frame's: render, grab (exposure wait, readout, transfer, decode), time it waited
            # in the camera's buffer (beyond the quickest frame), frames grabbed but never rendered
            **{k: (live.get("stats") or {}).get(k) for k in ("render_ms", "grab_ms", "waited_ms", "dropped")},
            "load_average": [round(x, 2) for x in os.getloadavg()]}


def screenshots(page, base: str, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    httpx.put(base + "/rig/lamps", json={"preset": "strong"}, headers=HEADERS)
    page.fill("#live-exposure", "6")
    page.dispatch_event("#live-exposure", "change")
    page.click("#live-toggle")
    page.wait_for_function("window.m2s2hilLive && window.m2s2hilLive.frames >= 5", timeout=60000)
    page.screenshot(path=str(out / "console_setup.png"))
    page.click("#live-toggle")
    httpx.put(base + "/rig/lamps", json={"preset": None}, headers=HEADERS)
    page.click("#tabs button[data-view='sessions']")
    page.select_option("#f-sat", "voyager")
    page.dispatch_event("#f-sat", "change")
    page.select_option("#f-build", "B3")
    start_session_from_form(page, tilts=("E1",), step_deg=45, frames=8)
    page.wait_for_function("document.querySelectorAll('#run-sheet img[src^=\"blob:\"]').length >= 3",
                           timeout=120000)
    page.screenshot(path=str(out / "console_sessions.png"))
    page.wait_for_function("document.getElementById('run-state').textContent === 'completed'", timeout=180000)
    sid = page.inner_text("#run-id")
    page.click("#tabs button[data-view='browser']")
    page.locator("#sessions-table tbody tr", has_text=sid).click()
    page.click("#b-verify")
    page.wait_for_function("document.getElementById('b-result').textContent.startsWith('verified')",
                           timeout=60000)
    page.wait_for_function("document.querySelectorAll('#b-sheet img[src^=\"blob:\"]').length === 8")
    page.screenshot(path=str(out / "console_browser.png"))
    page.click("#tabs button[data-view='calibration']")
    page.select_option("#w-light", "strong")
    page.fill("#w-exposure", "4")
    page.fill("#w-frames", "4")
    page.click("#white-form button[type=submit]")
    page.wait_for_function("!['', 'capturing…'].includes(document.getElementById('w-result').textContent)",
                           timeout=120000)
    httpx.put(base + "/rig/lamps", json={"preset": "strong"}, headers=HEADERS)  # a lit, coloured scene
    page.fill("#p-exposure", "6")
    page.click("#phase-form button[type=submit]")
    page.wait_for_function("document.getElementById('p-result').textContent.length > 0", timeout=60000)
    page.screenshot(path=str(out / "console_calibration.png"))
    # the emergency stop during a session
    start_session_from_form(page, tilts=("E1",), step_deg=10)
    page.wait_for_function("document.getElementById('run-state').textContent === 'running'", timeout=60000)
    time.sleep(3)
    page.keyboard.press("Escape")
    page.wait_for_function("document.getElementById('banner').textContent.includes('EMERGENCY STOP')")
    page.wait_for_function("document.getElementById('run-state').textContent === 'estopped'", timeout=60000)
    page.screenshot(path=str(out / "console_estop.png"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--exposure-ms", type=float, nargs="*", default=[5.0, 20.0])
    ap.add_argument("--screenshots", type=Path, default=None)
    args = ap.parse_args()
    exe = chromium_path()
    if exe is None:
        sys.exit("no chromium on PATH")
    from playwright.sync_api import sync_playwright

    port = free_port()
    base = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as data:
        env = {**os.environ, "M2S2HIL_DATA": data}
        daemon = subprocess.Popen([sys.executable, "-m", "m2s2hil.commands.serve", "--port", str(port),
                                   "--data-root", data], env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        try:
            wait_up(base)
            proc = psutil.Process(daemon.pid)
            httpx.put(base + "/rig/lamps", json={"preset": "weak"}, headers=HEADERS)
            with sync_playwright() as p:
                b = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS, headless=True)
                page = b.new_page(viewport={"width": 1400, "height": 1000}, bypass_csp=True)
                page.goto(base + "/")
                page.wait_for_function("document.getElementById('rig-status').textContent.includes('idle')")
                rows = [measure(page, proc, args.seconds, e, base) for e in args.exposure_ms]
                if args.screenshots is not None:
                    screenshots(page, base, args.screenshots)
                b.close()
        finally:
            daemon.terminate()
            daemon.wait(timeout=60)
    print(json.dumps({"machine": describe_machine(), "date": time.strftime("%Y-%m-%d"),
                      "sensor": "2048x2048 simulated TOUCAN, real clock", "rows": rows}, indent=2))


if __name__ == "__main__":
    main()

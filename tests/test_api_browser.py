"""A web page on another origin cannot drive the rig: headless Chromium (Debian's package,
driven by playwright) loads a page from a second local server that tries every
state-changing endpoint of the daemon every way a page can without the daemon's consent
(fetch in no-cors mode, text/plain and form bodies, form posts of every encoding, a
custom header, a JSON body). Each request that reaches the daemon is refused with 403, and
the rig, the queue and the session read back unchanged through GET /rig and GET /queue."""

from __future__ import annotations

import contextlib
import http.server
import json
import re
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from api_support import daemon, free_port, sweep, uvicorn_thread

from m2s2hil.api.guards.csrf import STATE_CHANGING

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]  # a browser and two servers: about 5 s

ATTACK_JS = """
async function attack(base, targets, sweep) {
  const tries = [];
  for (const [method, path] of targets) {
    const url = base + path;
    const simple = method === "POST";  // no-cors allows GET, HEAD and POST only
    tries.push(fetch(url, {method, mode: "no-cors"}));
    tries.push(fetch(url, {method, mode: "no-cors", headers: {"Content-Type": "text/plain"}, body: sweep}));
    tries.push(fetch(url, {method, mode: "no-cors", headers: {"X-M2S2HIL": "1"}}));  // the header is dropped
    tries.push(fetch(url, {method, mode: "no-cors", body: new URLSearchParams({a: "1"})}));
    tries.push(fetch(url, {method, headers: {"X-M2S2HIL": "1"}}));  // needs a preflight: refused
    tries.push(fetch(url, {method, headers: {"Content-Type": "application/json"}, body: sweep}));
    if (!simple) continue;
    for (const enctype of ["application/x-www-form-urlencoded", "multipart/form-data", "text/plain"]) {
      const frame = document.createElement("iframe");
      frame.name = "f" + Math.random().toString(36).slice(2);
      document.body.appendChild(frame);
      const form = document.createElement("form");
      Object.assign(form, {method: "POST", action: url, target: frame.name, enctype});
      const input = document.createElement("input");
      // text/plain sends name=value: a JSON body a lenient parser would accept
      Object.assign(input, {type: "hidden", name: sweep.slice(0, -1) + ', "x": "', value: '"}'});
      form.appendChild(input);
      document.body.appendChild(form);
      tries.push(new Promise(done => { frame.onload = done; setTimeout(done, 5000); form.submit(); }));
    }
  }
  await Promise.allSettled(tries);
  document.title = "done";
}
"""


class Recorder:
    """ASGI wrapper: every request the daemon receives, with the status it answered."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self.seen: list[dict[str, Any]] = []

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status: dict[str, int] = {}

        async def recording_send(msg: Any) -> None:
            if msg["type"] == "http.response.start":
                status["code"] = msg["status"]
            await send(msg)

        await self.app(scope, receive, recording_send)
        headers = {k.decode(): v.decode("latin-1") for k, v in scope["headers"]}
        self.seen.append({"method": scope["method"], "path": scope["path"], "origin": headers.get("origin"),
                          "content_type": headers.get("content-type"), "status": status.get("code")})


@contextlib.contextmanager
def attacker_site(page_html: str) -> Iterator[str]:
    """The other origin: a second tiny HTTP server on another port of 127.0.0.1."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = page_html.encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: Any) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", free_port()), Handler)
    t = threading.Thread(target=server.serve_forever, daemon=True)
    t.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def _targets(app: Any, sid: str) -> list[tuple[str, str]]:
    """Every state-changing (method, path) the application documents, path parameters filled in."""
    out = []
    for path, item in app.openapi()["paths"].items():
        for method in sorted({m.upper() for m in item} & STATE_CHANGING):
            out.append((method, re.sub(r"\{[^}]+\}", "turntable", path.replace("{session_id}", sid))))
    return out


def _observable(d: Any, sid: str) -> dict[str, Any]:
    rig = d.client.get("/rig").json()
    devices = {dev["name"]: dev["state"] for dev in rig["devices"]}
    queue = d.client.get("/queue").json()
    return {"devices": devices, "held": queue["held"], "queued": [e["session_id"] for e in queue["items"]],
            "session": d.client.get(f"/sessions/{sid}").json()["state"]}


def test_a_page_on_another_origin_cannot_change_anything(tmp_path, new_page) -> None:
    with daemon(tmp_path / "data") as d:
        # The situation the attack aims at: an emergency stop held the queue, a session waits.
        assert d.client.post("/rig/stop").status_code == 200
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        before = _observable(d, sid)
        assert before["held"] and before["queued"] == [sid] and before["session"] == "queued"

        recorder = Recorder(d.client.app)
        targets = _targets(d.client.app, sid)
        assert ("POST", "/rig/stop") in targets and ("POST", "/queue/release") in targets
        with uvicorn_thread(recorder) as base:
            page_html = (f"<!doctype html><title>cat pictures</title><body><script>{ATTACK_JS}"
                         f"attack({json.dumps(base)}, {json.dumps(targets)}, "
                         f"{json.dumps(json.dumps(sweep()))});</script></body>")
            with attacker_site(page_html) as evil:
                page = new_page()
                page.goto(evil + "/")
                page.wait_for_function("document.title === 'done'", timeout=90_000)
                page.close()

                # Control: the daemon's own origin may (the console's case).
                own = new_page()
                own.goto(base + "/healthz")
                status = own.evaluate(
                    "fetch('/queue/hold?reason=own-origin', {method: 'POST', headers: {'X-M2S2HIL': '1'}})"
                    ".then(r => r.status)")
                own.close()

        attacks = [r for r in recorder.seen if r["origin"] == evil and r["method"] in STATE_CHANGING]
        posts = sum(m == "POST" for m, _ in targets)
        # Every no-cors fetch and form post of every POST endpoint arrived (so the browser did send
        # them) and got 403; the preflighted ones never left the browser.
        assert len(attacks) >= 7 * posts, recorder.seen
        assert {r["status"] for r in attacks} == {403}, [r for r in attacks if r["status"] != 403]
        assert {r["content_type"].split(";")[0] for r in attacks if r["content_type"]} <= {
            "text/plain", "application/x-www-form-urlencoded", "multipart/form-data"}
        assert status == 200  # the same-origin request went through
        after = _observable(d, sid)
        assert after == {**before, "held": "own-origin"}, (before, after)

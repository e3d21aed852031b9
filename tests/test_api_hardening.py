"""Issue 13's defences, request by request: the Host allow-list, the cross-site guard, free
text made safe for the log, cheap plan checks before the expensive expansion, and /healthz
answering while large plans are expanded."""

from __future__ import annotations

import itertools
import json
import logging
import threading

import httpx
import pytest
from api_support import daemon, sweep, uvicorn_thread

from m2s2hil.api.guards.csrf import normalise_origin
from m2s2hil.api.guards.hosts import split_host
from m2s2hil.api.guards.logsafe import clean_text
from m2s2hil.api.settings import load_serve_settings
from m2s2hil.atomic import DiskFull
from m2s2hil.daemon import admission
from m2s2hil.errors import ConfigError
from m2s2hil.plan import Sweep

EVIL = "https://evil.example"


@pytest.fixture
def d(tmp_path):
    with daemon(tmp_path / "data", allowed_hosts=["rig-pc.lab"],
                cors_origins=["https://ops.example.org"]) as dm:
        yield dm


# ---------------------------------------------------------------------- Host
def test_loopback_and_configured_hosts_are_served(d) -> None:
    for host in ("127.0.0.1:8750", "127.0.0.1", "localhost:1", "LOCALHOST.", "[::1]:8750", "rig-pc.lab:8750",
                 "Rig-PC.lab"):
        assert d.client.get("/healthz", headers={"Host": host}).status_code == 200, host


def test_other_hosts_get_421_and_are_not_reflected(d) -> None:
    for host, method, path in itertools.product(
            ("attacker.example", "attacker.example:8750", "127.0.0.1.nip.io", "10.0.0.5", "",
             "localhost:99999", "::1", "a b", "localhost@evil"),
            ("GET", "POST"), ("/healthz", "/sessions", "/rig/stop")):
        r = d.client.request(method, path, headers={"Host": host})
        assert r.status_code == 421, (host, path, r.text)
        assert r.headers["content-type"] == "application/json"
        assert "does not serve" in r.json()["detail"]
        if host:
            assert host not in r.text
    assert d.manager.held is None  # the refused emergency stop did nothing


def test_urls_are_relative_whatever_the_host(d) -> None:
    r = d.client.post("/sessions", json=sweep(), headers={"Host": "rig-pc.lab:8750"})
    assert r.status_code == 202
    sid = r.json()["session_id"]
    assert r.headers["location"] == r.json()["url"] == f"/sessions/{sid}"
    assert "rig-pc" not in r.text


def test_host_names_come_from_settings_and_the_listen_address(tmp_path) -> None:
    s = load_serve_settings(None, env={}, host="10.0.0.5", allowed_hosts=["rig-pc.lab", "[fd00::5]"])
    assert s.host_names() == ["rig-pc.lab", "[fd00::5]", "10.0.0.5"]
    assert load_serve_settings(None, env={}, host="0.0.0.0").host_names() == []
    with pytest.raises(ConfigError, match=r"serve\.allowed_hosts.*not a host name"):
        load_serve_settings(None, env={}, allowed_hosts=["http://x/"])
    with pytest.raises(ConfigError, match=r"serve\.cors_origins.*not an origin"):
        load_serve_settings(None, env={}, cors_origins=["ops.example.org"])
    assert split_host("[::1]:80") == ("::1", 80) and split_host("x:1:2") is None


# ---------------------------------------------------------------------- cross-site
STATE_CHANGES = [("POST", "/rig/stop"), ("POST", "/queue/release"), ("POST", "/queue/hold?reason=x"),
                 ("POST", "/sessions/any-id/abort"), ("POST", "/sessions/any-id/pause"),
                 ("POST", "/sessions/any-id/resume")]


def test_a_foreign_origin_cannot_change_state(d) -> None:
    for origin in (EVIL, "null", "http://127.0.0.1:9999", "http://localhost", "https://127.0.0.1:8750",
                   "garbage"):
        for method, path in STATE_CHANGES:
            r = d.client.request(method, path, headers={"Origin": origin})  # with X-M2S2HIL: 1
            assert r.status_code == 403, r.text
            assert "not an allowed origin" in r.json()["detail"]
        r = d.client.post("/sessions", json=sweep(), headers={"Origin": origin})
        assert r.status_code == 403
    assert d.manager.held is None and d.manager.queue()["items"] == []


def test_without_json_or_the_header_nothing_changes(d) -> None:
    for ctype in (None, "text/plain", "application/x-www-form-urlencoded", "multipart/form-data"):
        headers = {"X-M2S2HIL": ""} | ({"Content-Type": ctype} if ctype else {})
        for method, path in STATE_CHANGES:
            r = d.client.request(method, path, headers=headers)
            assert r.status_code == 403 and "X-M2S2HIL: 1" in r.json()["detail"], (path, r.text)
        r = d.client.post("/sessions", content=json.dumps(sweep()), headers=headers)
        assert r.status_code == 403
    assert d.manager.held is None and d.manager.queue()["items"] == []


def test_own_and_configured_origins_and_plain_scripts_may(d) -> None:
    for origin in ("http://127.0.0.1:8750", "http://localhost:8750", "http://[::1]:8750",
                   "https://ops.example.org"):
        r = d.client.post("/queue/hold", params={"reason": "ok"}, headers={"Origin": origin})
        assert r.status_code == 200
    assert d.client.post("/queue/release", headers={"Content-Type": "application/json"}).status_code == 200
    r = d.client.post("/sessions", json=sweep(), headers={"X-M2S2HIL": ""})  # JSON alone suffices
    assert r.status_code == 202
    assert d.client.get("/sessions", headers={"Origin": EVIL}).status_code == 200  # reading is not refused
    # (a browser does not let the page read it: no CORS header for that origin)
    assert "access-control-allow-origin" not in d.client.get("/sessions", headers={"Origin": EVIL}).headers


def test_two_origins_are_refused_whichever_comes_first(d) -> None:
    own = "http://127.0.0.1:8750"
    for first, second in ((own, EVIL), (EVIL, own), (own, own)):
        headers = [("Origin", first), ("Origin", second), ("X-M2S2HIL", "1")]
        for method, path in STATE_CHANGES:
            r = d.client.request(method, path, headers=headers)
            assert r.status_code == 403 and "more than one Origin" in r.json()["detail"], (path, r.text)
    assert d.manager.held is None
    assert d.client.get("/healthz", headers=[("Origin", own), ("Origin", EVIL)]).status_code == 200


def test_a_trailing_dot_is_the_same_host_for_host_and_origin(d) -> None:
    for host, origin in (("localhost.:8750", "http://localhost.:8750"), ("localhost.:8750", "http://localhost:8750"),
                         ("localhost:8750", "http://localhost.:8750"), ("rig-pc.lab.:8750", "http://rig-pc.lab.:8750")):
        r = d.client.post("/queue/hold", params={"reason": "swap"}, headers={"Host": host, "Origin": origin})
        assert r.status_code == 200, (host, origin, r.text)
    r = d.client.post("/queue/hold", headers={"Host": "localhost.:8750", "Origin": "http://localhost.:9999"})
    assert r.status_code == 403  # the port still counts
    assert normalise_origin("http://LocalHost.:8750") == "http://localhost:8750"
    assert normalise_origin("http://.:8750") is None


def test_origin_normalisation() -> None:
    assert normalise_origin("HTTP://LocalHost:80") == "http://localhost"
    assert normalise_origin("http://[::1]:8750/") == "http://[::1]:8750"
    for bad in ("null", "file:///x", "http://a/b", "http://u@a", "http://a:99999", ""):
        assert normalise_origin(bad) is None


# ---------------------------------------------------------------------- log and journal text
def test_clean_text_escapes_controls_and_limits_length() -> None:
    assert clean_text("a\nb\r\x00\x1b[31m\u2028\u202e\tz\\") == "a\\nb\\r\\x00\\x1b[31m\\u2028\\u202e\\tz\\\\"
    assert clean_text("ok: ümlaut ✓") == "ok: ümlaut ✓"
    long = clean_text("x" * 500, 50)
    assert len(long) == 50 and long.endswith("…")
    assert len(clean_text("\x00" * 100, 40)) == 40


def test_a_hold_reason_cannot_forge_a_log_line(d, caplog) -> None:
    forged = "swap\n2026-12-01 10:00:00 INFO m2s2hil.serve: rig left safe: lamps off\x00"
    handler_out: list[str] = []

    class Lines(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            handler_out.append(self.format(record))

    h = Lines()
    logging.getLogger().addHandler(h)
    try:
        with caplog.at_level(logging.INFO):
            r = d.client.post("/queue/hold", params={"reason": forged})
    finally:
        logging.getLogger().removeHandler(h)
    assert r.status_code == 200
    held = r.json()["held"]
    assert "\n" not in held and "\x00" not in held and "\\n2026-12-01" in held
    logged = [line for line in handler_out if "queue held" in line]
    assert logged, handler_out
    assert all("\n" not in line and "\x00" not in line for line in handler_out)
    lines = "\n".join(handler_out).splitlines()
    assert not any(line.startswith("2026-12-01 10:00:00 INFO") for line in lines)
    too_long = d.client.post("/queue/hold", params={"reason": "x" * 201})
    assert too_long.status_code == 422


# ---------------------------------------------------------------------- plans: cheap checks first
def test_disk_check_comes_before_the_expansion_and_does_not_say_resume(d, monkeypatch) -> None:
    def full(path, need):
        raise DiskFull(path, needed=need, free=1000)

    def never(self, rig):
        raise AssertionError("the plan was expanded before the disk check")

    monkeypatch.setattr(admission, "check_free_space", full)
    monkeypatch.setattr(Sweep, "expand", never)
    r = d.client.post("/sessions", json=sweep(azimuth_step_deg=0.5, frames_per_pose=3))
    assert r.status_code == 507, r.text
    detail = r.json()["detail"]
    assert "no session was created" in detail and "resume" not in detail
    assert d.client.get("/sessions").json()["total"] == 0


def test_frame_limit_is_computed_without_expanding(d, monkeypatch) -> None:
    monkeypatch.setattr(Sweep, "expand", lambda self, rig: pytest.fail("expanded"))
    body = sweep(lighting=["weak", "strong", "directional"], tilts=["E0", "E1", "E2"], azimuth_step_deg=0.05,
                 frames_per_pose=2)
    r = d.client.post("/sessions", json=body)
    assert r.status_code == 422 and "asks for 129600 frames" in r.json()["detail"]


def test_published_lighting_names_are_accepted(d) -> None:
    s = Sweep(satellite="voyager", build="B3", lighting=["solo", "ALL", "Dir"])
    assert s.lighting == ["weak", "strong", "directional"]
    r = d.client.post("/sessions", json=sweep(lighting=["solo"], exposure={"all": 0.01}))
    assert r.status_code == 202, r.text


def test_a_queued_answer_has_its_position(d) -> None:
    d.client.post("/queue/hold")
    for i in range(3):
        body = d.client.post("/sessions", json=sweep(azimuth_start_deg=i)).json()
        assert body["state"] == "queued" and body["queue_position"] == i + 1


@pytest.mark.slow  # four plan expansions of ~0.5 s each
def test_healthz_answers_while_large_plans_are_expanded(tmp_path) -> None:
    """Four large plans submitted at once (each expansion scores ~100 orders of 6480 frames):
    /healthz keeps answering before they are all done."""
    with daemon(tmp_path / "data") as d, uvicorn_thread(d.client.app) as base:
        d.client.post("/queue/hold")  # they stay queued: only admission is measured
        done: list[int] = []

        def submit(i: int) -> None:
            body = sweep(tilts=["E0", "E1", "E2"], azimuth_step_deg=0.5, frames_per_pose=3,
                         azimuth_start_deg=0.1 * (i + 1))  # distinct plans: no cache hit
            with httpx.Client(base_url=base, timeout=120) as c:
                done.append(c.post("/sessions", json=body).status_code)

        threads = [threading.Thread(target=submit, args=(i,)) for i in range(4)]
        for t in threads:
            t.start()
        answered_meanwhile = 0
        with httpx.Client(base_url=base, timeout=60) as c:
            while len(done) < 4:
                r = c.get("/healthz")
                assert r.status_code == 200
                if len(done) < 4:
                    answered_meanwhile += 1
        for t in threads:
            t.join(120)
        assert done == [202] * 4
        assert answered_meanwhile >= 2, "healthz did not answer while the plans were expanded"


def test_unreadable_bodies_get_400_naming_why(d) -> None:
    json_type = {"Content-Type": "application/json"}
    r = d.client.post("/sessions", content=b'{"satellite": "voyager",', headers=json_type)
    assert r.status_code == 400 and r.json()["detail"].startswith("body: malformed JSON at character")
    big = b'{"satellite": "voyager", "build": "B3", "gain": ' + b"9" * 5000 + b"}"
    r = d.client.post("/sessions", content=big, headers=json_type)
    assert r.status_code == 400 and "too many digits" in r.json()["detail"]
    r = d.client.post("/sessions", content=b'{"satellite": "\xff"}', headers=json_type)
    assert r.status_code == 400 and "UTF-8" in r.json()["detail"]


def test_methods_a_path_lacks_get_405_with_all_it_has(d) -> None:
    r = d.client.options("/sessions")
    assert r.status_code == 405 and r.headers["allow"] == "GET, POST"
    r = d.client.delete("/rig/stop")  # a method no route has: 405, not the cross-site 403
    assert r.status_code == 405 and r.headers["allow"] == "POST"


def test_cross_origin_websockets_are_refused() -> None:
    """The console may add WebSockets, which CORS does not cover: the guard closes a
    handshake from a foreign Origin before it is accepted."""
    from starlette.applications import Starlette
    from starlette.routing import WebSocketRoute
    from starlette.testclient import TestClient
    from starlette.websockets import WebSocket, WebSocketDisconnect

    from m2s2hil.api.guards.csrf import CrossSiteGuard

    async def echo(ws: WebSocket) -> None:
        await ws.accept()
        await ws.send_text("hello")
        await ws.close()

    app = Starlette(routes=[WebSocketRoute("/ws", echo)])
    app.add_middleware(CrossSiteGuard)
    with TestClient(app, base_url="http://127.0.0.1:8750") as c:
        with c.websocket_connect("ws://127.0.0.1:8750/ws", headers={"Origin": "http://127.0.0.1:8750"}) as ws:
            assert ws.receive_text() == "hello"
        with pytest.raises(WebSocketDisconnect) as info, \
                c.websocket_connect("ws://127.0.0.1:8750/ws", headers={"Origin": EVIL}) as ws:
            ws.receive_text()
        assert info.value.code == 1008

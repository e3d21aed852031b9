"""Listening rules, bearer tokens (constant-time), body size limit, CORS, ids only (no paths)."""

from __future__ import annotations

import os
import secrets
import subprocess
import sys

import pytest
from api_support import TOKEN, daemon, sweep

from m2s2hil.api.guards.security import InsecureListen, check_listen, is_loopback
from m2s2hil.api.settings import load_serve_settings
from m2s2hil.errors import ConfigError


@pytest.mark.parametrize(("host", "loop"), [
    ("127.0.0.1", True), ("127.8.9.10", True), ("::1", True), ("[::1]", True), ("localhost", True),
    ("0.0.0.0", False), ("::", False), ("192.168.1.20", False), ("rig.example.org", False), ("", False),
])
def test_loopback_addresses(host, loop) -> None:
    assert is_loopback(host) is loop


def test_off_loopback_needs_a_long_enough_token() -> None:
    check_listen("127.0.0.1", None)
    check_listen("0.0.0.0", TOKEN)
    with pytest.raises(InsecureListen, match=r"refusing to listen on '0\.0\.0\.0' without a bearer token.*"
                                             r"M2S2HIL_TOKEN"):
        check_listen("0.0.0.0", None)
    with pytest.raises(InsecureListen, match="needs at least 16"):
        check_listen("10.0.0.5", "short")
    with pytest.raises(InsecureListen, match="at least 16"):
        check_listen("127.0.0.1", "short")  # a configured token must be a real one anywhere


@pytest.mark.slow  # a real `m2s2hil serve` process
def test_serve_refuses_to_start_off_loopback_without_token(tmp_path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "M2S2HIL_TOKEN"}
    p = subprocess.run(
        [sys.executable, "-m", "m2s2hil.commands.serve", "--host", "0.0.0.0", "--port", "1",
         "--data-root", str(tmp_path / "d")],
        capture_output=True, text=True, timeout=60, env=env,
    )
    assert p.returncode == 2, p.stderr
    assert "refusing to listen on '0.0.0.0' without a bearer token" in p.stderr
    assert "Traceback" not in p.stderr
    assert not (tmp_path / "d").exists()  # refused before touching rig or data


def test_settings_precedence(tmp_path) -> None:
    f = tmp_path / "serve.toml"
    f.write_text('[serve]\nhost = "0.0.0.0"\nport = 9000\ntoken = "from-the-file-0123456789"\n'
                 'data_root = "data"\n')
    s = load_serve_settings(f, env={})
    assert (s.host, s.port, s.token_value(), s.data_root) == ("0.0.0.0", 9000, "from-the-file-0123456789",
                                                              tmp_path / "data")
    s = load_serve_settings(f, env={"M2S2HIL_TOKEN": TOKEN}, port=9001, host=None)
    assert (s.port, s.host, s.token_value()) == (9001, "0.0.0.0", TOKEN)
    assert TOKEN not in repr(s)  # the secret stays out of logs
    f.write_text("[serve]\nprot = 1\n")
    with pytest.raises(ConfigError, match=r"serve\.prot: unknown key"):
        load_serve_settings(f, env={})
    f.write_text("[daemon]\n")
    with pytest.raises(ConfigError, match="unknown table"):
        load_serve_settings(f, env={})


def test_token_rules_and_constant_time_comparison(tmp_path, monkeypatch) -> None:
    calls: list[tuple[bytes, bytes]] = []
    real = secrets.compare_digest

    def spy(a, b):
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(secrets, "compare_digest", spy)  # the constant-time comparison the check uses
    with daemon(tmp_path / "data", token=TOKEN) as d:
        c = d.client
        r = c.get("/sessions", headers={"Authorization": ""})
        assert r.status_code == 401 and "missing bearer token" in r.json()["detail"]
        assert r.headers["www-authenticate"].startswith("Bearer")
        r = c.get("/sessions", headers={"Authorization": f"Bearer {TOKEN[:-1]}x"})
        assert r.status_code == 401 and r.json()["detail"] == "invalid bearer token"
        assert calls[-1] == (f"{TOKEN[:-1]}x".encode(), TOKEN.encode())
        assert c.post("/rig/stop", headers={"Authorization": "Bearer nope"}).status_code == 401
        assert c.post("/sessions", json=sweep(), headers={"Authorization": "Basic abc"}).status_code == 401
        assert c.get("/sessions").status_code == 200  # the client's default header has the token
        assert calls[-1] == (TOKEN.encode(), TOKEN.encode())
        assert c.get("/metrics", headers={"Authorization": ""}).status_code == 401
        assert c.get("/healthz", headers={"Authorization": ""}).status_code == 200  # liveness stays open
        assert d.manager.held is None  # the refused emergency stop did nothing


def test_request_bodies_are_size_limited(tmp_path) -> None:
    with daemon(tmp_path / "data", max_body_bytes=2048) as d:
        big = {**sweep(), "pad": "x" * 5000}
        r = d.client.post("/sessions", json=big)
        assert r.status_code == 413 and "above the limit of 2048 bytes" in r.json()["detail"]

        def chunks():  # no Content-Length: counted as it arrives
            for _ in range(10):
                yield b" " * 1000

        r = d.client.post("/sessions", content=chunks(), headers={"content-type": "application/json"})
        assert r.status_code == 413
        assert d.client.post("/sessions", json=sweep()).status_code == 202  # small bodies pass


def test_cors_is_off_unless_configured(tmp_path) -> None:
    pre = {"Origin": "https://ops.example.org", "Access-Control-Request-Method": "GET"}
    with daemon(tmp_path / "a") as d:
        r = d.client.get("/sessions", headers={"Origin": "https://ops.example.org"})
        assert "access-control-allow-origin" not in r.headers
        assert "access-control-allow-origin" not in d.client.options("/sessions", headers=pre).headers
    with daemon(tmp_path / "b", cors_origins=["https://ops.example.org"]) as d:
        r = d.client.get("/sessions", headers={"Origin": "https://ops.example.org"})
        assert r.headers["access-control-allow-origin"] == "https://ops.example.org"
        r = d.client.get("/sessions", headers={"Origin": "https://evil.example.org"})
        assert "access-control-allow-origin" not in r.headers


@pytest.mark.parametrize("path", [
    "/sessions/..%2F..%2Fetc%2Fpasswd", "/sessions/%2E%2E", "/sessions/.journal", "/sessions/a%00b",
    "/sessions/..%2Fdata/frames/1/raw", "/sessions/x/frames/..%2F..%2Fjournal.sqlite/raw",
    "/sessions/%2Fetc%2Fpasswd/events",
])
def test_no_endpoint_takes_a_path(tmp_path, path) -> None:
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc" / "passwd").write_text("root:x:0:0")
    with daemon(tmp_path / "data") as d:
        r = d.client.get(path)
        assert r.status_code in (404, 422), (path, r.status_code, r.text)
        assert "root:x" not in r.text

"""Streams are counted by their real connections (m2s2hil.api.streams) and the server drops clients
that never finish their headers (m2s2hil.api.http_server), over real sockets on loopback:
a viewer that disconnects or half-closes is reaped, the camera stops after the last one, a
viewer or subscriber beyond the limit gets 503 with Retry-After, a slowloris client gets 408."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import httpx
import pytest
import uvicorn
from api_support import daemon, free_port, small_rig_config, sweep

from m2s2hil.api.http_server import server_limits
from m2s2hil.api.streams import StreamLimits, Streams

HEADERS = {"X-M2S2HIL": "1"}


@contextlib.contextmanager
def served(app: Any, **limits: Any) -> Iterator[int]:
    """``app`` on uvicorn (in a thread) with the daemon's server limits; yields the port."""
    kw = {"header_timeout_s": 10.0, "keep_alive_s": 5.0, "max_header_bytes": 16 * 1024,
          "max_connections": 1000, **limits}
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                           lifespan="off", **server_limits(**kw)))
    t = threading.Thread(target=server.run, daemon=True)
    t.start()
    deadline = time.monotonic() + 20
    while not server.started:
        assert time.monotonic() < deadline and t.is_alive(), "uvicorn did not start"
        time.sleep(0.02)
    try:
        yield port
    finally:
        server.should_exit = True
        t.join(timeout=15)


def wait_for(pred: Callable[[], bool], what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting until {what}"
        time.sleep(0.05)


def open_viewer(port: int) -> socket.socket:
    """A viewer on a raw socket, returned once the first part of the stream has arrived."""
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    s.sendall(b"GET /camera/live.mjpeg HTTP/1.1\r\nHost: 127.0.0.1:8750\r\n\r\n")
    got = b""
    while b"--m2s2hil-frame" not in got:
        chunk = s.recv(65536)
        assert chunk, f"the stream ended before its first part: {got[:200]!r}"
        got += chunk
    assert got.startswith(b"HTTP/1.1 200"), got[:200]
    return s


@pytest.fixture
def d(tmp_path):
    with daemon(tmp_path / "data", rig_config=small_rig_config(64)) as d:
        yield d


def _live(port: int) -> dict:
    return httpx.get(f"http://127.0.0.1:{port}/camera/live", headers=HEADERS, timeout=30).json()


def test_viewers_that_leave_are_reaped_and_the_camera_stops_after_the_last(d) -> None:
    with served(d.client.app) as port:
        viewers = [open_viewer(port) for _ in range(6)]
        assert _live(port)["viewers"] == 6
        camera = d.client.app.state.console.camera
        assert camera.streaming
        for s in viewers[:3]:
            s.close()  # gone
        for s in viewers[3:5]:
            s.shutdown(socket.SHUT_WR)  # half-closed: the server reads EOF
        wait_for(lambda: _live(port)["viewers"] == 1, "the five that left are no longer counted")
        assert camera.streaming  # one still watches
        viewers[5].close()
        wait_for(lambda: _live(port)["viewers"] == 0, "the last viewer is no longer counted")
        wait_for(lambda: not camera.streaming, "the camera stopped streaming")
        assert d.client.app.state.streams.live.count == 0
        for s in viewers[3:5]:
            s.close()


def test_a_viewer_beyond_the_limit_gets_503_with_retry_after(d) -> None:
    d.client.app.state.streams = Streams(StreamLimits(live_viewers=2, retry_after_s=7))
    with served(d.client.app) as port:
        first, second = open_viewer(port), open_viewer(port)
        r = httpx.get(f"http://127.0.0.1:{port}/camera/live.mjpeg", headers=HEADERS, timeout=30)
        assert r.status_code == 503, r.text
        assert r.headers["Retry-After"] == "7"
        assert "2 live-view viewers" in r.json()["detail"]
        first.close()
        wait_for(lambda: d.client.app.state.streams.live.count == 1, "the first viewer's slot is free")
        third = open_viewer(port)  # its place is taken again
        for s in (second, third):
            s.close()


def test_an_event_subscriber_beyond_the_limit_gets_503_and_its_slot_returns(d) -> None:
    d.client.app.state.streams = Streams(StreamLimits(sse_subscribers=1))
    assert d.client.post("/queue/hold", json={"reason": "test"}).status_code == 200
    sid = d.client.post("/sessions", json=sweep()).json()["session_id"]  # waits: the queue is held
    with served(d.client.app) as port, httpx.Client(base_url=f"http://127.0.0.1:{port}", headers=HEADERS,
                                                    timeout=30) as http:
        with http.stream("GET", f"/sessions/{sid}/events") as first:
            assert first.status_code == 200
            lines = first.iter_lines()  # kept: a dropped iterator closes the connection
            assert "queued" in next(lines)
            r = http.get(f"/sessions/{sid}/events")
            assert r.status_code == 503 and int(r.headers["Retry-After"]) > 0, r.text
        wait_for(lambda: d.client.app.state.streams.sse.count == 0, "the subscriber's slot is free")
        with http.stream("GET", f"/sessions/{sid}/events") as again:
            assert again.status_code == 200


def test_a_client_trickling_its_headers_is_dropped(d) -> None:
    with served(d.client.app, header_timeout_s=0.5) as port:
        s = socket.create_connection(("127.0.0.1", port), timeout=30)
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1:8750\r\n")
        got = b""
        for _ in range(300):  # one header byte every 50 ms, for at most 15 s
            try:
                s.sendall(b"X")
            except OSError:
                break  # closed by the server
            s.settimeout(0.05)
            try:
                chunk = s.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                break  # a reset: whatever came before it is in `got`
            if not chunk:
                break
            got += chunk
        s.close()
        assert got.startswith(b"HTTP/1.1 408"), got
        # A client that sends its headers in time is served as ever.
        assert httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=30).status_code == 200

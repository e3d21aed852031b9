"""The clients that stay connected: live-view viewers (``GET /camera/live.mjpeg``) and event
subscribers (``GET /sessions/{id}/events``). Each runs in its own thread with its own connection,
bounded in frames or events and in time; a subscriber's ``frame`` events are frames the daemon
has acknowledged as stored."""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field

import httpx

from .daemon import Traffic, client


@dataclass
class Acks:
    """Frames the daemon said were stored, by session (from event streams and frame lists)."""

    by_session: dict[str, set[str]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, sid: str, event_ids: set[str]) -> None:
        with self.lock:
            self.by_session.setdefault(sid, set()).update(event_ids)

    def total(self) -> int:
        with self.lock:
            return sum(len(v) for v in self.by_session.values())


class Stream(threading.Thread):
    """A bounded streaming GET; ``status`` is its answer's code (None: cut before one came)."""

    def __init__(self, port: int, traffic: Traffic, route: str, path: str, max_s: float) -> None:
        super().__init__(daemon=True, name=f"soak {route}")
        self.port, self.traffic, self.route, self.path, self.max_s = port, traffic, route, path, max_s
        self.status: int | None = None
        self.items = 0

    def run(self) -> None:
        deadline = time.monotonic() + self.max_s
        http = client(self.port, timeout=min(10.0, self.max_s))
        try:
            with http.stream("GET", self.path) as r:
                self.status = r.status_code
                self.traffic.note("GET", self.route, r)
                if r.status_code == 200:
                    self.consume(r, deadline)
        except (httpx.TransportError, httpx.StreamError):
            if self.status is None:
                self.traffic.note("GET", self.route, None)
        finally:
            http.close()

    def consume(self, r: httpx.Response, deadline: float) -> None:
        raise NotImplementedError


class LiveViewer(Stream):
    """Reads ``max_frames`` parts of the MJPEG live view (or until ``max_s``), then leaves."""

    def __init__(self, port: int, traffic: Traffic, max_frames: int, max_s: float) -> None:
        super().__init__(port, traffic, "/camera/live.mjpeg", f"/camera/live.mjpeg?max_frames={max_frames}",
                         max_s)

    def consume(self, r: httpx.Response, deadline: float) -> None:
        for chunk in r.iter_bytes():
            self.items += chunk.count(b"Content-Type: image/jpeg")
            if time.monotonic() > deadline:
                return


class EventWatcher(Stream):
    """Follows a session's events until ``finished``, the stream's end or ``max_s``; every
    ``frame`` event's ``event_id`` goes to ``acks``."""

    def __init__(self, port: int, traffic: Traffic, sid: str, acks: Acks, max_s: float) -> None:
        super().__init__(port, traffic, "/sessions/{id}/events", f"/sessions/{sid}/events", max_s)
        self.sid, self.acks = sid, acks

    def consume(self, r: httpx.Response, deadline: float) -> None:
        kind = ""
        for line in r.iter_lines():
            if line.startswith("event:"):
                kind = line[6:].strip()
            elif line.startswith("data:") and kind == "frame":
                self.items += 1
                self.acks.add(self.sid, {json.loads(line[5:])["event_id"]})
            elif line.startswith("data:") and kind == "finished":
                return
            if time.monotonic() > deadline:
                return

"""``GET /sessions/{id}/events``: the engine's events as Server-Sent Events.

Each message has ``event:`` = the event kind (``state``, ``progress``, ``frame``,
``fault``, ``finished``), ``data:`` = the event as JSON, and ``id:`` = ``<run>-<seq>``:
``seq`` is the engine's monotonically increasing sequence number, ``run`` counts the
engine runs of the session (a session resumed after a daemon restart is run 2, whose
``seq`` starts again at 1). A client that reconnects with ``Last-Event-ID`` gets every
event after that one still in the engine's history (:meth:`EventBus.since`); an id of an
earlier run replays the current run from its start; a plain integer is read as a
``seq`` of the current run. When the history no longer reaches back that far, a ``gap``
message (no id) says which sequence numbers are gone; the status endpoint has the totals.

A session queued behind another first gets a ``queued`` message (no id) and the stream
waits. A session no engine of this daemon knows (finished before it started) is replayed
from its journal (frames, faults, runs, the end) with ids ``j-<n>``, then the stream ends.
Messages without an id never move the client's Last-Event-ID.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

from m2s2hil.daemon.manager import SessionManager
from m2s2hil.engine.state import SessionFinished

POLL_S = 0.1


@dataclass(frozen=True)
class Cursor:
    run: int | None  # None: a journal replay id
    seq: int


def parse_last_event_id(value: str | None) -> Cursor | None:
    """``"3-17"`` → run 3 seq 17; ``"17"`` → current run seq 17; ``"j-5"`` → journal 5; junk → None
    (the stream starts from the beginning, as for a first connection)."""
    if not value:
        return None
    v = value.strip()
    try:
        if v.startswith("j-"):
            return Cursor(None, max(0, int(v[2:])))
        if "-" in v:
            run, seq = v.split("-", 1)
            return Cursor(max(1, int(run)), max(0, int(seq)))
        return Cursor(0, max(0, int(v)))  # run 0: "the current run"
    except ValueError:
        return None


def _msg(event: str, data: dict[str, Any], id_: str | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"event": event, "data": json.dumps(data, default=str)}
    if id_ is not None:
        out["id"] = id_
    return out


async def session_events(manager: SessionManager, session_id: str,
                         last_event_id: str | None) -> AsyncIterator[dict[str, Any]]:
    """The message generator (the caller checked the session exists)."""
    cursor = parse_last_event_id(last_event_id)
    manager.metrics.sse_delta(+1)
    try:
        job = manager.job(session_id)
        if job is None:
            async for m in _journal_replay(manager, session_id, cursor):
                yield m
            return
        announced = False
        while job.engine is None:
            if job.finished.is_set():  # cancelled (or failed to start) before running
                yield _msg("state", {"session_id": session_id, "new": job.final_state, "error": job.error})
                return
            if not announced:
                st = manager.reads.status(session_id)
                yield _msg("queued", {"session_id": session_id, "position": st.get("queue_position")})
                announced = True
            await asyncio.sleep(POLL_S)  # a client that leaves cancels this generator
        engine, run = job.engine, job.run
        last = cursor.seq if cursor is not None and cursor.run in (0, run) else 0
        while True:
            evs = engine.bus.since(last)
            if evs:
                if evs[0].seq > last + 1:
                    yield _msg("gap", {"session_id": session_id, "first_missing": last + 1,
                                       "last_missing": evs[0].seq - 1, "run": run})
                for ev in evs:
                    yield _msg(ev.kind, {**ev.to_dict(), "session_id": session_id, "run": run},
                               f"{run}-{ev.seq}")
                    last = ev.seq
                    if isinstance(ev, SessionFinished):
                        return
                continue
            if engine.bus.closed and not engine.bus.since(last):
                return
            await asyncio.sleep(POLL_S)  # a client that leaves cancels this generator
    finally:
        manager.metrics.sse_delta(-1)


async def _journal_replay(manager: SessionManager, session_id: str,
                          cursor: Cursor | None) -> AsyncIterator[dict[str, Any]]:
    state, events = await asyncio.to_thread(manager.reads.journal_events, session_id)
    start = cursor.seq if cursor is not None and cursor.run is None else 0
    for n, ev in enumerate(events, start=1):
        if n > start:
            yield _msg(ev["kind"], {**ev, "session_id": session_id, "replay": True}, f"j-{n}")
    yield _msg("end", {"session_id": session_id, "state": state,
                       "detail": "replayed from the journal; no engine of this daemon runs this session"})

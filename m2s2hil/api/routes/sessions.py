"""Sessions: submit a sweep, list and read them, pause / resume / abort, and their live events."""

from __future__ import annotations

import asyncio
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Header, Query, Request, Response
from sse_starlette import EventSourceResponse

from m2s2hil.plan import Sweep

from .. import models as m
from ..common import (
    CONFLICT,
    CROSS_SITE,
    MARKED,
    NOT_FOUND,
    Limit,
    Manager,
    Offset,
    SessionId,
    links,
    status_out,
)
from ..sse import session_events
from ..streams import BUSY, SlotEventSource, streams_of
from . import synthetic

router = APIRouter(tags=["sessions"])

SWEEP_EXAMPLE = {"satellite": "voyager", "build": "B3", "lighting": ["weak"], "tilts": ["E1"],
                 "azimuth_step_deg": 30}


@router.post("/sessions", status_code=202, response_model=m.SessionCreated,
             responses={429: {"model": m.ErrorBody, "description": "The queue is full."},
                        507: {"model": m.ErrorBody, "description": "Not enough free space for the plan."},
                        **CONFLICT, **CROSS_SITE})
def create_session(mg: Manager, response: Response, sweep: Annotated[Sweep, Body(
        openapi_examples={"short": {"summary": "one lighting, one tilt, 12 azimuths",
                                    "value": SWEEP_EXAMPLE}})]) -> dict:
    """Queue a session for this sweep; it starts when the rig is free (at once when idle)."""
    # A plain def: FastAPI runs it in its thread pool, so the plan's expansion, the disk check
    # and the session's creation stay off the event loop (/healthz and the SSE streams go on).
    job = mg.submissions.submit(sweep)
    url = f"/sessions/{job.session_id}"  # relative: never built from the Host header
    response.headers["Location"] = url
    st = mg.reads.status(job.session_id)
    if st["state"] == "queued" and st.get("queue_position") is None:
        st = mg.reads.status(job.session_id)  # it left the queue between two reads: report where it is now
    return {"session_id": job.session_id, "url": url, "state": st["state"],
            "queue_position": st.get("queue_position") if st["state"] == "queued" else None,
            "planned_events": job.planned, "links": links(job.session_id)}


@router.get("/sessions", response_model=m.SessionPage)
def list_sessions(
    mg: Manager,
    state: Annotated[m.SessionState | None, Query()] = None,
    satellite: Annotated[str | None, Query(max_length=64)] = None,
    build: Annotated[str | None, Query(max_length=64)] = None,
    offset: Offset = 0,
    limit: Limit = 50,
) -> dict:
    """Sessions under the data root, newest first (filters are exact, case-insensitive for names)."""
    items, total = mg.reads.sessions(state=state, satellite=satellite, build=build, offset=offset,
                                     limit=limit)
    # a render (POST /synthetic) this daemon knows: its views, not a plan
    items = [synthetic.live_status(mg, s["session_id"]) or s for s in items]
    return {"items": [status_out(s) for s in items], "total": total, "offset": offset, "limit": limit}


@router.get("/sessions/{session_id}", response_model=m.SessionStatus, responses=NOT_FOUND)
async def get_session(mg: Manager, session_id: SessionId) -> dict:
    """Status snapshot: state, progress, ETA, pose, lamps, faults."""
    syn = await synthetic.status_of(mg, session_id)  # a render (POST /synthetic): its own progress
    if syn is not None:
        return status_out(syn)
    job = mg.job(session_id)
    if job is not None and job.engine is not None:
        # In memory, no I/O: answered on the event loop (no thread hop, fewer GIL hand-overs
        # while the capture threads are busy).
        return status_out(mg.reads.status(session_id))
    return status_out(await asyncio.to_thread(mg.reads.status, session_id))


def _control(action: Literal["pause", "resume", "abort"], doc: str) -> None:
    def endpoint(mg: Manager, session_id: SessionId) -> dict:
        syn = synthetic.control_of(mg, session_id, action)  # a render: abort only, never the engine
        return status_out(syn if syn is not None else mg.control(session_id, action))

    endpoint.__doc__ = doc
    router.add_api_route(f"/sessions/{{session_id}}/{action}", endpoint, methods=["POST"],
                         response_model=m.SessionStatus, name=f"{action}_session",
                         dependencies=MARKED,
                         responses={**NOT_FOUND, **CONFLICT, **CROSS_SITE})


_control("pause", "Park the running session at its next safe boundary (lamps off, motion stopped).")
_control("resume", "Continue a paused session; an interrupted one (not running here) is queued again.")
_control("abort", "End the running session at its next safe boundary; a queued one is cancelled.")

#: Each message of the stream (OpenAPI 3.1: the schema of a text/event-stream describes one event).
SSE_MESSAGE = {"type": "object", "title": "SseMessage", "properties": {
    "event": {"type": "string", "description": "state, progress, frame, fault, finished, queued, gap, end"},
    "data": {"type": "string", "description": "One JSON object."},
    "id": {"type": "string", "description": "<run>-<seq>, or j-<n> for a journal replay; absent on "
                                            "queued, gap and end."},
    "retry": {"type": "integer"}}}
SSE_DOC: dict[str, Any] = {"content": {"text/event-stream": {"schema": SSE_MESSAGE}},
           "description": "Server-Sent Events, one message per event; see docs/api.md."}


@router.get("/sessions/{session_id}/events", response_class=EventSourceResponse,
            responses={200: SSE_DOC, **NOT_FOUND, **BUSY})
async def session_events_stream(
    request: Request,
    mg: Manager,
    session_id: SessionId,
    last_event_id: Annotated[str | None, Header(alias="Last-Event-ID", max_length=64)] = None,
) -> Response:
    """Progress, frames and faults as they happen; resumable with Last-Event-ID. A subscriber
    counts while its connection lasts; beyond the daemon's limit, 503 with Retry-After."""
    await asyncio.to_thread(mg.reads.status, session_id)  # 404 before the stream starts
    streams = streams_of(request)
    if not streams.sse.acquire():
        return streams.busy(streams.sse)
    events = (synthetic.events_of(mg, session_id, last_event_id)
              or session_events(mg, session_id, last_event_id))
    return SlotEventSource(streams.sse, events, ping=15,
                           send_timeout=streams.limits.send_timeout_s, headers={"Cache-Control": "no-store"})


router.include_router(synthetic.router)  # POST /synthetic: a session of its own kind, served by these routes

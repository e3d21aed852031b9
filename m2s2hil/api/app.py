"""The REST API: :func:`create_app` builds the FastAPI application around a
:class:`~m2s2hil.api.manager.SessionManager`.

Status codes (every error body is ``{"detail": "<what and where>"}``; validation errors
add ``errors``, one entry per problem):

===  ==========================================================================
202  ``POST /sessions``: accepted; ``Location`` and ``url`` name the new session
401  a token is configured and the request has none or a wrong one
404  no such session, or no such frame / file in it
409  the session's state does not allow it (pause a queued or finished session,
     resume a running one, …), or the daemon is shutting down
413  request body above the configured limit
422  invalid input: malformed JSON, a sweep the catalog or the rig cannot do, an
     id or a number outside its pattern or range, a plan above the frame limit
429  the queue is full (``queue_limit`` sessions already wait)
507  the data root has not enough free space for the plan
===  ==========================================================================
"""

from __future__ import annotations

import asyncio
import logging
import os
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Depends, FastAPI, Header, Path, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, PlainTextResponse
from sse_starlette import EventSourceResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from m2s2hil.engine.state import IllegalTransition
from m2s2hil.errors import M2S2Error, UsageError
from m2s2hil.plan import Sweep
from m2s2hil.store.atomic import DiskFull
from m2s2hil.store.frame_files import dumps
from m2s2hil.store.session import SessionCorrupt, software_version

from . import models as m
from .manager import Conflict, QueueFull, SessionManager, UnknownSession
from .prometheus import CONTENT_TYPE
from .security import BodyLimit, bearer_guard
from .sse import session_events

log = logging.getLogger(__name__)

API_TITLE = "m2s2hil capture daemon"
SWEEP_EXAMPLE = {"satellite": "voyager", "build": "B3", "lighting": ["weak"], "tilts": ["E1"],
                 "azimuth_step_deg": 30}


class StrictJSONResponse(JSONResponse):
    """JSON with NaN and infinities as null (the standard forbids them; engines may report them)."""

    def render(self, content: Any) -> bytes:
        return dumps(content).encode("utf-8")


def _err(status: int, detail: str, headers: dict[str, str] | None = None, **extra: Any) -> JSONResponse:
    return StrictJSONResponse({"detail": detail, **extra}, status_code=status, headers=headers)


def _loc(loc: Sequence[Any]) -> str:
    return ".".join(str(p) for p in loc) or "request"


ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": m.ErrorBody, "description": "Malformed request (a body that is not UTF-8 JSON, a bad "
                                                "Content-Length)."},
    401: {"model": m.ErrorBody, "description": "Missing or wrong bearer token (when one is configured)."},
    413: {"model": m.ErrorBody, "description": "Request body above the limit."},
    422: {"model": m.ErrorBody, "description": "Invalid input."},
}
NOT_FOUND = {404: {"model": m.ErrorBody, "description": "No such session (or frame)."}}
CONFLICT = {409: {"model": m.ErrorBody,
                  "description": "The session's or the daemon's state does not allow it."}}

SessionId = Annotated[str, Path(pattern=m.SESSION_ID_PATTERN, max_length=128,
                                description="A session id as returned by POST /sessions (no paths).")]
FrameN = Annotated[int, Path(ge=0, le=2**31 - 1, description="The frame's index in the plan.")]
Offset = Annotated[int, Query(ge=0, le=10**9)]
Limit = Annotated[int, Query(ge=1, le=500)]


def create_app(
    manager: SessionManager | None,
    *,
    token: str | None = None,
    cors_origins: Sequence[str] = (),
    max_body_bytes: int = 64 * 1024,
    manage_lifecycle: bool = False,
    resume_interrupted: bool = False,
    shutdown_timeout_s: float = 120.0,
) -> FastAPI:
    """The application. ``manage_lifecycle``: start the manager on startup (resuming
    interrupted sessions if asked) and close it on shutdown (pause at a safe boundary,
    rig safe); tests that drive the manager themselves leave it off. ``manager=None``
    builds an application good only for its OpenAPI schema."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if manage_lifecycle and manager is not None:
            await asyncio.to_thread(manager.start, resume_interrupted=resume_interrupted)
        try:
            yield
        finally:
            if manage_lifecycle and manager is not None:
                await asyncio.to_thread(manager.close, reason="daemon shutdown", timeout=shutdown_timeout_s)

    app = FastAPI(
        title=API_TITLE,
        version=software_version(),
        description=(
            "Capture multispectral datasets of satellite mockups on a hardware-in-the-loop rig. "
            "One rig runs one session; further sessions wait in a first-in-first-out queue. "
            "See docs/api.md."
        ),
        default_response_class=StrictJSONResponse,
        lifespan=lifespan,
        generate_unique_id_function=lambda route: route.name,  # operationId = the function's name
    )
    app.state.manager = manager
    _document_catalog_names(app)
    guard = bearer_guard(token)
    api = APIRouter(dependencies=[Depends(guard)], responses=ERRORS)

    def mgr() -> SessionManager:
        if manager is None:  # only the schema-export app has none
            raise Conflict("this application was built without a rig (schema export only)")
        return manager

    def links(sid: str) -> dict[str, str]:
        return {"self": f"/sessions/{sid}", "events": f"/sessions/{sid}/events",
                "frames": f"/sessions/{sid}/frames"}

    def status_out(st: dict) -> dict:
        return {**st, "links": links(st["session_id"])}

    # ------------------------------------------------------------------ sessions
    @api.post("/sessions", status_code=202, response_model=m.SessionCreated, tags=["sessions"],
              responses={429: {"model": m.ErrorBody, "description": "The queue is full."},
                         507: {"model": m.ErrorBody, "description": "Not enough free space for the plan."},
                         **CONFLICT})
    def create_session(request: Request, response: Response, sweep: Annotated[Sweep, Body(
            openapi_examples={"short": {"summary": "one lighting, one tilt, 12 azimuths",
                                        "value": SWEEP_EXAMPLE}})]) -> dict:
        """Queue a session for this sweep; it starts when the rig is free (at once when idle)."""
        job = mgr().submit(sweep)
        url = str(request.url_for("get_session", session_id=job.session_id))
        response.headers["Location"] = url
        st = mgr().status(job.session_id)
        return {"session_id": job.session_id, "url": url, "state": st["state"],
                "queue_position": st.get("queue_position"), "planned_events": job.planned,
                "links": links(job.session_id)}

    @api.get("/sessions", response_model=m.SessionPage, tags=["sessions"])
    def list_sessions(
        state: Annotated[m.SessionState | None, Query()] = None,
        satellite: Annotated[str | None, Query(max_length=64)] = None,
        build: Annotated[str | None, Query(max_length=64)] = None,
        offset: Offset = 0,
        limit: Limit = 50,
    ) -> dict:
        """Sessions under the data root, newest first (filters are exact, case-insensitive for names)."""
        items, total = mgr().sessions(state=state, satellite=satellite, build=build, offset=offset,
                                      limit=limit)
        return {"items": [status_out(s) for s in items], "total": total, "offset": offset, "limit": limit}

    @api.get("/sessions/{session_id}", response_model=m.SessionStatus, tags=["sessions"],
             responses=NOT_FOUND)
    async def get_session(session_id: SessionId) -> dict:
        """Status snapshot: state, progress, ETA, pose, lamps, faults."""
        mg = mgr()
        job = mg.job(session_id)
        if job is not None and job.engine is not None:
            # In memory, no I/O: answered on the event loop (no thread hop, fewer GIL hand-overs
            # while the capture threads are busy).
            return status_out(mg.status(session_id))
        return status_out(await asyncio.to_thread(mg.status, session_id))

    def control(action: Literal["pause", "resume", "abort"], doc: str) -> None:
        def endpoint(session_id: SessionId) -> dict:
            return status_out(mgr().control(session_id, action))

        endpoint.__doc__ = doc
        api.add_api_route(f"/sessions/{{session_id}}/{action}", endpoint, methods=["POST"],
                          response_model=m.SessionStatus, tags=["sessions"], name=f"{action}_session",
                          responses={**NOT_FOUND, **CONFLICT})

    control("pause", "Park the running session at its next safe boundary (lamps off, motion stopped).")
    control("resume", "Continue a paused session; an interrupted one (not running here) is queued again.")
    control("abort", "End the running session at its next safe boundary; a queued one is cancelled.")

    @api.get("/sessions/{session_id}/events", tags=["sessions"], response_class=EventSourceResponse,
             responses={200: {"content": {"text/event-stream": {"schema": {"type": "string"}}},
                              "description": "Server-Sent Events; see docs/api.md."}, **NOT_FOUND})
    async def session_events_stream(
        session_id: SessionId,
        last_event_id: Annotated[str | None, Header(alias="Last-Event-ID", max_length=64)] = None,
    ) -> EventSourceResponse:
        """Progress, frames and faults as they happen; resumable with Last-Event-ID."""
        await asyncio.to_thread(mgr().status, session_id)  # 404 before the stream starts
        return EventSourceResponse(session_events(mgr(), session_id, last_event_id), ping=15,
                                   headers={"Cache-Control": "no-store"})

    # ------------------------------------------------------------------ frames
    @api.get("/sessions/{session_id}/frames", response_model=m.FramePage, tags=["frames"],
             responses={**NOT_FOUND, **CONFLICT})
    def list_frames(session_id: SessionId, offset: Offset = 0, limit: Limit = 50) -> dict:
        """Stored frames in plan order, with their files (sha256) and metadata."""
        recs, total = mgr().frames(session_id, offset=offset, limit=limit)
        items = []
        for r in recs:
            base = f"/sessions/{session_id}/frames/{r.index}"
            items.append({"n": r.index, "event_id": r.event_id, "time": r.time, "dark_id": r.dark_id,
                          "files": {k: f.model_dump() for k, f in r.files.items()}, "meta": r.meta,
                          "preview_url": f"{base}/preview.png" if "preview" in r.files else None,
                          "raw_url": f"{base}/raw"})
        return {"items": items, "total": total, "offset": offset, "limit": limit}

    @api.get("/sessions/{session_id}/frames/{n}/preview.png", tags=["frames"], response_class=Response,
             responses={200: {"content": {"image/png": {}}, "description": "8-bit RGB preview."},
                        **NOT_FOUND, **CONFLICT})
    def frame_preview(session_id: SessionId, n: FrameN) -> Response:
        """The frame's RGB preview (bands nearest 650/550/470 nm)."""
        data = mgr().frame_file(session_id, n, "preview")
        return Response(data, media_type="image/png", headers={"Cache-Control": "max-age=3600"})

    @api.get("/sessions/{session_id}/frames/{n}/raw", tags=["frames"], response_class=Response,
             responses={200: {"content": {"image/tiff": {}}, "description": "Raw mosaic, uint16 TIFF."},
                        **NOT_FOUND, **CONFLICT})
    def frame_raw(session_id: SessionId, n: FrameN) -> Response:
        """The stored raw mosaic TIFF (metadata JSON in its ImageDescription), checked against its sha256."""
        data = mgr().frame_file(session_id, n, "raw")
        return Response(data, media_type="image/tiff",
                        headers={"Content-Disposition": f'attachment; filename="{session_id}-{n}.raw.tiff"'})

    # ------------------------------------------------------------------ queue and rig
    @api.get("/queue", response_model=m.QueueState, tags=["queue"])
    def get_queue() -> dict:
        """The running session and the ones waiting, first to run first."""
        return mgr().queue()

    @api.post("/queue/hold", response_model=m.QueueState, tags=["queue"])
    def hold_queue(reason: Annotated[str, Query(min_length=1, max_length=200)] = "operator") -> dict:
        """Hold the queue: the running session goes on, no queued one starts (e.g. to swap the mockup)."""
        mgr().hold(reason)
        return mgr().queue()

    @api.post("/queue/release", response_model=m.QueueState, tags=["queue"])
    def release_queue() -> dict:
        """Let queued sessions start again after an emergency stop or a failure held the queue."""
        mgr().release()
        return mgr().queue()

    @api.get("/rig", response_model=m.RigState, tags=["rig"])
    def get_rig() -> dict:
        """Each device's state and health."""
        return mgr().rig_state()

    @api.post("/rig/stop", response_model=m.StopReport, tags=["rig"])
    def emergency_stop() -> dict:
        """Emergency stop: lamps off and motion stopped now, even during a session (which is aborted);
        the queue is held until POST /queue/release."""
        return mgr().emergency_stop()

    @api.get("/metrics", response_class=PlainTextResponse, tags=["daemon"],
             responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format."}})
    def metrics() -> PlainTextResponse:
        """Prometheus metrics: frames, faults by class, queue depths, session durations."""
        return PlainTextResponse(mgr().metrics.render(), media_type=CONTENT_TYPE)

    app.include_router(api)

    @app.get("/healthz", response_model=m.Health, tags=["daemon"])
    def healthz() -> dict:
        """Liveness and a one-line summary; needs no token."""
        mg = mgr()
        writable = os.access(mg.root, os.W_OK)
        q = mg.queue()
        return {"status": "ok" if writable and not q["held"] else "degraded", "version": software_version(),
                "rig": mg.rig.config.rig.name, "simulated": bool(mg.rig.simulated),
                "data_root_writable": writable, "running": q["running"], "queued": len(q["items"]),
                "held": q["held"], "uptime_s": _uptime(mg)}

    # ------------------------------------------------------------------ errors
    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", "")).removeprefix(
            "Value error, "), "type": str(e.get("type", ""))} for e in exc.errors()]
        detail = "; ".join(f"{_loc(e['loc'])}: {e['msg']}" for e in errors) or "invalid request"
        return _err(422, detail, errors=errors)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = str(exc.detail)
        if exc.status_code == 400 and detail == "There was an error parsing the body":
            detail = "the request body could not be decoded: it must be UTF-8 JSON"
        return _err(exc.status_code, detail, headers=getattr(exc, "headers", None))

    @app.exception_handler(M2S2Error)
    async def domain_error(request: Request, exc: M2S2Error) -> JSONResponse:
        if isinstance(exc, UnknownSession):
            return _err(404, str(exc))
        if isinstance(exc, (Conflict, IllegalTransition)):
            return _err(409, str(exc))
        if isinstance(exc, QueueFull):
            return _err(429, str(exc), headers={"Retry-After": "60"})
        if isinstance(exc, DiskFull):
            return _err(507, str(exc))
        if isinstance(exc, UsageError):
            return _err(422, str(exc))
        if isinstance(exc, SessionCorrupt):
            log.error("corrupt session data: %s", exc)
            return _err(500, f"stored session data is damaged: {exc}")
        log.exception("unexpected error on %s %s", request.method, request.url.path, exc_info=exc)
        return _err(500, f"{type(exc).__name__}: {exc}")

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unexpected error on %s %s", request.method, request.url.path, exc_info=exc)
        return _err(500, f"internal error ({type(exc).__name__}); see the daemon's log")

    if cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=list(cors_origins), allow_methods=["GET", "POST"],
                           allow_headers=["Authorization", "Content-Type", "Last-Event-ID"])
    app.add_middleware(BodyLimit, max_bytes=max_body_bytes)
    return app


def _document_catalog_names(app: FastAPI) -> None:
    """Name the catalog's satellites, builds, lighting conditions and elevations, and the
    processing methods, in the Sweep schema (the model validates them in code, so pydantic
    cannot say so itself). Canonical names only; the validators also accept other cases and
    the dataset's aliases."""
    from fastapi.openapi.utils import get_openapi

    from m2s2hil.catalog import load_catalog
    from m2s2hil.processing.demosaic import METHODS as DEMOSAIC_METHODS

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            doc = get_openapi(title=app.title, version=app.version, description=app.description,
                              routes=app.routes)
            cat = load_catalog()
            props = doc.get("components", {}).get("schemas", {}).get("Sweep", {}).get("properties", {})
            builds = sorted({b for s in cat.satellites.values() for b in s.builds})
            for key, names in (("satellite", list(cat.satellites)), ("build", builds)):
                if key in props:
                    props[key]["enum"] = names
            if "processing" in props:
                props["processing"]["enum"] = list(DEMOSAIC_METHODS)
            for key, names in (("lighting", list(cat.lighting)), ("tilts", list(cat.elevations))):
                if key in props and isinstance(props[key].get("items"), dict):
                    props[key]["items"]["enum"] = names
                    props[key]["uniqueItems"] = True
            app.openapi_schema = doc
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def _uptime(mg: SessionManager) -> float:
    import time

    return max(0.0, time.time() - mg.started_at)


def schema_app() -> FastAPI:
    """An application without a rig, for exporting the OpenAPI schema."""
    return create_app(None)


def openapi_json() -> str:
    """The committed schema (docs/openapi.json): deterministic, sorted keys, trailing newline."""
    import json

    return json.dumps(schema_app().openapi(), indent=2, sort_keys=True) + "\n"


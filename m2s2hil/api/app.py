"""The REST API: :func:`create_app` assembles the FastAPI application around a
:class:`~m2s2hil.daemon.manager.SessionManager` from the routers (``routes/``, and the
operator console's in ``console/``), the error handlers (``handlers.py``) and the
middleware, outermost first: the Host allow-list (``guards/hosts.py``), the cross-site guard
(``guards/csrf.py``), CORS when configured, the body limit.

Status codes (every error body is ``{"detail": "<what and where>"}``; validation errors
add ``errors``, one entry per problem):

===  ==========================================================================
202  ``POST /sessions``: accepted; ``Location`` and ``url`` name the new session
400  a body that is not JSON (or not UTF-8, or a number too long to read)
401  a token is configured and the request has none or a wrong one
403  refused as a possible cross-site request (see guards/csrf.py)
404  no such session, or no such frame / file in it
409  the session's state does not allow it (pause a queued or finished session,
     resume a running one, …), or the daemon is shutting down
413  request body above the configured limit
421  the Host header names a host the daemon does not serve
422  invalid input: a sweep the catalog or the rig cannot do, an id or a number
     outside its pattern or range, a plan above the frame limit
429  the queue is full (``queue_limit`` sessions already wait)
507  the data root has not enough free space for the plan
===  ==========================================================================

To add routes (e.g. the operator console's): write an ``APIRouter`` in its own module and
add it to :data:`GUARDED_ROUTERS` (token required) or :data:`OPEN_ROUTERS`; the Host and
cross-site checks cover every route whatever its router.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from typing import Any

from fastapi import APIRouter, Depends, FastAPI
from fastapi.middleware.cors import CORSMiddleware

from m2s2hil.daemon.manager import SessionManager
from m2s2hil.store.folder import software_version

from . import handlers
from .common import ERRORS, StrictJSONResponse, require_token
from .console import browser, calibration, live, manual, page, pictures, snapshots
from .guards.csrf import HEADER, CrossSiteGuard
from .guards.hosts import HostAllowList
from .guards.security import BodyLimit
from .routes import activity, daemon, exports, frames, lens, queue, rig, sessions
from .streams import StreamLimits, Streams

API_TITLE = "m2s2hil capture daemon"

GUARDED_ROUTERS: list[APIRouter] = [sessions.router, frames.router, queue.router, rig.router, daemon.router,
                                    lens.router, activity.router, exports.router,
                                    # the operator console's (docs/console.md)
                                    manual.router, live.router, snapshots.router, calibration.router,
                                    browser.router, page.router, pictures.router]
OPEN_ROUTERS: list[APIRouter] = [daemon.open_router, page.open_router]


def create_app(
    manager: SessionManager | None,
    *,
    token: str | None = None,
    cors_origins: Sequence[str] = (),
    allowed_hosts: Sequence[str] = (),
    max_body_bytes: int = 64 * 1024,
    manage_lifecycle: bool = False,
    resume_interrupted: bool = False,
    shutdown_timeout_s: float = 120.0,
    stream_limits: StreamLimits | None = None,
) -> FastAPI:
    """The application. ``manage_lifecycle``: start the manager on startup (resuming
    interrupted sessions if asked) and close it on shutdown (pause at a safe boundary,
    rig safe); tests that drive the manager themselves leave it off. ``manager=None``
    builds an application good only for its OpenAPI schema. ``allowed_hosts``: names
    besides the loopback ones that the Host header may carry; ``cors_origins`` are also
    the origins allowed to change state from a browser."""

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
            f"State-changing requests need a JSON body or the header `{HEADER}: 1`, and browsers may "
            "send them only from the daemon's own origin. See docs/api.md and docs/security.md."
        ),
        default_response_class=StrictJSONResponse,
        lifespan=lifespan,
        generate_unique_id_function=lambda route: route.name,  # operationId = the function's name
    )
    app.state.manager = manager
    app.state.token = token
    app.state.streams = Streams(stream_limits)  # live-view and SSE slots (streams.py)
    _document_catalog_names(app)
    for router in GUARDED_ROUTERS:
        app.include_router(router, dependencies=[Depends(require_token)], responses=ERRORS)
    for router in OPEN_ROUTERS:
        app.include_router(router, responses={k: v for k, v in ERRORS.items() if k != 401})
    handlers.install(app)

    # add_middleware wraps: the last added runs first.
    app.add_middleware(activity.ActivityRecorder)  # innermost: what passed the guards (who, from where)
    app.add_middleware(BodyLimit, max_bytes=max_body_bytes)
    if cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=list(cors_origins), allow_methods=["GET", "POST"],
                           allow_headers=["Authorization", "Content-Type", "Last-Event-ID", HEADER])
    app.add_middleware(CrossSiteGuard, extra_origins=cors_origins, allowed_hosts=allowed_hosts)
    app.add_middleware(HostAllowList, allowed=allowed_hosts)
    return app


def _document_catalog_names(app: FastAPI) -> None:
    """Name the catalog's satellites, builds, lighting conditions and elevations, and the
    processing methods, in the Sweep schema (the model validates them in code, so pydantic
    cannot say so itself). Canonical names only; the validators also accept other cases and
    the dataset's aliases."""
    from fastapi.openapi.utils import get_openapi

    from m2s2hil.catalog import load_catalog
    from m2s2hil.config import DEMOSAIC_METHODS
    from m2s2hil.plan import AXES

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
            # Lighting: the canonical names and the published release's (solo, all, dir).
            lights = list(cat.lighting) + [lt.dataset for lt in cat.lighting.values()]
            for key, names in (("lighting", lights), ("tilts", list(cat.elevations))):
                if key in props and isinstance(props[key].get("items"), dict):
                    props[key]["items"]["enum"] = names
                    props[key]["uniqueItems"] = True
            if "axis_order" in props:
                props["axis_order"]["enum"] = ["auto", *(">".join(p) for p in itertools.permutations(AXES))]
            schemas = doc.get("components", {}).get("schemas", {})
            for model, key in (("FixedExposure", "seconds"), ("AutoExposure", "start_s")):
                field = schemas.get(model, {}).get("properties", {}).get(key)
                if field is not None:  # exposure tables are keyed by lighting condition
                    field["propertyNames"] = {"enum": lights}
            if app.state.token is None:  # this daemon wants no token: its schema must not say it does
                doc.get("components", {}).pop("securitySchemes", None)
                for item in doc.get("paths", {}).values():
                    for op in item.values():
                        op.pop("security", None)
                        op.get("responses", {}).pop("401", None)
            app.openapi_schema = doc
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def schema_app() -> FastAPI:
    """An application without a rig, for exporting the OpenAPI schema (as a daemon with a token
    serves it: the committed schema documents the bearer scheme)."""
    return create_app(None, token="schema-export-only-0123456789")


def openapi_json() -> str:
    """The committed schema (docs/openapi.json): deterministic, sorted keys, trailing newline."""
    import json

    return json.dumps(schema_app().openapi(), indent=2, sort_keys=True) + "\n"

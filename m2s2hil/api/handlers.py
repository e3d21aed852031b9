"""How errors become responses: every error body is ``{"detail": "<what and where>"}``
(validation errors add ``errors``, one entry per problem), never a traceback."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from m2s2hil.atomic import DiskFull
from m2s2hil.daemon.errors import Conflict, QueueFull, UnknownSession
from m2s2hil.daemon.hold import HoldNotSaved
from m2s2hil.engine.state import IllegalTransition
from m2s2hil.errors import M2S2Error, UsageError
from m2s2hil.store.errors import SessionCorrupt

from .common import error_response
from .guards.csrf import flat_routes
from .guards.logsafe import clean_text

log = logging.getLogger("m2s2hil.api")


def _loc(loc: Sequence[Any]) -> str:
    return ".".join(str(p) for p in loc) or "request"


def _unreadable_body(cause: BaseException | None) -> str:
    """Why a body could not be parsed, in the client's terms."""
    if isinstance(cause, UnicodeDecodeError):
        return "the request body is not UTF-8 (JSON must be)"
    if isinstance(cause, ValueError) and "digits" in str(cause):
        return "body: a number in the JSON has too many digits to be read (at most 4300)"
    if isinstance(cause, RecursionError):
        return "body: the JSON is nested too deeply"
    return "the request body could not be read as JSON"


def install(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", "")).removeprefix(
            "Value error, "), "type": str(e.get("type", ""))} for e in exc.errors()]
        malformed = [e for e in exc.errors() if e.get("type") == "json_invalid"]
        if malformed:  # not JSON at all: 400, as for any body that cannot be read
            e = malformed[0]
            where = (e.get("loc") or ("body", 0))[-1]
            why = (e.get("ctx") or {}).get("error", "invalid JSON")
            return error_response(400, f"body: malformed JSON at character {where}: {why}",
                                  errors=[{**errors[0], "msg": str(why)}])
        detail = "; ".join(f"{_loc(e['loc'])}: {e['msg']}" for e in errors) or "invalid request"
        return error_response(422, detail, errors=errors)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = str(exc.detail)
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 400 and detail == "There was an error parsing the body":
            detail = _unreadable_body(exc.__cause__)
        if exc.status_code == 405:
            # Starlette names the methods of the first route on the path only (GET /sessions
            # and POST /sessions are two routes): list every route's.
            allowed = _methods_for(request)
            headers["Allow"] = ", ".join(allowed)
            detail = f"{request.method} is not allowed here; allowed: {', '.join(allowed)}"
        return error_response(exc.status_code, detail, headers=headers or None)

    @app.exception_handler(M2S2Error)
    async def domain_error(request: Request, exc: M2S2Error) -> JSONResponse:
        if isinstance(exc, UnknownSession):
            return error_response(404, str(exc))
        if isinstance(exc, (Conflict, IllegalTransition)):
            return error_response(409, str(exc))
        if isinstance(exc, QueueFull):
            return error_response(429, str(exc), headers={"Retry-After": "60"})
        if isinstance(exc, DiskFull):
            return error_response(507, _disk_full(exc, submitted=request.url.path == "/sessions"))
        if isinstance(exc, UsageError):
            return error_response(422, str(exc))
        if isinstance(exc, HoldNotSaved):  # the disk refused it: say what holds and what does not
            log.error("%s", exc)
            return error_response(500, str(exc))
        if isinstance(exc, SessionCorrupt):
            log.error("corrupt session data: %s", exc)
            return error_response(500, f"stored session data is damaged: {exc}")
        log.exception("unexpected error on %s %s", request.method, clean_text(request.url.path), exc_info=exc)
        return error_response(500, f"{type(exc).__name__}: {exc}")

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unexpected error on %s %s", request.method, clean_text(request.url.path), exc_info=exc)
        return error_response(500, f"internal error ({type(exc).__name__}); see the daemon's log")


def _methods_for(request: Request) -> list[str]:
    from starlette.routing import Match

    methods: set[str] = set()
    for route in flat_routes(request.app.router.routes):
        if route.matches(request.scope)[0] != Match.NONE:
            methods |= set(getattr(route, "methods", None) or ())
    return sorted(methods)


def _disk_full(exc: DiskFull, *, submitted: bool) -> str:
    """What to do about a full disk. A refused submission created no session: there is
    nothing to resume, so the advice is not the engine's "resume the session"."""
    parts = [f"not enough free space in {exc.path}"]
    if exc.needed is not None and exc.free is not None:
        parts.append(f"the plan needs {exc.needed / 1e6:.1f} MB, {exc.free / 1e6:.1f} MB are free")
    advice = ("free some space or submit a smaller sweep (no session was created)" if submitted
              else "free some space and try again")
    return ": ".join(parts) + "; " + advice

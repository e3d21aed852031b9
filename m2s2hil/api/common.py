"""What every router of the API shares: the JSON response class, the documented error
responses, path and query parameter types, the manager and token dependencies, and links.

A new router (e.g. the operator console's) imports from here and is added in
:func:`m2s2hil.api.app.create_app`; the token guard, the Host allow-list and the
cross-site checks then cover it without further code."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import Depends, Header, HTTPException, Path, Query, Request
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from m2s2hil.daemon.errors import Conflict
from m2s2hil.daemon.manager import SessionManager
from m2s2hil.store.frame_files import dumps

from . import models as m
from .guards.security import token_matches


class StrictJSONResponse(JSONResponse):
    """JSON with NaN and infinities as null (the standard forbids them; engines may report them)."""

    def render(self, content: Any) -> bytes:
        return dumps(content).encode("utf-8")


def error_response(status: int, detail: str, headers: dict[str, str] | None = None,
                   **extra: Any) -> JSONResponse:
    return StrictJSONResponse({"detail": detail, **extra}, status_code=status, headers=headers)


#: FastAPI's ``responses=`` (status -> OpenAPI response object).
Responses = dict[int | str, dict[str, Any]]

ERRORS: Responses = {
    400: {"model": m.ErrorBody, "description": "Malformed request (a body that is not JSON, a number "
                                                "too long to read, a bad Content-Length)."},
    401: {"model": m.ErrorBody, "description": "Missing or wrong bearer token (when one is configured)."},
    413: {"model": m.ErrorBody, "description": "Request body above the limit."},
    421: {"model": m.ErrorBody, "description": "The Host header names a host this daemon does not serve."},
    422: {"model": m.ErrorBody, "description": "Invalid input."},
}
#: Added to state-changing operations (see csrf.py).
CROSS_SITE: Responses = {403: {
    "model": m.ErrorBody,
    "description": "Refused as a possible cross-site request: an Origin that is not allowed, or neither "
                   "a JSON body nor the X-M2S2HIL header."}}
NOT_FOUND: Responses = {404: {"model": m.ErrorBody, "description": "No such session (or frame)."}}
CONFLICT: Responses = {409: {"model": m.ErrorBody,
                  "description": "The session's or the daemon's state does not allow it."}}

SessionId = Annotated[str, Path(pattern=m.SESSION_ID_PATTERN, max_length=128,
                                description="A session id as returned by POST /sessions (no paths).")]
FrameN = Annotated[int, Path(ge=0, le=2**31 - 1, description="The frame's index in the plan.")]
Offset = Annotated[int, Query(ge=0, le=10**9)]
Limit = Annotated[int, Query(ge=1, le=500)]


async def get_manager(request: Request) -> SessionManager:
    """The application's session manager (async: no thread hop for a lookup)."""
    manager = request.app.state.manager
    if manager is None:  # only the schema-export app has none
        raise Conflict("this application was built without a rig (schema export only)")
    return manager


Manager = Annotated[SessionManager, Depends(get_manager)]

_bearer = HTTPBearer(auto_error=False, description="Required when the daemon has a token configured.")


async def require_token(request: Request,
                        cred: HTTPAuthorizationCredentials | None = Depends(_bearer)) -> None:
    """The bearer-token check, against ``app.state.token`` (no-op when None). Declared on
    every guarded router so the OpenAPI schema documents the scheme."""
    expected: str | None = request.app.state.token
    if expected is None:
        return
    if cred is None:
        raise HTTPException(401, "missing bearer token (Authorization: Bearer <token>)",
                            headers={"WWW-Authenticate": 'Bearer realm="m2s2hil"'})
    if not token_matches(cred.credentials, expected):
        raise HTTPException(401, "invalid bearer token",
                            headers={"WWW-Authenticate": 'Bearer realm="m2s2hil", error="invalid_token"'})


async def marked_request(
    x_m2s2hil: Annotated[Literal["1"], Header(alias="X-M2S2HIL", description=(
        "Marks a request without a body as sent by a script, which a web page cannot send to "
        "another site without asking first (see docs/security.md)."))],
) -> None:
    """Declares the header on the operations without a body (the check itself is csrf.py's,
    which runs first and answers 403)."""


#: Dependencies of every state-changing operation without a body.
MARKED = [Depends(marked_request)]


def links(sid: str) -> dict[str, str]:
    """Relative links (never built from the Host header)."""
    return {"self": f"/sessions/{sid}", "events": f"/sessions/{sid}/events",
            "frames": f"/sessions/{sid}/frames"}


def status_out(st: dict) -> dict:
    return {**st, "links": links(st["session_id"])}

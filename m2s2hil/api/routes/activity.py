"""The activity log over HTTP (``GET /activity``), the clients seen recently (``GET
/activity/clients``), and the middleware that records who sent each request and from where.

Every request passes :class:`ActivityRecorder` once it has passed the Host and cross-site guards:
the client is counted as connected (:meth:`ActivityLog.seen`), and a request that changes
something (any method but GET, HEAD, OPTIONS; a POST that only computes, such as
``/plans/estimate``, does not count) becomes an ``action`` entry with its method, path,
status and actor. A route may say what it did in words (``request.state.activity``, e.g.
``turntable jog +1° → 11°``). Who: the ``X-M2S2HIL-Client`` header when the client sends one
(the console sends one id per tab; an id is ``[A-Za-z0-9._-]``, at most 64 characters, anything
else is ignored), whether the request carried the daemon's token; from where: the client's
address and its ``Origin``. Free text from the request is cut and escaped (``logsafe``).
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request

from m2s2hil.daemon.activity import ActivityLog, Actor

from ..common import Manager
from ..guards.logsafe import clean_text
from ..guards.security import Receive, Scope, Send, token_matches
from ..models import ActivityClients, ActivityPage, BusyOut

router = APIRouter(tags=["activity"])

CLIENT_HEADER = "X-M2S2HIL-Client"
_CLIENT_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
_READ_ONLY = frozenset({"GET", "HEAD", "OPTIONS"})
# POSTs that change nothing (the session form asks for an estimate on every edit): seen, not logged
_READ_ONLY_POSTS = frozenset({"/plans/estimate"})
Kind = Literal["action", "fault", "retry", "state", "session", "queue", "daemon"]


def actor_of(headers: dict[str, str], client: tuple[str, int] | None, token: str | None) -> Actor:
    """Who sent a request (its lower-cased headers) and from where."""
    cid = headers.get(CLIENT_HEADER.lower())
    auth = headers.get("authorization", "")
    scheme, _, given = auth.partition(" ")
    return Actor(
        address=client[0] if client else None,
        client=cid if cid is not None and _CLIENT_ID.match(cid) else None,
        origin=clean_text(headers["origin"], 200) if "origin" in headers else None,
        authenticated=(token is not None and scheme.lower() == "bearer"
                       and token_matches(given.strip(), token)),
        user_agent=clean_text(headers["user-agent"], 120) if "user-agent" in headers else None,
    )


def request_actor(request: Request) -> Actor:
    return actor_of({k.lower(): v for k, v in request.headers.items()}, request.client and
                    (request.client.host, request.client.port), request.app.state.token)


class ActivityRecorder:
    """ASGI middleware: every request is seen, every state change recorded (module docstring)."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        manager = scope["app"].state.manager if "app" in scope else None
        if scope["type"] != "http" or manager is None:
            await self.app(scope, receive, send)
            return
        log: ActivityLog = manager.activity
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        actor = actor_of(headers, scope.get("client"), scope["app"].state.token)
        method = scope["method"]
        if method in _READ_ONLY or scope.get("path") in _READ_ONLY_POSTS:
            log.seen(actor)
            await self.app(scope, receive, send)
            return
        status = 500
        state = scope.setdefault("state", {})  # shared with the route (request.state), copies or not

        async def send_status(message: Any) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            path = clean_text(scope.get("path", ""), 200)
            said = state.get("activity")
            what = f"{method} {path}"
            message = f"{said} ({what} → {status})" if said else f"{what} → {status}"
            log.seen(actor, what if status < 400 else None)
            log.record("action", message, level="info" if status < 400 else "warning", actor=actor,
                       method=method, path=path, status=status)


@router.get("/activity", response_model=ActivityPage)
def get_activity(
    mg: Manager,
    since: Annotated[int, Query(ge=0, le=2**53, description="Entries after this seq (0: the oldest kept).")]
    = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 200,
    kind: Annotated[list[Kind] | None, Query(description="Only these kinds (repeat the parameter).")] = None,
    session_id: Annotated[str | None, Query(max_length=128, description="Only this session's entries.")]
    = None,
) -> dict:
    """The daemon's activity log, oldest first: faults, retries, state changes, sessions' ends,
    holds and operator actions (with who and from where). Poll with ``since`` = the ``last_seq``
    of the previous answer; ``gap`` says entries after ``since`` are gone from the ring."""
    kinds: set[str] | None = set(kind) if kind else None
    items, next_seq, gap = mg.activity.since(since, limit=limit, kinds=kinds, session_id=session_id)
    return {"items": [a.to_dict() for a in items], "last_seq": next_seq, "newest_seq": mg.activity.last_seq,
            "gap": gap}


@router.get("/activity/clients", response_model=ActivityClients)
def get_clients(
    request: Request, mg: Manager,
    window_s: Annotated[float, Query(ge=1, le=600, description="Seen (and acting) within this many seconds.")]
    = 60.0,
) -> dict:
    """The clients that sent requests within ``window_s`` (``you`` marks the asking one: send
    ``X-M2S2HIL-Client`` to be told apart from other tabs on the same machine), which of them
    changed something in that time (``controlling``, ``last_action``), and how many others."""
    return mg.activity.clients(request_actor(request), window_s=window_s)


@router.get("/busy", response_model=BusyOut)
def get_busy(mg: Manager) -> dict:
    """The long operator actions running now (a snapshot, darks, the white reference, the phase
    check, exports), each with what it is and since when: a second one of the same gets 409."""
    return {"items": mg.busy.items()}

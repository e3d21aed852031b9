"""No cross-site state changes: the check every state-changing request passes first.

A page on any web site can make the operator's browser send a "simple" request (a form
post, a ``fetch`` in ``no-cors`` mode) to ``http://127.0.0.1:8750`` without asking the
daemon first; the browser only hides the answer, the rig has already moved. Browsers send
two things cross-site only after a CORS preflight that the daemon does not grant: a
``Content-Type`` other than the three form types, and a custom header. So a
state-changing request (POST, PUT, PATCH, DELETE) must

- have ``Content-Type: application/json`` (what a body-carrying API request has anyway), or
  carry the header ``X-M2S2HIL: 1`` (what a request without a body adds), and
- if it has an ``Origin`` (browsers send one on every such request), come from an
  allowed origin: the daemon's own (scheme, a host name the Host allow-list accepts, and
  the port the request was sent to: ``http://127.0.0.1:8750``, ``http://localhost:8750``,
  ``http://[::1]:8750``, configured names) or one configured in ``cors_origins``.
  ``Origin: null`` (sandboxed frames, ``file:`` pages) is never allowed, nor a request with
  more than one ``Origin`` (a browser sends one; which of several a proxy or framework would
  read is anyone's guess, so none is trusted). A host name's trailing dot (``localhost.``,
  the same name written as a fully qualified one) is ignored here as in the Host allow-list.

Refusals are 403 with ``{"detail": …}``. WebSocket handshakes (not covered by CORS at all)
from a disallowed Origin are closed before they are accepted. Requests without an Origin
(curl, scripts, the CLI) pass the origin check: they are not made by a browser for a page.
As pure ASGI middleware it covers every route, including those added later."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any
from urllib.parse import urlsplit

from .hosts import header, header_count, normalise_hosts, refuse, split_host
from .security import Receive, Scope, Send

#: The custom header that marks a request as sent by a script that may send it (its value: "1").
HEADER = "X-M2S2HIL"
STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
_DEFAULT_PORT = {"http": 80, "https": 443, "ws": 80, "wss": 443}


def normalise_origin(origin: str) -> str | None:
    """``scheme://host[:port]`` in lower case with the default port dropped; None when not an origin."""
    try:
        parts = urlsplit(origin.strip())
        port = parts.port
    except ValueError:
        return None
    if parts.scheme not in ("http", "https") or not parts.hostname or parts.path not in ("", "/") \
            or parts.query or parts.fragment or parts.username or parts.password:
        return None
    host = parts.hostname.lower().rstrip(".")  # "localhost." is localhost, as in split_host
    if not host:
        return None
    host = f"[{host}]" if ":" in host else host
    shown_port = f":{port}" if port not in (None, _DEFAULT_PORT[parts.scheme]) else ""
    return f"{parts.scheme}://{host}{shown_port}"


class CrossSiteGuard:
    """ASGI middleware enforcing the rules of this module's docstring."""

    def __init__(self, app: Any, *, extra_origins: Iterable[str] = (), allowed_hosts: Iterable[str] = ()
                 ) -> None:
        self.app = app
        self.hosts = normalise_hosts(allowed_hosts)  # the loopback names and the configured ones
        extras = set()
        for o in extra_origins:
            n = normalise_origin(o)
            if n is None:
                raise ValueError(f"not an origin (scheme://host[:port]): {o!r}")
            extras.add(n)
        self.extra_origins = frozenset(extras)

    def origin_allowed(self, origin: str, scope: Scope) -> bool:
        norm = normalise_origin(origin)
        if norm is None:
            return False  # "null", garbage
        if norm in self.extra_origins:
            return True
        parts = urlsplit(norm)
        scheme = scope.get("scheme", "http")
        own_scheme = {"ws": "http", "wss": "https"}.get(scheme, scheme)
        host = split_host(header(scope, b"host") or "")
        if host is None or parts.scheme != own_scheme:
            return False
        own_port = host[1] if host[1] is not None else _DEFAULT_PORT[own_scheme]
        origin_port = parts.port if parts.port is not None else _DEFAULT_PORT[parts.scheme]
        return (parts.hostname or "").lower() in self.hosts and origin_port == own_port

    def refusal(self, scope: Scope) -> str | None:
        """Why the request is refused, or None."""
        origin = header(scope, b"origin")
        if origin is not None and header_count(scope, b"origin") > 1 and (
                scope["type"] == "websocket" or scope.get("method", "GET").upper() in STATE_CHANGING):
            return ("cross-site request refused: more than one Origin header (a browser sends one; "
                    "see docs/security.md)")
        if scope["type"] == "websocket":
            if origin is not None and not self.origin_allowed(origin, scope):
                return "cross-origin WebSocket refused"
            return None
        if scope.get("method", "GET").upper() not in STATE_CHANGING:
            return None
        if origin is not None and not self.origin_allowed(origin, scope):
            return (f"cross-site request refused: Origin {_shown(origin)} is not an allowed origin (the "
                    "daemon's own, or one listed in cors_origins; see docs/security.md)")
        ctype = (header(scope, b"content-type") or "").split(";")[0].strip().lower()
        marked = (header(scope, HEADER.lower().encode()) or "").strip() == "1"
        json_type = ctype == "application/json" or (ctype.startswith("application/")
                                                     and ctype.endswith("+json"))
        if not json_type and not marked:
            return (f"a state-changing request needs Content-Type: application/json or the header "
                    f"{HEADER}: 1 (a web page cannot send either to another site; see docs/security.md)")
        return None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] in ("http", "websocket"):
            why = self.refusal(scope)
            # Route matching (every route's regex) only for a request that would be refused:
            # reads, the bulk of the traffic (live view, polling), never pay for it.
            if why is not None and _reaches_a_handler(scope):
                await refuse(scope, send, 403, why)
                return
        await self.app(scope, receive, send)


def flat_routes(routes: Iterable[Any]) -> Iterator[Any]:
    """The routes of an application, those of included routers one by one (FastAPI keeps
    an included router as one entry)."""
    for route in routes:
        if hasattr(route, "effective_candidates"):
            yield from flat_routes(route.effective_candidates())
        else:
            yield route


def _reaches_a_handler(scope: Scope) -> bool:
    """Whether a route of the application would run for this method and path. Requests that
    reach none (404, 405) change nothing and keep their usual answer."""
    from starlette.routing import Match

    app = scope.get("app")
    routes = getattr(getattr(app, "router", None), "routes", None)
    if routes is None:
        return True  # not inside a Starlette application: check everything
    return any(route.matches(scope)[0] == Match.FULL for route in flat_routes(routes))


def _shown(origin: str) -> str:
    """The origin as quoted in the error: short, printable."""
    from .logsafe import clean_text

    return repr(clean_text(origin, 80))

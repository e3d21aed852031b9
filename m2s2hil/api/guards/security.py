"""Who may talk to the daemon, and how much they may send.

- Listening on a loopback address (127.0.0.0/8, ::1, ``localhost``) is the default and
  needs no token. Any other address needs a bearer token (``[serve] token`` or
  ``M2S2HIL_TOKEN``) of at least :data:`MIN_TOKEN_LENGTH` characters; without one the
  daemon refuses to start (:class:`InsecureListen`).
- When a token is configured every endpoint but ``/healthz`` wants
  ``Authorization: Bearer <token>`` (:func:`m2s2hil.api.common.require_token`); it is
  compared in constant time (:func:`secrets.compare_digest`) so the time to reject says
  nothing about the token.
- The Host allow-list (:mod:`.hosts`) and the cross-site guard (:mod:`.csrf`) stand in
  front of every route.
- :class:`BodyLimit` rejects request bodies above a size with 413, by ``Content-Length``
  before reading and by counting for chunked bodies.
"""

from __future__ import annotations

import ipaddress
import json
import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from m2s2hil.errors import ConfigError

MIN_TOKEN_LENGTH = 16


class InsecureListen(ConfigError):
    """Listening off loopback without a usable token."""


def is_loopback(host: str) -> bool:
    h = host.strip().strip("[]").lower()
    if h in ("localhost", "localhost.", "ip6-localhost"):
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False  # a host name we cannot vouch for: treat as reachable from outside


def check_listen(host: str, token: str | None, source: str = "serve") -> None:
    """Refuse a configuration that would expose the rig without authentication."""
    if is_loopback(host):
        if token is not None and len(token) < MIN_TOKEN_LENGTH:
            raise InsecureListen(source, "token",
                                 f"a bearer token needs at least {MIN_TOKEN_LENGTH} characters")
        return
    if not token:
        raise InsecureListen(
            source, "host",
            f"refusing to listen on {host!r} without a bearer token: anyone who can reach it could "
            f"move the rig. Set M2S2HIL_TOKEN (or token in the [serve] table) to a secret of at least "
            f"{MIN_TOKEN_LENGTH} characters, or listen on 127.0.0.1",
        )
    if len(token) < MIN_TOKEN_LENGTH:
        raise InsecureListen(
            source, "token",
            f"the bearer token is {len(token)} characters; listening on {host!r} needs at least "
            f"{MIN_TOKEN_LENGTH} (e.g. python -c 'import secrets; print(secrets.token_urlsafe(32))')",
        )


def token_matches(given: str, expected: str) -> bool:
    """Constant-time comparison of the UTF-8 bytes (length differences leak only the length)."""
    return secrets.compare_digest(given.encode("utf-8"), expected.encode("utf-8"))


Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[MutableMapping[str, Any]]]
Send = Callable[[MutableMapping[str, Any]], Awaitable[None]]


class BodyLimit:
    """ASGI middleware: request bodies above ``max_bytes`` get 413 with a JSON detail.

    The body (small by construction) is read here before the application sees it, so an
    oversized chunked body is refused before any handler runs."""

    def __init__(self, app: Callable[[Scope, Receive, Send], Awaitable[None]], max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    n = int(value)
                except ValueError:
                    await self._reply(send, 400, "Content-Length is not a number")
                    return
                if n > self.max_bytes:
                    await self._reply(send, 413, f"request body of {n} bytes is above the limit of "
                                                 f"{self.max_bytes} bytes")
                    return
        chunks: list[bytes] = []
        seen = 0
        while True:
            msg = await receive()
            if msg["type"] != "http.request":  # the client went away
                return
            body = msg.get("body", b"")
            seen += len(body)
            if seen > self.max_bytes:
                await self._reply(send, 413, f"request body is above the limit of {self.max_bytes} bytes")
                return
            chunks.append(body)
            if not msg.get("more_body", False):
                break
        replayed = False

        async def replay() -> MutableMapping[str, Any]:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": b"".join(chunks), "more_body": False}
            return await receive()  # e.g. a streaming response waiting for the disconnect

        await self.app(scope, replay, send)

    @staticmethod
    async def _reply(send: Send, status: int, detail: str) -> None:
        body = json.dumps({"detail": detail}).encode()
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode()),
                                (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})

"""The Host allow-list: a defence against DNS rebinding.

A web page on ``attacker.example`` can make its own name resolve to 127.0.0.1; the
browser then treats the daemon as the attacker's own origin and lets the page read and
write it. Such requests still carry ``Host: attacker.example``: the daemon answers only
requests whose Host is a loopback name (``127.0.0.1``, ``localhost``, ``[::1]``, any
port) or a name configured with ``allowed_hosts`` / ``--allowed-host``. Anything else gets
421 Misdirected Request with a JSON body, before any route runs. (The daemon never builds a
URL from the Host header either: ``Location`` and ``url`` fields are relative.)"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

from .security import Receive, Scope, Send

#: Always allowed: the names a browser on this machine uses to reach a loopback daemon.
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


def split_host(value: str) -> tuple[str, int | None] | None:
    """``"name:port"``, ``"[v6]:port"`` or a bare name -> (lower-case name, port or None);
    None when it cannot be a Host header value."""
    value = value.strip()
    if not value or any(c in value for c in " /\\@?#\x00"):
        return None
    port: int | None = None
    if value.startswith("["):
        end = value.find("]")
        if end < 0:
            return None
        name, rest = value[1:end], value[end + 1:]
        if rest:
            if not rest.startswith(":"):
                return None
            port_s = rest[1:]
        else:
            port_s = None
    else:
        name, sep, port_s_ = value.partition(":")
        if ":" in port_s_:
            return None  # an unbracketed IPv6 address is not a Host header
        port_s = port_s_ if sep else None
    if port_s is not None:
        if not port_s.isdigit() or len(port_s) > 5 or int(port_s) > 65535:
            return None
        port = int(port_s)
    name = name.lower().rstrip(".")
    return (name, port) if name else None


def normalise_hosts(names: Iterable[str]) -> frozenset[str]:
    """Configured names (``rig-pc.lab``, ``10.0.0.5``, ``[fd00::5]``) as the middleware compares them."""
    out = set(LOOPBACK_HOSTS)
    for n in names:
        parsed = split_host(n)
        if parsed is None:
            raise ValueError(f"not a host name: {n!r}")
        out.add(parsed[0])
    return frozenset(out)


def header(scope: Scope, name: bytes) -> str | None:
    """The first ``name`` header (lower-case bytes), or None."""
    for k, v in scope.get("headers", []):
        if k == name:
            return v.decode("latin-1")
    return None


def header_count(scope: Scope, name: bytes) -> int:
    """How many ``name`` headers the request has."""
    return sum(1 for k, _ in scope.get("headers", []) if k == name)


class HostAllowList:
    """ASGI middleware: refuse requests (HTTP and WebSocket) whose Host is not allowed."""

    def __init__(self, app: Any, allowed: Iterable[str] = ()) -> None:
        self.app = app
        self.allowed = normalise_hosts(allowed)

    def allows(self, host_header: str | None) -> bool:
        parsed = split_host(host_header) if host_header is not None else None
        return parsed is not None and parsed[0] in self.allowed

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] in ("http", "websocket") and not self.allows(header(scope, b"host")):
            detail = ("the Host header names a host this daemon does not serve (loopback names and "
                      "the names given with --allowed-host; see docs/security.md)")
            await refuse(scope, send, 421, detail)
            return
        await self.app(scope, receive, send)


async def refuse(scope: Scope, send: Send, status: int, detail: str) -> None:
    """Answer with ``{"detail": …}`` (HTTP) or close before accepting (WebSocket: the server
    answers the handshake with 403)."""
    if scope["type"] == "websocket":
        await send({"type": "websocket.close", "code": 1008, "reason": detail[:120]})
        return
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})
